"""Density on awkward trees in still air (issue 30, item 4; done when: "every pair within 3 mm, and the
mean displacement at 3 M points per scan <= its value at 300 k").

The awkward seeded trees of `bench_scale.py` (leaves, a bent trunk, ground; `bench_scale.TREES` and
`HELD_OUT`), each re-cast at the angular step that gives ~300 k, 1 M and 3 M points per scan
(`bench_scale.ensure_case`: the same tree, stations and noise streams, only the step finer; cached
in `--cache`, shared with bench_scale). Each case is registered by `treereg_core.pipeline.register`
with the default parameters, the angular step estimated from the files as a user's would be, in a
child process of its own (so that its peak memory is its own). Per pair: the rotation error
and the mean displacement of the target scan's points under the pair's verified transform
(`verify`'s `T_ref_target`, as given) against the simulator's truth, the pair's verdict; per case:
the placement (the joint pose graph: what `register` returns) of every target scan against the
truth, register's wall and CPU time in process (reading the files not included) and their ratios to the
first size's run of the same tree (300 k by default), and the child's peak RSS through reading and
registering (its VmHWM before the errors are computed).

    python benchmarks/bench_density.py                               # 3 trees x 300k, 1M, 3M
    python benchmarks/bench_density.py --trees awkward2 --sizes 3M   # one case (e.g. its runtime first)
    python benchmarks/bench_density.py --trees awkward2 held6 bent_ground awkward leafon_bent leafon_ground \
        bent ground leafon held0 held15 held18 held21 held3 held9 held12 --json rows.json   # RESULTS.md's (27 min)
    python benchmarks/bench_density.py --trees ... --from-json rows.json                  # its tables again
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_scale import HELD_OUT, SIZES, TREES, ensure_case, rss_run  # noqa: E402
from common import Report, features_of, md_table  # noqa: E402

from treereg_core.geometry.rigid import invert, mean_displacement, rotation_error_deg  # noqa: E402
from treereg_core.io.cases import TRUTH_NAME, read_truth  # noqa: E402
from treereg_core.io.scans import read_scan  # noqa: E402
from treereg_core.simulate.cases import benchmark_cases  # noqa: E402

#: The issue's bound: every pair within 3 mm.
BOUND_M = 0.003
DEFAULT_TREES = ["awkward2", "held6", "bent_ground"]
DEFAULT_SIZES = ["300k", "1M", "3M"]


def spec_of(tree: str):
    return benchmark_cases(24, 0)[TREES[tree]] if tree in TREES else benchmark_cases(24, 1)[HELD_OUT[tree]]


def high_water() -> float:
    """This process's peak resident memory in bytes (`VmHWM` of /proc/self/status)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return float(line.split()[1]) * 1024.0
    return float("nan")


def disp(T: np.ndarray, T_true: np.ndarray, points: np.ndarray) -> float:
    """`mean_displacement` in chunks of 1 M points (its copies of 5 M points would set the peak)."""
    return sum(mean_displacement(T, T_true, points[a:a + 1_000_000]) * len(points[a:a + 1_000_000])
               for a in range(0, len(points), 1_000_000)) / len(points)


def one(folder: Path, out: Path) -> None:
    """Register one case folder in this process and write what it measured as JSON to `out`."""
    from treereg_core.pipeline import register

    truth = read_truth(folder / TRUTH_NAME)
    t0 = time.perf_counter()
    scans = [read_scan(folder / name) for name in truth]  # truth.json's order: the reference first
    read_s = time.perf_counter() - t0
    t0, c0 = time.perf_counter(), time.process_time()
    reg = register(scans)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    # The peak through reading and registering, before the errors below (their copies of the points):
    # this process's own high-water mark (VmHWM). Not `ru_maxrss`: Linux carries the forking parent's
    # peak into it across exec, and the parent here has simulated 3 M-point scans.
    peak = high_water()
    pipe = reg.pipeline
    ver = pipe.output("verify")
    pairs = []
    for i, p in enumerate(pipe.pairs):
        a, b = scans[p.ref], scans[p.tgt]
        T_true = invert(truth[a.name]) @ truth[b.name]
        it = ver.items[i] if ver is not None and i < len(ver.items) else None
        T = getattr(it, "T_ref_target", None)
        if T is not None:
            T = pipe._as_given(T, p.ref, p.tgt)  # the stages register levelled scans
        pairs.append({"pair": f"{b.name}->{a.name}", "verdict": getattr(it, "verdict", "failed"),
                      "rot_deg": rotation_error_deg(T, T_true) if T is not None else None,
                      "disp_m": disp(T, T_true, b.points) if T is not None else None,
                      "reason": "; ".join(getattr(it, "reasons", ()))[:160]})
    placed = {}
    verdicts = pipe.verdicts()
    for s in scans[1:]:
        T = reg.transforms.get(s.name)
        placed[s.name] = {"verdict": verdicts.get(s.name, ("failed",))[0],
                          "rot_deg": rotation_error_deg(T, truth[s.name]) if T is not None else None,
                          "disp_m": disp(T, truth[s.name], s.points) if T is not None else None}
    out.write_text(json.dumps({"points": [len(s.points) for s in scans], "read_s": read_s, "wall_s": wall, "register_cpu_s": cpu,
                               "register_rss": peak, "ok": reg.ok, "message": reg.message, "pairs": pairs, "placed": placed}))


def measure(folder: Path) -> dict:
    """`one` in a child process: its result, and the child's wall, CPU and peak RSS."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "one.json"
        wall, rss, status, err, cpu = rss_run([sys.executable, str(Path(__file__).resolve()), "--one", str(folder),
                                               "--json-out", str(out)], cwd=ROOT)
        res = json.loads(out.read_text()) if out.is_file() else {"pairs": [], "placed": {}, "points": []}
    # `rss` (wait4's ru_maxrss) includes this parent's peak, inherited through fork: not reported.
    res.update(child_wall_s=wall, cpu_s=cpu, rss=rss, status=status,
               err=err.strip().splitlines()[-1] if status and err.strip() else "")
    return res


def mm(x: float | None) -> str:
    return "-" if x is None else f"{x * 1000:.2f}"


def deg(x: float | None) -> str:
    return "-" if x is None else f"{x:.4f}"


def pts(n: list[int]) -> str:
    return "/".join(f"{v / 1e6:.2f}M" if v >= 1e6 else f"{v / 1e3:.0f}k" for v in n)


def mean_of(values: list[float | None]) -> float | None:
    return float(np.mean(values)) if values and all(v is not None for v in values) else None


def summary_table(runs: dict[tuple[str, str], dict], trees: list[str], sizes: list[str]) -> str:
    """One row per tree: per size the pairs' mean displacements (mm; over the bound in bold), their
    worst rotation error, register's wall / CPU time against the first size's, the peak RSS; then
    whether every pair is within the bound at every size, and the mean of the pairs at the last size
    against the first's."""
    rows = []
    for tree in trees:
        cells = [tree, features_of(spec_of(tree))]
        base = runs.get((tree, sizes[0]))
        within = True
        for size in sizes:
            r = runs.get((tree, size))
            if r is None or not r["pairs"] or any(p["disp_m"] is None for p in r["pairs"]):
                cells.append("-")
                within = False
                continue
            d = [p["disp_m"] for p in r["pairs"]]
            within &= all(x <= BOUND_M for x in d) and all(p["verdict"] == "verified" for p in r["pairs"])
            ratio = (f"{r['wall_s'] / base['wall_s']:.2f} / {r['register_cpu_s'] / base['register_cpu_s']:.2f}"
                     if base and base is not r else "1.00 / 1.00")
            cells.append(", ".join(f"**{x * 1000:.2f}**" if x > BOUND_M else f"{x * 1000:.2f}" for x in d)
                         + f"; {max(p['rot_deg'] for p in r['pairs']):.3f}°; "
                         + ("all verified" if all(p["verdict"] == "verified" for p in r["pairs"]) else
                            "/".join(p["verdict"] for p in r["pairs"]))
                         + f"; x{ratio}; {r['register_rss'] / 1e9:.2f} GB")
        first, last = runs.get((tree, sizes[0])), runs.get((tree, sizes[-1]))
        m0 = mean_of([p["disp_m"] for p in first["pairs"]]) if first else None
        m1 = mean_of([p["disp_m"] for p in last["pairs"]]) if last else None
        cells.append("yes" if within else "no")
        cells.append("-" if m0 is None or m1 is None else
                     f"{m1 * 1000:.2f} vs {m0 * 1000:.2f}: {'yes' if m1 <= m0 else 'no'}")
        rows.append(cells)
    return md_table(("tree", "what makes it awkward",
                     *(f"{s}: pairs (mm); worst rot; verdicts; wall / CPU vs {sizes[0]}; peak RSS" for s in sizes),
                     f"every pair <= {BOUND_M * 1000:g} mm", f"mean of pairs, {sizes[-1]} <= {sizes[0]}"), rows)


def main() -> None:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trees", nargs="*", default=DEFAULT_TREES, choices=list(TREES) + list(HELD_OUT))
    ap.add_argument("--sizes", nargs="*", default=DEFAULT_SIZES, choices=list(SIZES))
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "treereg_bench_scale")
    ap.add_argument("--out", type=Path, help="also write the report to this file")
    ap.add_argument("--json", type=Path, help="also write every case's measurements here")
    ap.add_argument("--from-json", type=Path, help="print the tables of a run saved with --json (no registering)")
    ap.add_argument("--one", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--json-out", type=Path, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.one:
        one(a.one, a.json_out)
        return
    runs: dict[tuple[str, str], dict] = {}
    if a.from_json:  # the tables again from a run's --json, nothing registered
        saved = json.loads(a.from_json.read_text())
        runs = {(t, s): saved[f"{t} {s}"] for t in a.trees for s in a.sizes if f"{t} {s}" in saved}
    else:
        a.cache.mkdir(parents=True, exist_ok=True)
    for tree in a.trees if not a.from_json else ():
        for size in a.sizes:
            folder = ensure_case(a.cache, tree, size, ".ply")
            r = measure(folder)
            runs[tree, size] = r
            print(f"  {tree} {size}: {pts(r['points'])}, register {r.get('wall_s', float('nan')):.1f} s "
                  f"(child {r['child_wall_s']:.1f} s), {r.get('register_rss', float('nan')) / 1e9:.2f} GB, pairs "
                  f"{', '.join(mm(p['disp_m']) for p in r['pairs'])} mm {r['err']}", file=sys.stderr, flush=True)
    rep = Report()
    for size in a.sizes:
        rep.say(f"\n#### {size} points per scan\n")
        rows = []
        for tree in a.trees:
            r = runs.get((tree, size))
            if r is None:
                continue
            base = runs.get((tree, a.sizes[0]))
            ratio = (f"{r['wall_s'] / base['wall_s']:.2f} / {r['register_cpu_s'] / base['register_cpu_s']:.2f}"
                     if base and "wall_s" in r and "wall_s" in base else "-")
            for j, p in enumerate(r["pairs"]):
                first = j == 0
                rows.append([tree if first else "", features_of(spec_of(tree)) if first else "",
                             pts(r["points"]) if first else "", p["pair"], deg(p["rot_deg"]), mm(p["disp_m"]),
                             p["verdict"] + (f" ({p['reason']})" if p["verdict"] != "verified" and p["reason"] else ""),
                             f"{r['wall_s']:.1f} / {r['register_cpu_s']:.1f}" if first and "wall_s" in r else "",
                             ratio if first else "", f"{r['register_rss'] / 1e9:.2f}" if first else ""])
            if not r["pairs"]:
                rows.append([tree, features_of(spec_of(tree)), pts(r["points"]), "-", "-", "-",
                             f"exit {r['status']}: {r['err']}", "-", "-", "-"])
        rep.say(md_table(("tree", "what makes it awkward", "points per scan", "pair", "rot err (deg)", "mean disp (mm)",
                          "verdict", "register wall / CPU (s)", "wall / CPU vs first size", "peak RSS (GB)"), rows))
    rep.say("\n#### Mean displacement across densities\n")
    rows = []
    for tree in a.trees:
        cells = [tree]
        for size in a.sizes:
            r = runs.get((tree, size))
            if r is None:
                cells.append("-")
                continue
            pair_mean = mean_of([p["disp_m"] for p in r["pairs"]])
            placed = [v["disp_m"] for v in r["placed"].values()]
            cells.append(f"{mm(pair_mean)} (pairs {', '.join(mm(p['disp_m']) for p in r['pairs'])}; "
                         f"placed {', '.join(mm(v) for v in placed)})")
        rows.append(cells)
    rep.say(md_table(("tree", *(f"{s}: mean of pairs (each pair; each placed scan), mm" for s in a.sizes)), rows))
    rep.say("\n#### Per tree: every pair's displacement, the worst rotation, time and memory\n")
    rep.say(summary_table(runs, a.trees, a.sizes))
    rep.save(a.out)
    if a.json:
        a.json.write_text(json.dumps({f"{t} {s}": v for (t, s), v in runs.items()}, indent=1))


if __name__ == "__main__":
    main()
