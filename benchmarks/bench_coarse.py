"""Coarse registration benchmark: the paper's literal settings against the robust default.

Prints markdown tables:
1. every scan pair (2->1, 3->1) of the seeded simulated cases (`simulate.benchmark_cases`):
   rotation error, mean displacement of the target's points, ORB matches, tie points, inliers and
   time, for both presets side by side;
2. a summary per preset (success = rotation error < 5 deg and mean displacement < 0.35 m);
3. the same on stations simulated from each real tree in ../shared/data/real_trees/;
4. the wall time of coarse registration of 3 scans of ~300k points (prepare, sequences, matching,
   estimates), stage by stage.

Times in the pair tables are ratios to the median time per pair of the robust default in this same
run (= 1.0); the baseline's seconds are printed with the summary.

    python benchmarks/bench_coarse.py              # 24 cases, real trees, timing
    python benchmarks/bench_coarse.py --n 6 --small --real-seeds 1 --no-timing   # quick look
    python benchmarks/bench_coarse.py --ablation   # + one setting changed at a time
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import Report, parser, real_tree_cases  # noqa: E402

from treereg_core.coarse import estimate_coarse, match_sequences, register_coarse  # noqa: E402
from treereg_core.ground import prepare_scan  # noqa: E402
from treereg_core.params import PRESETS  # noqa: E402
from treereg_core.rigid import mean_displacement, rotation_error_deg  # noqa: E402
from treereg_core.sequences import build_sequence  # noqa: E402
from treereg_core.simulate import CaseSpec, SimulatedCase, benchmark_cases  # noqa: E402

PRESET_NAMES = ("robust", "paper")
MAX_ROT_DEG = 5.0
MAX_DISP_M = 0.35


@dataclass
class Row:
    case: str
    features: str
    points: int
    pair: str
    preset: str
    ok: bool
    rot_deg: float
    disp_m: float
    matches: int
    ties: int
    inliers: int
    seconds: float
    message: str

    @property
    def success(self) -> bool:
        return self.ok and self.rot_deg < MAX_ROT_DEG and self.disp_m < MAX_DISP_M


def features_of(spec: CaseSpec) -> str:
    f = [name for name in ("leaves", "bent", "ground") if getattr(spec, name)]
    if spec.tilt_deg:
        f.append(f"tilt {spec.tilt_deg:g}")
    if spec.lean_deg:
        f.append(f"lean {spec.lean_deg:g}")
    return ", ".join(f) or "plain"


def run_case(name: str, features: str, case: SimulatedCase) -> list[Row]:
    rows = []
    n = len(case.scans)
    for k in range(1, n):
        for preset in PRESET_NAMES:
            t0 = time.perf_counter()
            r = register_coarse(case.scans[0], case.scans[k], PRESETS[preset], n_scans=n)
            dt = time.perf_counter() - t0
            T = case.T_ref_scan[k]
            matches = 0
            if r.match is not None:
                matches = sum(int(pm.kept.sum()) for pm in r.match.pairs)
            rows.append(Row(name, features, case.scans[k].n_points, f"{k + 1}->1", preset, r.ok,
                            rotation_error_deg(r.T_ref_target, T),
                            mean_displacement(r.T_ref_target, T, case.scans[k].points),
                            matches, r.n_ties, r.n_inliers, dt, r.message))
    return rows


def pair_table(rows: list[Row], baseline_s: float) -> str:
    head = "| case | features | points | pair |"
    sub = "|---|---|---|---|"
    for p in PRESET_NAMES:
        head += f" {p}: rot (deg) | disp (m) | matches | ties | inliers | time (x) |"
        sub += "---|---|---|---|---|---|"
    lines = [head, sub]
    by_key: dict[tuple[str, str], dict[str, Row]] = {}
    for r in rows:
        by_key.setdefault((r.case, r.pair), {})[r.preset] = r
    for (case, pair), d in by_key.items():
        first = next(iter(d.values()))
        line = f"| {case} | {first.features} | {first.points} | {pair} |"
        for p in PRESET_NAMES:
            r = d[p]
            mark = "" if r.success else " ✗"
            line += (f" {r.rot_deg:.2f}{mark} | {r.disp_m:.3f} | {r.matches} | {r.ties} | {r.inliers} |"
                     f" {r.seconds / baseline_s:.2f} |")
        lines.append(line)
    return "\n".join(lines)


def summary_table(rows: list[Row], baseline_s: float) -> str:
    lines = ["| preset | pairs | success | success rate | median disp (m) | median rot (deg) | "
             "median disp of successes (m) | median time (x) |", "|---|---|---|---|---|---|---|---|"]
    for p in PRESET_NAMES:
        rs = [r for r in rows if r.preset == p]
        if not rs:
            continue
        ok = [r for r in rs if r.success]
        med_ok = f"{np.median([r.disp_m for r in ok]):.4f}" if ok else "-"
        lines.append(
            f"| {p} | {len(rs)} | {len(ok)} | {len(ok) / len(rs):.0%} | "
            f"{np.median([r.disp_m for r in rs]):.4f} | {np.median([r.rot_deg for r in rs]):.2f} | {med_ok} | "
            f"{np.median([r.seconds for r in rs]) / baseline_s:.2f} |")
    return "\n".join(lines)


def failures(rows: list[Row]) -> str:
    bad = [r for r in rows if not r.success and r.preset == "robust"]
    if not bad:
        return "No failures of the robust default."
    return "\n".join(f"- {r.case} {r.pair} ({r.features}): rot {r.rot_deg:.1f} deg, disp {r.disp_m:.2f} m, "
                     f"{r.inliers}/{r.ties} inliers. {r.message}" for r in bad)


#: One setting of the robust default changed at a time: (label, section, field, value).
ABLATIONS: tuple[tuple[str, str, str, object], ...] = (
    ("bare binary image for ORB (no ramp)", "matching", "image_mode", "binary"),
    ("snap keypoints to occupied pixels within 3 px", "matching", "snap_px", 3),
    ("beta check on (4.1)", "matching", "beta_check", True),
    ("3 pairs x 5 matches (paper counts)", "matching", "n_pairs", 3),
    ("similarity: iou", "matching", "similarity", "iou"),
    ("similarity: ncc", "matching", "similarity", "ncc"),
    ("no ground removal", "prepare", "remove_ground", False),
    ("absolute azimuth (no wrap handling)", "projection", "relative_azimuth", False),
    ("plain SVD over all ties", "coarse", "estimator", "svd"),
    ("RANSAC with 6 DOF", "coarse", "dof", 6),
    ("no 6-DOF refit", "coarse", "refit_6dof", False),
    ("no narrowing of the inlier distance", "coarse", "final_inlier_m", None),
)


def ablation(cases: list[tuple[str, SimulatedCase]]) -> str:
    """Summary rows of the robust default with one setting changed at a time."""
    base = PRESETS["robust"]
    lines = ["| variant | pairs | success | median disp (m) | median rot (deg) | median seconds |",
             "|---|---|---|---|---|---|"]
    for label, section, name, value in (("robust default", "", "", None),) + ABLATIONS:
        params = base if not section else base.with_value(section, name, value)
        if label.startswith("3 pairs"):
            params = params.with_value("matching", "matches_per_pair", 5)
        res = []
        for _, case in cases:
            n = len(case.scans)
            for k in range(1, n):
                t0 = time.perf_counter()
                r = register_coarse(case.scans[0], case.scans[k], params, n_scans=n)
                dt = time.perf_counter() - t0
                T = case.T_ref_scan[k]
                rot = rotation_error_deg(r.T_ref_target, T)
                disp = mean_displacement(r.T_ref_target, T, case.scans[k].points)
                res.append((r.ok and rot < MAX_ROT_DEG and disp < MAX_DISP_M, disp, rot, dt))
        arr = np.array(res, dtype=float)
        lines.append(f"| {label} | {len(arr)} | {int(arr[:, 0].sum())} | {np.median(arr[:, 1]):.4f} | "
                     f"{np.median(arr[:, 2]):.2f} | {np.median(arr[:, 3]):.2f} |")
        print(f"  ablation {label} done", file=sys.stderr, flush=True)
    return "\n".join(lines)


def timing(seed: int, target_points: int = 300_000, repeats: int = 3) -> str:
    """Coarse registration of 3 scans (2->1, 3->1) of ~`target_points` points each, stage by stage."""
    # Points per scan grow as 1/step^2: scale the step of a 13 m tree to the target count.
    spec = CaseSpec(seed=seed, height_m=13.0, angular_step_deg=(0.03, 0.03))
    case = spec.build(None)
    n0 = np.mean([s.n_points for s in case.scans])
    step = round(0.03 * float(np.sqrt(n0 / target_points)), 4)
    spec = CaseSpec(seed=seed, height_m=13.0, angular_step_deg=(step, step))
    case = spec.build(None)
    params = PRESETS["robust"]
    runs = []
    for _ in range(repeats):
        t = [time.perf_counter()]
        prep = [prepare_scan(s, params.prepare).scan for s in case.scans]
        t.append(time.perf_counter())
        seqs = [build_sequence(s, params.projection, len(prep)) for s in prep]
        t.append(time.perf_counter())
        res = []
        for k in range(1, len(prep)):
            m = match_sequences(seqs[0], seqs[k], prep[0], prep[k], params.matching)
            res.append(estimate_coarse(m, params.coarse))
        t.append(time.perf_counter())
        runs.append(np.diff(t))
    runs_a = np.array(runs)
    best = runs_a[np.argmin(runs_a.sum(axis=1))]
    errs = [mean_displacement(r.T_ref_target, case.T_ref_scan[k + 1], case.scans[k + 1].points)
            for k, r in enumerate(res)]
    pts = ", ".join(str(s.n_points) for s in case.scans)
    return "\n".join([
        f"3 scans of {pts} points (13 m tree, step {step} deg); {repeats} runs, the fastest shown "
        f"(all totals: {', '.join(f'{s:.2f}' for s in runs_a.sum(axis=1))} s).",
        "",
        "| stage | seconds |", "|---|---|",
        f"| prepare (ground, crop) x3 | {best[0]:.2f} |",
        f"| image sequences x3 ({len(seqs[0])} images each, largest "
        f"{max(p.shape for p in seqs[0].projections)} px) | {best[1]:.2f} |",
        f"| similarity + ORB + ties + RANSAC, 2->1 and 3->1 | {best[2]:.2f} |",
        f"| **total** | **{best.sum():.2f}** |",
        "",
        f"Mean displacement of that run: {', '.join(f'{e:.3f} m' for e in errs)}.",
    ])


def main(argv: list[str] | None = None) -> int:
    ap = parser(__doc__, real_seeds=3)
    ap.add_argument("--ablation", action="store_true",
                    help="also run the robust default with one setting changed at a time")
    a = ap.parse_args(argv)
    report = Report()
    say = report.say

    rows: list[Row] = []
    cases: list[tuple[str, SimulatedCase]] = []
    for i, spec in enumerate(benchmark_cases(a.n, a.seed, small=a.small)):
        case = spec.build(None)
        rows += run_case(f"c{i:02d}", features_of(spec), case)
        if a.ablation:
            cases.append((f"c{i:02d}", case))
        print(f"  case {i + 1}/{a.n} done", file=sys.stderr, flush=True)
    baseline = float(np.median([r.seconds for r in rows if r.preset == "robust"]))
    say(f"## Coarse registration: {a.n} simulated cases (seed {a.seed}{', small' if a.small else ''})")
    say()
    say(pair_table(rows, baseline))
    say()
    say(f"Summary (time 1.0 = median robust pair, {baseline:.2f} s, incl. preparing both scans):")
    say()
    say(summary_table(rows, baseline))
    say()
    say(failures(rows))

    if a.ablation:
        say()
        say("## Ablation: the robust default with one setting changed (same simulated cases)")
        say()
        say(ablation(cases))

    if a.real_seeds > 0:
        real: list[Row] = []
        for label, case in real_tree_cases(a.real_seeds, a.real_step):
            real += run_case(label, "real tree", case)
        say()
        say(f"## Stations simulated from real trees (step {a.real_step} deg, {a.real_seeds} station sets each)")
        say()
        say(pair_table(real, baseline))
        say()
        say(summary_table(real, baseline))
        say()
        say(failures(real))

    if not a.no_timing:
        say()
        say("## Timing: coarse registration of 3 scans x ~300k points (robust default)")
        say()
        say(timing(a.seed))
    report.save(a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
