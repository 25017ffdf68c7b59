"""Whole-plot surveys (issue 31 item 5): every station's plot-wide error, time and peak memory of
`treereg register` and of Sylva (the peer tool, `benchmarks/sylva.py`) on the same station files.

For each survey of `simulate.survey.survey_cases()` (or, where that module does not exist yet, a
3-station plot of `simulate.plots.PlotSpec`): simulate it once into a cache folder (float32 PLY,
one per station, and truth.json: reused while the simulator's sources are unchanged), then

- run `python -m treereg_cli register <stations> --out <dir>/transforms.json --keep-unverified`
  as a user would (default parameters; register's own survey flag added when it has one), and
  read each station's verdict from the file's "quality" block and its `T_ref_scan`;
- run Sylva (`sylva coreg <stations> --reference 0`, its defaults) in its own venv;

and print one markdown table per survey, a row per station: treereg's verdict, rotation error
(deg) and plot-wide mean displacement of ALL the station's points (mm), against the simulator's
truth, and Sylva's same two; then the median and the worst over the stations other than the
first (the reference, the identity for both), and each tool's wall time (a ratio to treereg's
time in the same run; seconds below) and peak memory (RSS of the child process and its
descendants, `os.wait4`). The two run one after the other, never side by side.

    python benchmarks/bench_survey.py                     # every survey
    python benchmarks/bench_survey.py --only "3x3 leaf-off"
    python benchmarks/bench_survey.py --small             # the small surveys (tests, quick look)
    python benchmarks/bench_survey.py --plot              # a 3-station plot instead (the fallback)

Sylva is optional: without its venv (TREEREG_SYLVA_PYTHON, default /work/sylva-venv) the Sylva
columns stay empty and one line says how to install it.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import Report, md_table  # noqa: E402
from sylva import NOT_INSTALLED, SylvaRun, run_measured, run_sylva, sylva_available, sylva_version  # noqa: E402

from treereg_core.geometry.rigid import mean_displacement, rotation_error_deg  # noqa: E402
from treereg_core.io.cases import TRUTH_NAME, read_truth  # noqa: E402
from treereg_core.io.scans import read_points  # noqa: E402
from treereg_core.simulate.cases import write_case  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
CACHE = Path("/tmp/treereg_bench_survey")
SIM_SOURCES = ("survey.py", "plots.py", "scanner.py", "tree.py", "cases.py", "wind.py")


@dataclass(frozen=True)
class Survey:
    """A survey to measure: its label and the spec that builds it (`.build()`)."""

    label: str
    spec: Any


@dataclass(frozen=True)
class ToolRun:
    """One tool on one survey: {station: T_first_station} (absent: not placed), verdicts, cost."""

    transforms: dict[str, np.ndarray]
    verdicts: dict[str, str]
    seconds: float
    peak_mb: float
    error: str | None
    command: str


def surveys(small: bool, plot: bool) -> tuple[list[Survey], str]:
    """The surveys of `survey_cases()`, or the fallback 3-station plot; and a line saying which."""
    if not plot:
        try:
            from treereg_core.simulate.survey import survey_cases
        except ImportError:
            note = "treereg_core.simulate.survey is not there yet: a 3-station plot instead"
        else:
            specs = survey_cases(small=small) if small else survey_cases()
            items = specs.items() if isinstance(specs, dict) else ((_label(s), s) for s in specs)
            return ([Survey(str(k), s) for k, s in items],
                    f"`simulate.survey.survey_cases({'small=True' if small else ''})`")
    else:
        note = "a 3-station plot (--plot)"
    from treereg_core.simulate.plots import PlotSpec

    spec = (PlotSpec(seed=0, n_stations=3, angular_step_deg=(0.2, 0.2), plot_radius_m=15.0) if small
            else PlotSpec(seed=0, n_stations=3))
    return [Survey("3-station plot", spec)], note


def _label(spec: Any) -> str:
    label = getattr(spec, "label", None)
    return str(label) if label else repr(spec)


def _spec_key(spec: Any) -> str:
    """A cache key: the spec and the simulator's sources (a changed simulator simulates again)."""
    h = hashlib.sha256()
    to_dict = getattr(spec, "to_dict", None)
    h.update((json.dumps(to_dict(), sort_keys=True, default=str) if callable(to_dict) else repr(spec)).encode())
    h.update(type(spec).__qualname__.encode())
    for name in SIM_SOURCES:
        f = REPO / "treereg_core" / "simulate" / name
        if f.is_file():
            h.update(f.read_bytes())
    return h.hexdigest()[:16]


def case_folder(s: Survey, cache: Path, say) -> tuple[Path, float]:
    """The survey's station files and truth.json, simulated now or found in the cache."""
    folder = cache / f"{re.sub(r'[^A-Za-z0-9]+', '_', s.label).strip('_')[:60]}_{_spec_key(s.spec)}"
    truth = folder / TRUTH_NAME
    if truth.is_file() and all((folder / n).is_file() for n in read_truth(truth)):
        return folder, 0.0
    t0 = time.perf_counter()
    folder.mkdir(parents=True, exist_ok=True)
    # float32 PLY: Sylva 0.3.0 cannot read double PLY (see sylva.py); both tools read these files.
    try:
        from treereg_core.simulate.survey import SurveySpec, write_survey
    except ImportError:
        SurveySpec = write_survey = None
    if write_survey is not None and isinstance(s.spec, SurveySpec):
        write_survey(s.spec, folder, dtype="float32")  # station by station: one scan in memory
    else:
        write_case(s.spec.build(), folder, dtype="float32")
    seconds = time.perf_counter() - t0
    say(f"(simulated {s.label} in {seconds:.0f} s into {folder})")
    return folder, seconds


def _register_flags(one_tree: bool) -> list[str]:
    """register's survey flag when it has one (`--survey`, alone or beside `--one-tree`), or with
    `one_tree` its `--one-tree` (the one-tree mode: the registration before plot-wide surveys)."""
    try:
        text = subprocess.run([sys.executable, "-m", "treereg_cli", "register", "--help"], capture_output=True,
                              text=True, timeout=120, cwd=REPO, env=_env()).stdout
    except (OSError, subprocess.SubprocessError):
        return []
    if one_tree:
        return ["--one-tree"] if re.search(r"\[(--survey \| )?--one-tree", text) else []
    return ["--survey"] if re.search(r"\[--survey(\]| \|)", text) else []


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def run_treereg(files: list[Path], workdir: Path, extra: list[str], timeout_s: float | None) -> ToolRun:
    out = workdir / "transforms.json"
    if out.exists():
        out.unlink()
    cmd = [sys.executable, "-m", "treereg_cli", "register", *map(str, files), "--out", str(out),
           "--keep-unverified", *extra]
    shown = "treereg register <stations> --keep-unverified" + "".join(f" {a}" for a in extra)
    m = run_measured(cmd, workdir / "treereg.log", cwd=workdir, timeout_s=timeout_s, env=_env())
    # register exits 1 when a scan failed, yet writes the file for the rest: the file is the result.
    if m.timed_out or not out.is_file():
        lines = [ln.strip() for ln in m.log.splitlines() if ln.strip()]
        why = "timeout" if m.timed_out else (lines[-1][:300] if lines else f"exit {m.returncode}")
        why = why if why.startswith("treereg") else f"treereg: {why}"
        return ToolRun({}, {f.name: "failed" for f in files}, m.seconds, m.peak_mb, why, shown)
    data = json.loads(out.read_text())
    ref = data.get("reference", files[0].name)
    T = {ref: np.eye(4)} | {n: np.asarray(M, dtype=np.float64) for n, M in data.get("transforms", {}).items()}
    quality = (data.get("quality") or {}).get("scans", {})
    verdicts = {f.name: ("reference" if f.name == ref else quality.get(f.name, {}).get("verdict", "?" if f.name in T else "failed"))
                for f in files}
    return ToolRun(T, verdicts, m.seconds, m.peak_mb, None, shown)


def sylva_tool(files: list[Path], workdir: Path, timeout_s: float | None) -> ToolRun:
    run: SylvaRun = run_sylva(files, workdir, timeout_s=timeout_s)
    verdicts = {n: ("registered" if ok else "not registered") for n, ok in run.registered.items()}
    shown = "sylva --no-progress coreg <stations> --reference 0 -o <dir>"
    return ToolRun(run.transforms, verdicts, run.seconds, run.peak_mb, run.error, shown)


def _fmt(v: float | None, digits: int) -> str:
    return "—" if v is None else f"{v:.{digits}f}"


def errors_of(run: ToolRun, name: str, T_true: np.ndarray, pts: np.ndarray) -> tuple[float | None, float | None]:
    T = run.transforms.get(name)
    if T is None:
        return None, None
    return rotation_error_deg(T, T_true), mean_displacement(T, T_true, pts) * 1000.0


def measure(s: Survey, args, rep: Report, flags: list[str], have_sylva: bool) -> dict[str, Any]:
    """One survey's tables (above); returns treereg's row of the scaling table."""
    full = _label(s.spec)
    rep.say(f"### {s.label}" + (f" ({full})" if full != s.label else ""))
    rep.say()
    folder, _ = case_folder(s, args.cache, rep.say)
    truth = read_truth(folder / TRUTH_NAME)
    names = list(truth)
    files = [folder / n for n in names]
    work = folder / "runs"
    if work.exists():
        shutil.rmtree(work)
    tr = run_treereg(files, work / "treereg", flags, args.timeout)
    sy = sylva_tool(files, work / "sylva", args.timeout) if have_sylva else None
    rows, errs = [], {"tr": [], "sy": []}
    n_points = 0
    for k, n in enumerate(names):
        pts = read_points(folder / n, check_units=False)
        n_points += len(pts)
        tr_e = errors_of(tr, n, truth[n], pts)
        sy_e = errors_of(sy, n, truth[n], pts) if sy is not None else (None, None)
        del pts
        if k > 0:
            errs["tr"].append(tr_e)
            errs["sy"].append(sy_e)
        rows.append([n, tr.verdicts.get(n, "?"), _fmt(tr_e[0], 4), _fmt(tr_e[1], 2),
                     sy.verdicts.get(n, "?") if sy is not None else "—", _fmt(sy_e[0], 4), _fmt(sy_e[1], 2)])

    def summary(vals: list[tuple[float | None, float | None]], i: int, f) -> str:
        got = [v[i] for v in vals if v[i] is not None]
        missing = len(vals) - len(got)
        if not got:
            return "—"
        text = _fmt(float(f(got)), 4 if i == 0 else 2)
        return text + (f" ({missing} not placed)" if missing and f is max else "")

    n_verified = sum(v == "verified" for v in tr.verdicts.values())
    n_sylva = sum(v == "registered" for v in sy.verdicts.values()) - 1 if sy is not None else 0
    for label, f in (("**median**", np.median), ("**worst**", max)):
        rows.append([label, f"{n_verified} of {len(names) - 1} verified" if f is max else "",
                     summary(errs["tr"], 0, f), summary(errs["tr"], 1, f),
                     (f"{n_sylva} of {len(names) - 1} registered" if f is max and sy is not None else ""),
                     summary(errs["sy"], 0, f) if sy is not None else "—",
                     summary(errs["sy"], 1, f) if sy is not None else "—"])
    rep.say(f"{len(names)} stations, {n_points / 1e6:.1f} M points; plot-wide error: mean displacement of all of "
            "a station's points under the tool's pose against the truth's, and the rotation error; "
            "median and worst over the stations but the first (the reference).")
    rep.say()
    rep.say(md_table(["station", "treereg verdict", "treereg rot (deg)", "treereg disp (mm)",
                      "Sylva", "Sylva rot (deg)", "Sylva disp (mm)"], rows))
    rep.say()
    def mb(v: float) -> str:
        return "—" if not np.isfinite(v) else f"{v:.0f}"

    cost = [["treereg", "1.00", mb(tr.peak_mb)]]
    if sy is not None:
        cost.append(["Sylva", f"{sy.seconds / tr.seconds:.2f}" if tr.seconds > 0 else "—", mb(sy.peak_mb)])
    rep.say(md_table(["tool", "wall time (× treereg's)", "peak memory (MB)"], cost))
    rep.say()
    secs = f"treereg {tr.seconds:.1f} s" + (f", Sylva {sy.seconds:.1f} s" if sy is not None else "")
    rep.say(f"Seconds: {secs}. treereg: `{tr.command}`" + (f"; Sylva: `{sy.command}`" if sy is not None else "") + ".")
    for run in (tr, sy):
        if run is not None and run.error:
            rep.say(f"- {run.error}")
    if sy is None and not args.no_sylva:
        rep.say(f"- {NOT_INSTALLED}")
    rep.say()
    tr_disp = [e[1] for e in errs["tr"] if e[1] is not None]
    stages = {}
    if (work / "treereg" / "transforms.json").is_file():
        stages = json.loads((work / "treereg" / "transforms.json").read_text()).get("stage_seconds", {})
    return {"label": s.label, "stations": len(names), "points": n_points, "seconds": tr.seconds, "peak_mb": tr.peak_mb,
            "verified": n_verified, "median": float(np.median(tr_disp)) if tr_disp else None,
            "worst": max(tr_disp) if tr_disp else None, "stages": stages}


#: The scaling table's surveys: 9, 16, 36 and 60 stations.
SCALING = ("3x3 leaf-off", "4x4", "6x6", "10x6")


def scaling_table(rows: list[dict[str, Any]]) -> str:
    """treereg's time and memory against the station count (times as ratios to the first (smallest) survey's)."""
    base = rows[0]["seconds"] or float("nan")
    out = []
    for r in rows:
        st = r["stages"]
        stage_text = ", ".join(f"{k} {v:.1f}" for k, v in st.items() if k != "read") or "—"
        out.append([r["label"], str(r["stations"]), f"{r['points'] / 1e6:.1f}", f"{r['seconds']:.1f}",
                    f"{r['seconds'] / base:.2f}", f"{r['seconds'] / r['stations']:.2f}", f"{r['peak_mb']:.0f}",
                    stage_text, f"{r['verified']} of {r['stations'] - 1}", _fmt(r["median"], 2), _fmt(r["worst"], 2)])
    return md_table(["survey", "stations", "M points", "wall (s)", "wall (× the first row's)", "s a station",
                     "peak RSS (MB)", "stages (s)", "verified", "median (mm)", "worst (mm)"], out)


def main() -> int:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", action="append", metavar="LABEL",
                    help="only the survey whose label is or contains LABEL (repeatable)")
    ap.add_argument("--small", action="store_true", help="the small surveys (a quick look)")
    ap.add_argument("--plot", action="store_true", help="a 3-station plot instead of the surveys")
    ap.add_argument("--cache", type=Path, default=CACHE, help=f"simulated surveys kept here (default {CACHE})")
    ap.add_argument("--one-tree", action="store_true",
                    help="register in the one-tree mode (register --one-tree), as before plot-wide registration")
    ap.add_argument("--timeout", type=float, default=None, help="seconds allowed to each tool on a survey")
    ap.add_argument("--list", action="store_true", help="list the surveys' labels and stop")
    ap.add_argument("--out", type=Path, help="also write the report to this file")
    ap.add_argument("--no-sylva", action="store_true", help="treereg alone")
    ap.add_argument("--scaling", action="store_true",
                    help=f"treereg alone on the surveys of 9, 16, 36 and 60 stations ({', '.join(SCALING)}), then one "
                    "table of its time and peak memory against the station count")
    args = ap.parse_args()
    todo, source = surveys(args.small, args.plot)
    if args.scaling:
        args.only, args.no_sylva = list(SCALING), True
    if args.list:
        for s in todo:
            print(s.label)
        return 0
    if args.only:
        chosen = [s for s in todo if any(o == s.label for o in args.only)]
        todo = chosen or [s for s in todo if any(o.lower() in s.label.lower() for o in args.only)]
        if not todo:
            print(f"no survey matches {args.only}; --list lists them")
            return 2
    rep = Report()
    have_sylva = None if args.no_sylva else sylva_available()
    flags = _register_flags(args.one_tree)
    rep.say(f"Surveys: {source}. treereg at {_git_head()}; "
            + ("Sylva not run (--no-sylva)." if have_sylva is None else
               f"{sylva_version()} (its own venv, defaults)." if have_sylva else NOT_INSTALLED + "."))
    rep.say()
    rows = [measure(s, args, rep, flags, bool(have_sylva)) for s in todo]
    if args.scaling:
        rep.say("### Scaling")
        rep.say()
        rep.say(scaling_table(rows))
        rep.say()
    rep.save(args.out)
    return 0


def _git_head() -> str:
    try:
        r = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=REPO, timeout=30)
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "treereg_core", "treereg_cli"],
                               capture_output=True, text=True, cwd=REPO, timeout=30).stdout.strip()
        return (r.stdout.strip() or "?") + (" with the working tree's uncommitted changes" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "?"


if __name__ == "__main__":
    sys.exit(main())
