"""Coarse registration benchmark: the paper's literal settings against the robust default.

Every case runs through `treereg register`'s path (the pipeline) up to the coarse stage.

Prints markdown tables:
1. every scan pair (2->1, 3->1) of the seeded simulated cases (`simulate.benchmark_cases`):
   rotation error, mean displacement of the target's points, ORB matches, tie points, inliers, for
   both presets side by side, and the time of the case (all its pairs);
2. a summary per preset (success = rotation error < 5 deg and mean displacement < 0.35 m);
3. the same on stations simulated from each real tree in ../shared/data/real_trees/;
4. the wall time of coarse registration of 3 scans of ~300k points, stage by stage.

Times are ratios to the median time per case of the robust default in this same run (= 1.0); the
baseline's seconds are printed with the summary.

    python benchmarks/bench_coarse.py              # 24 cases, real trees, timing
    python benchmarks/bench_coarse.py --n 6 --small --real-seeds 1 --no-timing   # quick look
    python benchmarks/bench_coarse.py --ablation   # + one setting changed at a time
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np

from common import Report, error_of, features_of, md_table, parser, real_tree_cases, run_case  # noqa: E402

from treereg_core.params import PRESETS, Params  # noqa: E402
from treereg_core.simulate.cases import CaseSpec, SimulatedCase, benchmark_cases  # noqa: E402

PRESET_NAMES = ("robust", "paper")
MAX_ROT_DEG = 5.0
MAX_DISP_M = 0.35
#: The stages `treereg register --until coarse` runs.
COARSE_STAGES = ("prepare", "projection", "matching", "coarse")


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
    case_seconds: float
    message: str

    @property
    def success(self) -> bool:
        return self.ok and self.rot_deg < MAX_ROT_DEG and self.disp_m < MAX_DISP_M


def coarse_rows(name: str, features: str, case: SimulatedCase, preset: str, params: Params) -> list[Row]:
    """One row per target scan: the case through the pipeline up to coarse."""
    run = run_case(case, params, "coarse")
    rows = []
    for k in range(1, len(case.scans)):
        out = run.pipeline.output("coarse") or run.pipeline.output("matching")  # where every pair stopped
        c = out.items[k - 1]
        m = run.item("matching", k)
        T = getattr(c, "T_ref_target", np.eye(4))
        e = error_of(T, case, k)
        matches = sum(int(pm.kept.sum()) for pm in getattr(m, "pairs", ()))
        rows.append(Row(name, features, case.scans[k].n_points, f"{k + 1}->1", preset, c.ok, e.rot_deg, e.disp_m,
                        matches, getattr(m, "n_ties", 0), getattr(c, "n_inliers", 0),
                        run.total(COARSE_STAGES), c.message))
    return rows


def run_both(name: str, features: str, case: SimulatedCase) -> list[Row]:
    return [r for p in PRESET_NAMES for r in coarse_rows(name, features, case, p, PRESETS[p])]


def pair_table(rows: list[Row], baseline_s: float) -> str:
    header = ["case", "features", "points", "pair"]
    for p in PRESET_NAMES:
        header += [f"{p}: rot (deg)", "disp (m)", "matches", "ties", "inliers", "case time (x)"]
    by_key: dict[tuple[str, str], dict[str, Row]] = {}
    for r in rows:
        by_key.setdefault((r.case, r.pair), {})[r.preset] = r
    out = []
    for (case, pair), d in by_key.items():
        first = next(iter(d.values()))
        line = [case, first.features, first.points, pair]
        for p in PRESET_NAMES:
            r = d[p]
            line += [f"{r.rot_deg:.2f}{'' if r.success else ' ✗'}", f"{r.disp_m:.3f}", r.matches, r.ties, r.inliers,
                     f"{r.case_seconds / baseline_s:.2f}"]
        out.append(line)
    return md_table(header, out)


def summary_table(rows: list[Row], baseline_s: float) -> str:
    out = []
    for p in PRESET_NAMES:
        rs = [r for r in rows if r.preset == p]
        if not rs:
            continue
        ok = [r for r in rs if r.success]
        med_ok = f"{np.median([r.disp_m for r in ok]):.4f}" if ok else "-"
        out.append([p, len(rs), len(ok), f"{len(ok) / len(rs):.0%}", f"{np.median([r.disp_m for r in rs]):.4f}",
                    f"{np.median([r.rot_deg for r in rs]):.2f}", med_ok,
                    f"{np.median([r.case_seconds for r in rs]) / baseline_s:.2f}"])
    return md_table(["preset", "pairs", "success", "success rate", "median disp (m)", "median rot (deg)",
                     "median disp of successes (m)", "median case time (x)"], out)


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
    lines = ["| variant | pairs | success | median disp (m) | median rot (deg) | median seconds per case |",
             "|---|---|---|---|---|---|"]
    for label, section, name, value in (("robust default", "", "", None),) + ABLATIONS:
        params = base if not section else base.with_value(section, name, value)
        if label.startswith("3 pairs"):
            params = params.with_value("matching", "matches_per_pair", 5)
        rows = [r for name, case in cases for r in coarse_rows(name, "", case, label, params)]
        lines.append(f"| {label} | {len(rows)} | {sum(r.success for r in rows)} | {np.median([r.disp_m for r in rows]):.4f} | "
                     f"{np.median([r.rot_deg for r in rows]):.2f} | {np.median([r.case_seconds for r in rows]):.2f} |")
        print(f"  ablation {label} done", file=sys.stderr, flush=True)
    return "\n".join(lines)


def timing(seed: int, target_points: int = 300_000, repeats: int = 3) -> str:
    """`treereg register --until coarse` on 3 scans of ~`target_points` points each, stage by stage."""
    # Points per scan grow as 1/step^2: scale the step of a 13 m tree to the target count.
    case = CaseSpec(seed=seed, height_m=13.0, angular_step_deg=(0.03, 0.03)).build(None)
    n0 = np.mean([s.n_points for s in case.scans])
    step = round(0.03 * float(np.sqrt(n0 / target_points)), 4)
    case = CaseSpec(seed=seed, height_m=13.0, angular_step_deg=(step, step)).build(None)
    runs = [run_case(case, PRESETS["robust"], "coarse", truth=False) for _ in range(repeats)]
    totals = [r.total(COARSE_STAGES) for r in runs]
    best = runs[int(np.argmin(totals))]
    seqs = best.pipeline.output("projection").items
    errs = [error_of(best.item("coarse", k).T_ref_target, case, k).disp_m for k in range(1, len(case.scans))]
    pts = ", ".join(str(s.n_points) for s in case.scans)
    rows = [["prepare (ground, crop) x3", f"{best.seconds['prepare']:.2f}"],
            [f"image sequences x3 ({len(seqs[0])} images each, largest {max(p.shape for p in seqs[0].projections)} px)",
             f"{best.seconds['projection']:.2f}"],
            ["matching (similarity, ORB, ties), 2->1 and 3->1", f"{best.seconds['matching']:.2f}"],
            ["coarse (RANSAC), 2->1 and 3->1", f"{best.seconds['coarse']:.2f}"],
            ["**total**", f"**{best.total(COARSE_STAGES):.2f}**"]]
    return "\n".join([
        f"3 scans of {pts} points (13 m tree, step {step} deg); {repeats} runs, the fastest shown "
        f"(all totals: {', '.join(f'{t:.2f}' for t in totals)} s).", "", md_table(["stage", "seconds"], rows), "",
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
        rows += run_both(f"c{i:02d}", features_of(spec), case)
        if a.ablation:
            cases.append((f"c{i:02d}", case))
        print(f"  case {i + 1}/{a.n} done", file=sys.stderr, flush=True)
    baseline = float(np.median([r.case_seconds for r in rows if r.preset == "robust"]))
    say(f"## Coarse registration: {a.n} simulated cases (seed {a.seed}{', small' if a.small else ''})")
    say()
    say(pair_table(rows, baseline))
    say()
    say(f"Summary (time 1.0 = median robust case up to coarse, {baseline:.2f} s):")
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
            real += run_both(label, "real tree", case)
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
