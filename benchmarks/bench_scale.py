"""Scale benchmark: `treereg register` end to end at real station sizes, and `treereg batch` on many trees.

Prints markdown tables:
1. per tree, size (scans of ~100 k / 300 k / 1 M / 3 M / 10 M points each; the seeded simulated
   trees of `simulate.benchmark_cases` re-cast at finer angular steps, `--trees`: plain, the awkward
   kinds, and held-out awkward trees of another seed), stations (`--stations 3 6`) and workers
   (`--workers 1 0`; 0 = register's default, all cores): the wall time of `python3 -m treereg_cli
   register` run as a subprocess, the peak RSS of that process (and of the children it forked and
   reaped), the accuracy against the simulator's truth (rotation error, mean displacement of each
   target scan's points), and the ratio of the wall time to the *floor*: a fresh Python that imports
   numpy, scipy and OpenCV and reads the files, measured in the same run just before; then each
   run's wall time per stage (transforms.json's `stage_seconds`);
2. (--batch N) `treereg batch` over N small simulated trees with 1 and with 2 workers (and, with
   --dask, on a local Dask cluster), the time ratio, and whether the transforms are identical.

Cases are simulated once and cached (`--cache`, default /tmp/treereg_bench_scale): the 10 M cases
take a minute each to simulate and ~700 MB each on disk.

    python benchmarks/bench_scale.py                                 # everything (~20 minutes)
    python benchmarks/bench_scale.py --sizes 300k 3M --trees awkward # a part
    python benchmarks/bench_scale.py --sizes --batch 20              # batch only
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import Report, parser  # noqa: E402

from treereg_core.geometry.rigid import apply_transform, rotation_error_deg  # noqa: E402
from treereg_core.io.cases import TRUTH_NAME, read_truth  # noqa: E402
from treereg_core.io.scans import read_points  # noqa: E402
from treereg_core.io.transforms import read_transforms  # noqa: E402
from treereg_core.simulate.cases import CaseSpec, benchmark_cases, write_case  # noqa: E402

SIZES = {"100k": 100_000, "300k": 300_000, "1M": 1_000_000, "3M": 3_000_000, "10M": 10_000_000}
#: The trees, as indices into `benchmark_cases(24, 0)`: a plain leaning tree, the first awkward one
#: (leaves and ground), the most awkward one (bent, leaves, ground, tilted instruments), and one each
#: of the other awkward kinds (leaf-on, bent, ground; leaf-on and bent; leaves, ground and tilt).
TREES = {"plain": 1, "awkward": 0, "awkward2": 6, "bent": 3, "ground": 9, "leafon": 12, "bent_ground": 15,
         "leafon_bent": 18, "leafon_ground": 21}
#: Held-out trees: the awkward ones of another seed (`benchmark_cases(24, 1)`), never tuned on.
HELD_OUT = {f"held{k}": k for k in (0, 3, 6, 9, 12, 15, 18, 21)}
#: The floor: what any tool has to pay before registering (start Python, import the numerical
#: stack, read the files). PLY is read as the binary array it is; LAS/LAZ with laspy.
FLOOR = r"""
import sys, numpy, scipy, scipy.spatial, cv2
for f in sys.argv[1:]:
    if f.endswith(".ply"):
        with open(f, "rb") as fh:
            head = b""
            while not head.endswith(b"end_header\n"):
                head += fh.readline()
            n = int(head.split(b"element vertex ")[1].split()[0])
            t = "<f8" if b"property double x" in head else "<f4"
            p = numpy.fromfile(fh, dtype=t, count=3 * n).reshape(n, 3)
    else:
        import laspy
        p = laspy.read(f).xyz
    assert len(p) > 0
"""


def rss_run(cmd: list[str], cwd: Path | None = None, env: dict | None = None) -> tuple[float, float, int, str, float]:
    """Run `cmd`; (wall seconds, peak RSS in bytes of that process, exit status, stderr tail, CPU seconds)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    err = proc.stderr.read() if proc.stderr else b""
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    return (wall, usage.ru_maxrss * 1024.0, proc.returncode, err.decode(errors="replace")[-300:],
            usage.ru_utime + usage.ru_stime)


def case_dir(cache: Path, tree: str, size: str, fmt: str, stations: int = 3) -> Path:
    return cache / f"{tree}_{size}_{fmt.lstrip('.')}" if stations == 3 else cache / f"{tree}_{size}_{stations}st_{fmt.lstrip('.')}"


def scan_files(folder: Path) -> list[Path]:
    names = read_transforms(folder / TRUTH_NAME).names
    return [folder / n for n in names]


def ensure_case(cache: Path, tree: str, size: str, fmt: str, stations: int = 3) -> Path:
    """Simulate the tree at the step that gives ~`size` points per scan (once; cached), from
    `stations` stations (3: the benchmark case's own; more: evenly around the same tree)."""
    out = case_dir(cache, tree, size, fmt, stations)
    if (out / TRUTH_NAME).is_file():
        return out
    spec = benchmark_cases(24, 0)[TREES[tree]] if tree in TREES else benchmark_cases(24, 1)[HELD_OUT[tree]]
    # Points per scan scale as 1 / step^2: calibrate on the case at its own step.
    base = spec.build()
    n0 = float(np.mean([s.n_points for s in base.scans]))
    step = spec.angular_step_deg[0] * float(np.sqrt(n0 / SIZES[size]))
    spec = CaseSpec(**{**spec.to_dict(), "angular_step_deg": (round(step, 5), round(step, 5)),
                       **({"n_stations": stations} if stations != 3 else {})})
    print(f"  simulating {tree} at {size} points per scan (step {step:.4f} deg)", file=sys.stderr, flush=True)
    case = spec.build()
    tmp = Path(tempfile.mkdtemp(dir=cache))
    write_case(case, tmp)
    if fmt != ".ply":
        # Same points, written as LAS/LAZ; truth.json names the files.
        from treereg_core.io.scans import write_scan
        from treereg_core.io.transforms import TransformFile, write_transforms
        tf = read_transforms(tmp / TRUTH_NAME)
        names = {n: Path(n).with_suffix(fmt).name for n in tf.names}
        for s in case.scans:
            write_scan(tmp / names[s.name], s.points)
            (tmp / s.name).unlink()
        write_transforms(tmp / TRUTH_NAME, TransformFile(names[tf.reference], {names[k]: v for k, v in tf.transforms.items()},
                                                         tf.params, tf.software, tf.extra))
    tmp.rename(out)
    return out


@dataclass
class Row:
    tree: str
    size: str
    stations: int
    workers: str
    points: list[int]
    floor_s: float
    floor_cpu_s: float
    wall_s: float
    cpu_s: float
    rss: float
    status: int
    rot_deg: list[float]
    disp_m: list[float]
    note: str
    stage_s: dict[str, float]

    @property
    def ratio(self) -> float:
        return self.wall_s / self.floor_s

    @property
    def cpu_ratio(self) -> float:
        return self.cpu_s / self.floor_cpu_s


def accuracy(files: list[Path], transforms_json: Path, truth: dict[str, np.ndarray]) -> tuple[list[float], list[float], list[int]]:
    """Rotation error and mean displacement of each target scan's points against the truth."""
    tf = read_transforms(transforms_json)
    rot, disp, npts = [], [], []
    for f in files:
        pts = read_points(f)
        npts.append(len(pts))
        if f.name == tf.reference:
            continue
        if f.name not in tf.transforms:
            rot.append(float("nan"))
            disp.append(float("nan"))
            continue
        T, T_true = np.asarray(tf.matrix(f.name)), truth[f.name]
        rot.append(rotation_error_deg(T, T_true))
        # Chunks: the difference of two transformed copies of 10 M points is 500 MB otherwise.
        s = 0.0
        for a in range(0, len(pts), 1_000_000):
            p = pts[a:a + 1_000_000]
            s += float(np.linalg.norm(apply_transform(T, p) - apply_transform(T_true, p), axis=1).sum())
        disp.append(s / len(pts))
    return rot, disp, npts


def floor_time(files: list[Path], repeats: int) -> tuple[float, float]:
    """Median wall and CPU time of the floor (a fresh Python importing numpy, scipy, cv2 and reading the files)."""
    times, cpus = [], []
    for _ in range(repeats):
        wall, _, status, err, cpu = rss_run([sys.executable, "-c", FLOOR, *map(str, files)])
        if status:
            raise RuntimeError(f"floor failed: {err}")
        times.append(wall)
        cpus.append(cpu)
    return statistics.median(times), statistics.median(cpus)


def measure(tree: str, size: str, folder: Path, repeats: int, floor_repeats: int, extra: list[str],
            root: Path = ROOT, workers: int | None = None) -> Row:
    files = scan_files(folder)
    truth = read_truth(folder / TRUTH_NAME)
    # Reference first, as truth.json lists them.
    floor, floor_cpu = floor_time(files, floor_repeats)
    walls, cpus, rss, status, err, stages = [], [], 0.0, 0, "", []
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "transforms.json"
        for _ in range(repeats):
            w, r, status, err, c = rss_run([sys.executable, "-m", "treereg_cli", "register", *map(str, files),
                                            "--out", str(out), *extra,
                                            *(["--workers", str(workers)] if workers else [])], cwd=root)
            walls.append(w)
            cpus.append(c)
            rss = max(rss, r)
            if out.is_file():
                stages.append(json.loads(out.read_text()).get("stage_seconds", {}))
        if out.is_file():
            rot, disp, npts = accuracy(files, out, truth)
        else:
            rot, disp, npts = [], [], [0]
    note = "" if status == 0 else f"exit {status}: {err.strip().splitlines()[-1] if err.strip() else ''}"
    stage_s = {k: statistics.median(st.get(k, 0.0) for st in stages) for k in (stages[0] if stages else {})}
    return Row(tree, size, len(files), str(workers or "all"), npts, floor, floor_cpu, statistics.median(walls),
               statistics.median(cpus), rss, status, rot, disp, note, stage_s)


def fmt_list(v: list[float], scale: float, digits: int) -> str:
    return ", ".join(f"{x * scale:.{digits}f}" for x in v) if v else "-"


def scale_table(rep: Report, rows: list[Row]) -> None:
    rep.say("| tree | stations | workers | points per scan | floor wall (s) | register wall (s) | wall ratio | floor CPU (s) "
            "| register CPU (s) | CPU ratio | peak RSS (GB) | rot err (deg) | mean disp (mm) | note |")
    rep.say("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        pts = "/".join(f"{n / 1e6:.2f}M" if n >= 1e6 else f"{n / 1e3:.0f}k" for n in r.points)
        if len(r.points) > 3:  # six stations: the range
            lo, hi = min(r.points), max(r.points)
            pts = " to ".join(f"{n / 1e6:.2f}M" if n >= 1e6 else f"{n / 1e3:.0f}k" for n in (lo, hi))
        rep.say(f"| {r.tree} | {r.stations} | {r.workers} | {pts} | {r.floor_s:.2f} | {r.wall_s:.1f} | {r.ratio:.1f} | "
                f"{r.floor_cpu_s:.2f} | {r.cpu_s:.1f} | {r.cpu_ratio:.1f} | {r.rss / 1e9:.2f} | "
                f"{fmt_list(r.rot_deg, 1, 3)} | {fmt_list(r.disp_m, 1000, 1)} | {r.note} |")


def stage_table(rep: Report, rows: list[Row]) -> None:
    """Wall seconds per stage of each run (from transforms.json's stage_seconds)."""
    names = list(dict.fromkeys(k for r in rows for k in r.stage_s))
    if not names:
        return
    rep.say("\nWall time per stage (s, `stage_seconds` of transforms.json; read = reading the files):\n")
    rep.say("| tree | stations | workers | points | " + " | ".join(names) + " |")
    rep.say("|---|---|---|---|" + "---|" * len(names))
    for r in rows:
        rep.say(f"| {r.tree} | {r.stations} | {r.workers} | {r.size} | " + " | ".join(
            f"{r.stage_s[k]:.2f}" if k in r.stage_s else "-" for k in names) + " |")


# ---- batch -------------------------------------------------------------------------------------
def batch_cases(cache: Path, n: int) -> Path:
    """A folder of `n` tree folders (small simulated cases), made once."""
    root = cache / f"batch_{n}"
    if (root / ".complete").is_file():
        return root
    root.mkdir(parents=True, exist_ok=True)
    for k, spec in enumerate(benchmark_cases(n, 1, small=True)):
        d = root / f"tree{k + 1:02d}"
        if not (d / TRUTH_NAME).is_file():
            write_case(spec.build(), d)
    (root / ".complete").write_text("")
    return root


def batch_run(root: Path, out: Path, workers: int | None, dask: str | None = None) -> tuple[float, int, str]:
    cmd = [sys.executable, "-m", "treereg_cli", "batch", str(root), "--out", str(out), "--redo"]
    cmd += ["--dask", dask] if dask else ["--workers", str(workers)]
    wall, _, status, err, _ = rss_run(cmd, cwd=ROOT)
    return wall, status, err


def batch_transforms(out: Path) -> dict[str, dict[str, list]]:
    found = {}
    for f in sorted(out.glob("*/transforms.json")):
        found[f.parent.name] = {k: np.asarray(v).tolist() for k, v in read_transforms(f).transforms.items()}
    return found


def batch_section(rep: Report, cache: Path, n: int, dask: bool) -> None:
    root = batch_cases(cache, n)
    rep.say(f"\n### `treereg batch` on {n} trees (small simulated cases, 3 scans of ~10-30 k points each)\n")
    rows = []
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for label, workers in (("1 worker (serial)", 1), ("2 workers", 2)):
            out = Path(tmp) / f"w{workers}"
            wall, status, err = batch_run(root, out, workers)
            rows.append((label, wall, status, err))
            results[label] = batch_transforms(out)
        if dask:
            cluster_py = ("from dask.distributed import LocalCluster; import time, sys; "
                          "c = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None); "
                          "print(c.scheduler_address, flush=True); time.sleep(3600)")
            # The cluster's workers import this checkout's treereg (a real cluster runs the same install).
            env = {**os.environ, "PYTHONPATH": str(ROOT)}
            proc = subprocess.Popen([sys.executable, "-c", cluster_py], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                    text=True, env=env)
            try:
                addr = proc.stdout.readline().strip()
                out = Path(tmp) / "dask"
                wall, status, err = batch_run(root, out, None, dask=addr)
                rows.append(("Dask LocalCluster, 2 workers", wall, status, err))
                results["dask"] = batch_transforms(out)
            finally:
                proc.terminate()
                proc.wait()
    serial = rows[0][1]
    rep.say("| run | wall (s) | ratio to serial | exit | trees with transforms |")
    rep.say("|---|---|---|---|---|")
    for (label, wall, status, err), res in zip(rows, results.values()):
        rep.say(f"| {label} | {wall:.1f} | {wall / serial:.2f} | {status} | {len(res)} |")
    base = results["1 worker (serial)"]
    for label, res in results.items():
        if label != "1 worker (serial)":
            same = res == base
            rep.say(f"\n{label}: transforms {'identical to' if same else 'DIFFERENT from'} the serial run's.")


def main() -> None:
    ap = parser(__doc__, 0)
    ap.add_argument("--sizes", nargs="*", default=list(SIZES), choices=list(SIZES))
    ap.add_argument("--trees", nargs="*", default=["plain", "awkward"], choices=list(TREES) + list(HELD_OUT))
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "treereg_bench_scale")
    ap.add_argument("--format", default=".ply", choices=(".ply", ".las", ".laz"), help="scan file format")
    ap.add_argument("--repeats", type=int, default=1, help="register runs per case (median wall, max RSS)")
    ap.add_argument("--floor-repeats", type=int, default=3)
    ap.add_argument("--angular-step", action="store_true", help="give register the true angular step (else estimated)")
    ap.add_argument("--stations", nargs="*", type=int, default=[3], help="stations per tree (e.g. 3 6)")
    ap.add_argument("--workers", nargs="*", type=int, default=[0],
                    help="register's --workers, one row each (0 = its default: all cores)")
    ap.add_argument("--root", type=Path, default=ROOT,
                    help="the treereg checkout whose `python3 -m treereg_cli` is timed (e.g. an export of an older commit)")
    ap.add_argument("--batch", type=int, default=0, metavar="N", help="also time `treereg batch` on N trees")
    ap.add_argument("--dask", action="store_true", help="with --batch: also on a local Dask cluster")
    args = ap.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    rep = Report()
    if args.sizes:
        rep.say(f"### `treereg register` end to end, 3 scans per tree ({args.format} files"
                f"{', true angular step given' if args.angular_step else ', angular step estimated'})\n")
        rows = []
        for size in args.sizes:
            for tree in args.trees:
                for stations in args.stations:
                    folder = ensure_case(args.cache, tree, size, args.format, stations)
                    extra = []
                    if args.angular_step:
                        step = json.loads((folder / TRUTH_NAME).read_text())["angular_step_deg"]
                        extra = ["--angular-step", *map(str, step)]
                    for workers in args.workers:
                        row = measure(tree, size, folder, args.repeats, args.floor_repeats, extra, args.root,
                                      workers or None)
                        rows.append(row)
                        print(f"  {tree} {size} {stations} stations, workers {row.workers}: {row.wall_s:.1f} s, "
                              f"x{row.ratio:.1f} (CPU x{row.cpu_ratio:.1f}), {row.rss / 1e9:.2f} GB, "
                              f"disp {fmt_list(row.disp_m, 1000, 1)} mm {row.note}", file=sys.stderr, flush=True)
        scale_table(rep, rows)
        stage_table(rep, rows)
        rep.say("\nfloor = a fresh `python3` importing numpy, scipy and cv2 and reading the three files (median of "
                f"{args.floor_repeats}); register = `python3 -m treereg_cli register` as a subprocess; "
                "peak RSS of that process (`wait4`); CPU = user + system time of each process, less disturbed than "
                "wall time by other work on the machine. Displacement: mean over each target scan's points of the "
                "distance between its estimated and true placement.")
    if args.batch:
        batch_section(rep, args.cache, args.batch, args.dask)
    rep.save(args.out)


if __name__ == "__main__":
    main()
