"""Fine registration benchmark: coarse, fine and ICP side by side, as the paper's Table 2 and more.

Prints markdown tables:
1. the paper's Table 2 layout on two simulated trees like its A and B (3 scans each, 2->1 and
   3->1): the paper's branch-centre error d (eq. 8) of coarse, fine and ICP (from coarse), for the
   robust default and the literal-paper preset, with the errors against the truth beside it;
2. every pair of the seeded simulated set (`simulate.benchmark_cases`, a third awkward): coarse
   (robust), then from that same coarse result: fine (robust), fine (paper preset), ICP; rotation
   error, mean displacement of the target's points, and whether fine ended worse than coarse;
3. a summary per method (success = rotation error < 0.5 deg and displacement < 3 cm);
4. the same from a perturbed truth instead of coarse (fine's own accuracy, independent of coarse);
5. optionally (--ablation) the robust fine with one setting changed at a time;
6. stations simulated from the real trees in ../shared/data/real_trees/;
7. time per stage on 3 scans x ~300k points and the peak memory (tracemalloc) of fine.

Times are ratios to the median coarse time per pair of this same run (= 1.0); its seconds are
printed with the summary. Everything except the perturbed-truth starts and the ablation (the fine
stage alone, by design) runs through the pipeline, as `treereg register` does.

    python benchmarks/bench_fine.py                      # full run (several minutes)
    python benchmarks/bench_fine.py --n 6 --small --real-seeds 1 --no-timing   # quick look
"""

from __future__ import annotations

import sys
import time
import tracemalloc
from dataclasses import dataclass, field, replace

import numpy as np

from common import (  # noqa: E402
    SUMMARY_HEADER, Err, Report, error_of, features_of, md_table, parser, real_tree_cases, run_case, summary_row,
)

from treereg_core.evaluate.icp import align_icp  # noqa: E402
from treereg_core.fine.pose import FINE_SECTIONS, FineSections, register_fine  # noqa: E402
from treereg_core.params import PRESETS, Params  # noqa: E402
from treereg_core.pipeline import Pipeline  # noqa: E402
from treereg_core.simulate.cases import CaseSpec, SimulatedCase, benchmark_cases, coarse_like_error  # noqa: E402

MAX_ROT_DEG = 0.5
MAX_DISP_M = 0.03
METHODS = ("coarse", "fine", "fine (paper)", "ICP")
#: The sections of the paper's fine step (slices, arcs, fits, tie points): "fine (paper)" takes them
#: from the paper preset and everything before from the robust default, so it starts where the
#: robust coarse stage ended (the pipeline re-runs only the stages these sections feed).
PAPER_FINE_SECTIONS = ("slices", "arcs", "sections") + FINE_SECTIONS


@dataclass
class PairRow:
    case: str
    features: str
    points: int
    pair: str
    errs: dict[str, Err] = field(default_factory=dict)

    def worse(self, method: str) -> bool:
        """Ended worse than where it started (coarse), by more than 0.5 mm / 0.01 deg of noise."""
        a, c = self.errs[method], self.errs["coarse"]
        return a.disp_m > c.disp_m + 5e-4 or a.rot_deg > c.rot_deg + 0.01


def paper_fine_params(base: Params) -> Params:
    paper = PRESETS["paper"]
    return replace(base, **{s: getattr(paper, s) for s in PAPER_FINE_SECTIONS})


def case_rows(name: str, features: str, case: SimulatedCase) -> tuple[list[PairRow], list[dict[str, float]]]:
    """`treereg register`'s path (robust) up to the evaluation (with ICP), then the paper's fine step
    from the same coarse result; per pair the errors of each method and the paper's d (eq. 8)."""
    robust = PRESETS["robust"]
    run = run_case(case, robust, "evaluation")
    pipe: Pipeline = run.pipeline
    rows, d = [], []
    coarse_s = run.total(("prepare", "projection", "matching", "coarse")) / (len(case.scans) - 1)
    fine_s = run.total(("slices", "arcs", "sections", "fine")) / (len(case.scans) - 1)
    for k in range(1, len(case.scans)):
        c, f, i, ev = (run.item(s, k) for s in ("coarse", "fine", "icp", "evaluation"))
        errs = {"coarse": error_of(c.T_ref_target, case, k, coarse_s, c.message, c.ok)}
        # A pair whose coarse stage failed has no fine or ICP result: it counts as a failure at its start.
        errs["fine"] = error_of(getattr(f, "T_ref_target", c.T_ref_target), case, k, fine_s, f.message, f.ok)
        errs["ICP"] = error_of(getattr(i, "T_ref_target", c.T_ref_target), case, k,
                               run.seconds.get("icp", 0.0) / (len(case.scans) - 1), i.message, i.ok)
        rows.append(PairRow(name, features, case.scans[k].n_points, f"{k + 1}->1", errs))
        d.append({m: e.mean_distance_m for m, e in ev.by_method().items()} if ev.ok else {})
    paper = run_case(case, paper_fine_params(robust), "fine", pipe=pipe)
    for k, row in zip(range(1, len(case.scans)), rows):
        f = paper.item("fine", k)
        row.errs["fine (paper)"] = error_of(getattr(f, "T_ref_target", run.item("coarse", k).T_ref_target), case, k, paper.total(PAPER_STAGES) / (len(case.scans) - 1), f.message, f.ok)
    return rows, d


PAPER_STAGES = ("slices", "arcs", "sections", "fine")


def fine_alone(case: SimulatedCase, k: int, start: np.ndarray, params: Params) -> tuple[Err, float]:
    """The fine stage's own function from a given start (prepared scans as the pipeline prepares them)."""
    prep = Pipeline(list(case.scans), params)
    prep.run("prepare")
    scans = [it.scan for it in prep.output("prepare").items]
    t0 = time.perf_counter()
    r = register_fine(scans[0], scans[k], start, params=FineSections.of(params))
    dt = time.perf_counter() - t0
    return error_of(r.T_ref_target, case, k, dt, r.message), dt


def icp_alone(case: SimulatedCase, k: int, start: np.ndarray, params: Params) -> Err:
    prep = Pipeline(list(case.scans), params)
    prep.run("prepare")
    scans = [it.scan for it in prep.output("prepare").items]
    t0 = time.perf_counter()
    r = align_icp(scans[0].points, scans[k].points, start, icp=params.icp)
    return error_of(r.T_ref_target, case, k, time.perf_counter() - t0, r.message)


def pair_table(rows: list[PairRow], methods: tuple[str, ...], baseline_s: float) -> str:
    header = ["case", "features", "points", "pair"]
    for m in methods:
        header += [f"{m}: rot (deg)", "disp (m)", "time (x)"]
    out = []
    for r in rows:
        line = [r.case, r.features, r.points, r.pair]
        for m in methods:
            e = r.errs[m]
            mark = "" if e.within(MAX_ROT_DEG, MAX_DISP_M) else " ✗"
            worse = " ↑" if m != "coarse" and r.worse(m) else ""
            line += [f"{e.rot_deg:.3f}{mark}", f"{e.disp_m:.4f}{worse}", f"{e.seconds / baseline_s:.2f}" if e.seconds else "-"]
        out.append(line)
    return md_table(header, out)


def summary_table(rows: list[PairRow], methods: tuple[str, ...], baseline_s: float) -> str:
    out = [summary_row(m, [r.errs[m] for r in rows], MAX_ROT_DEG, MAX_DISP_M, baseline_s,
                       None if m == "coarse" else sum(r.worse(m) for r in rows)) for m in methods]
    return md_table(SUMMARY_HEADER, out)


def failures(rows: list[PairRow], method: str) -> str:
    bad = [r for r in rows if not r.errs[method].within(MAX_ROT_DEG, MAX_DISP_M) or r.worse(method)]
    if not bad:
        return f"No failures of {method}, and no pair ended worse than it started."
    return "\n".join(
        f"- {r.case} {r.pair} ({r.features}): start {r.errs['coarse'].rot_deg:.2f} deg / {r.errs['coarse'].disp_m:.3f} m"
        f" -> {method} {r.errs[method].rot_deg:.2f} deg / {r.errs[method].disp_m:.3f} m. {r.errs[method].note}"
        for r in bad)


def table2(trees: list[tuple[str, SimulatedCase]]) -> str:
    """The paper's Table 2: branch-centre error d (m) of coarse, fine and ICP, both presets, each
    preset's own pipeline from its own coarse stage to the evaluation."""
    out = []
    for name, case in trees:
        for preset in ("robust", "paper"):
            run = run_case(case, PRESETS[preset], "evaluation")
            for k in range(1, len(case.scans)):
                ev = run.item("evaluation", k)
                if not ev.ok:
                    out.append([f"{name} {k + 1}-1", preset, "n/a", "n/a", "n/a", 0, ev.message[:60], "", ""])
                    continue
                evs = ev.by_method()
                cells = [f"{e.mean_distance_m:.3f}" if e.ok else "n/a" for e in evs.values()]
                errs = [f"{e.rotation_error_deg:.2f}° / {e.mean_displacement_m:.3f} m" for e in evs.values()]
                out.append([f"{name} {k + 1}-1", preset, *cells, max(len(e.branches) for e in evs.values()), *errs])
    return md_table(["tree, pair", "preset", "coarse d (m)", "fine d (m)", "ICP d (m)", "branches", "coarse rot / disp",
                     "fine rot / disp", "ICP rot / disp"], out)


def paper_metric_summary(rows: list[dict[str, float]]) -> str:
    """Median of the paper's branch-centre error per method over the set."""
    out = []
    for m in ("coarse", "fine", "ICP"):
        v = np.array([d[m] for d in rows if m in d and np.isfinite(d[m])])
        if len(v):
            out.append([m, len(v), f"{np.median(v):.4f}", f"{v.mean():.4f}"])
    return md_table(["method", "pairs evaluated", "median d (m)", "mean d (m)"], out)


#: One setting of the robust fine changed at a time: (label, section, field, value).
ABLATIONS: tuple[tuple[str, str, str, object], ...] = (
    ("tie points + RANSAC (paper estimator, robust rest)", "fine", "method", "ties"),
    ("no influence check of pairs", "joint", "influence_factor", None),
    ("3 slices at the quartiles", "slices", "quantiles", (0.25, 0.5, 0.75)),
    ("one iteration", "fine", "max_iterations", 1),
    ("no surface refinement of weak directions", "surface", "refine", False),
    ("soft-L1 loss throughout", "joint", "refine_loss", "soft_l1"),
    ("no adaptive gate", "fine", "gate_factor", None),
    ("no radius-ratio gate", "sections", "max_radius_ratio", None),
    ("no range-jump split of arcs", "arcs", "max_range_jump_m", None),
    ("slices 0.2 m thick", "slices", "thickness_m", 0.2),
    ("no acceptance test", "acceptance", "test", False),
    ("surfaces polish all six directions", "surface", "polish", True),
    ("surfaces only (no sections: fallback forced)", "fine", "min_pairs", 1000),
)


def ablation(starts: list[tuple[SimulatedCase, int, np.ndarray]]) -> str:
    """The fine stage alone from the perturbed-truth starts, one setting changed at a time."""
    out = []
    base = PRESETS["robust"]
    for label, section, name, value in (("robust default", "", "", None),) + ABLATIONS:
        params = base if not section else base.with_value(section, name, value)
        res = []
        for case, k, start in starts:
            e, dt = fine_alone(case, k, start, params)
            s0 = error_of(start, case, k)
            worse = e.disp_m > s0.disp_m + 5e-4 or e.rot_deg > s0.rot_deg + 0.01
            res.append((e.within(MAX_ROT_DEG, MAX_DISP_M), e.disp_m, e.rot_deg, worse, dt))
        a = np.array(res, dtype=float)
        out.append([label, len(a), int(a[:, 0].sum()), f"{np.median(a[:, 1]):.4f}", f"{np.quantile(a[:, 1], 0.9):.4f}",
                    f"{a[:, 2].max():.3f}", int(a[:, 3].sum()), f"{np.median(a[:, 4]):.2f}"])
        print(f"  ablation {label} done", file=sys.stderr, flush=True)
    return md_table(["variant", "pairs", "success", "median disp (m)", "p90 disp (m)", "max rot (deg)",
                     "worse than start", "median seconds"], out)


def timing(seed: int, target_points: int = 300_000) -> str:
    """`treereg register`'s stages on 3 scans of ~`target_points` points, and the fine stage's peak memory."""
    case = CaseSpec(seed=seed, height_m=13.0, angular_step_deg=(0.03, 0.03)).build(None)
    n0 = np.mean([s.n_points for s in case.scans])
    step = round(0.03 * float(np.sqrt(n0 / target_points)), 4)
    case = CaseSpec(seed=seed, height_m=13.0, angular_step_deg=(step, step)).build(None)
    run = run_case(case, PRESETS["robust"], "evaluation", truth=False)
    pipe = run.pipeline
    pipe.invalidate("fine")
    tracemalloc.start()
    tracemalloc.reset_peak()
    pipe.run("fine")
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    register = ("prepare", "projection", "matching", "coarse", "slices", "arcs", "sections", "fine")
    rows = [[s, f"{run.seconds[s]:.2f}"] for s in run.seconds if s != "wall"]
    rows.append(["**treereg register (coarse + fine)**", f"**{run.total(register):.2f}**"])
    errs = [error_of(run.item("fine", k).T_ref_target, case, k).disp_m for k in range(1, len(case.scans))]
    pts = ", ".join(str(s.n_points) for s in case.scans)
    return "\n".join([
        f"3 scans of {pts} points (13 m tree, step {step} deg); wall time per stage on this 2-core machine, "
        "shared with other jobs.", "", md_table(["stage", "seconds"], rows), "",
        f"Peak memory allocated while the fine stage ran for both pairs (tracemalloc): {peak / 2**20:.0f} MiB.",
        f"Fine result: mean displacement {', '.join(f'{e * 1000:.1f} mm' for e in errs)}."])


def main(argv: list[str] | None = None) -> int:
    ap = parser(__doc__, real_seeds=2)
    ap.add_argument("--no-table2", action="store_true")
    ap.add_argument("--ablation", action="store_true", help="robust fine with one setting changed at a time")
    a = ap.parse_args(argv)
    report = Report()
    say = report.say

    if not a.no_table2:
        trees = [("A", CaseSpec(seed=a.seed * 1000 + 901, height_m=12.0, orders=3, angular_step_deg=(0.04, 0.04))),
                 ("B", CaseSpec(seed=a.seed * 1000 + 902, height_m=9.0, orders=3, lean_deg=3.0,
                                angular_step_deg=(0.035, 0.035)))]
        say("## Table 2 layout: branch-centre error d (paper eq. 8) on two simulated trees like the paper's A and B")
        say()
        say("Each preset's own pipeline: coarse is its coarse stage; fine and ICP start from it. d is the paper's model "
            "(branches found in the reference, three layers each; target points picked under the truth). "
            "Rotation error / mean displacement against the truth beside it. Paper: fine 0.023-0.030 m.")
        say()
        say(table2([(n, s.build(None)) for n, s in trees]))
        print("  table 2 done", file=sys.stderr, flush=True)

    rows: list[PairRow] = []
    truth_rows: list[PairRow] = []
    metric_rows: list[dict[str, float]] = []
    starts: list[tuple[SimulatedCase, int, np.ndarray]] = []
    robust = PRESETS["robust"]
    for i, spec in enumerate(benchmark_cases(a.n, a.seed, small=a.small)):
        case = spec.build(None)
        name = f"c{i:02d}"
        case_rows_, d = case_rows(name, features_of(spec), case)
        rows += case_rows_
        metric_rows += d
        rng = np.random.default_rng(1000 + i)
        for k in range(1, len(case.scans)):
            start = coarse_like_error(case.T_ref_scan[k], case.scans[k].points, rng)
            starts.append((case, k, start))
            truth_rows.append(PairRow(name, features_of(spec), case.scans[k].n_points, f"{k + 1}->1", {
                "coarse": error_of(start, case, k), "fine": fine_alone(case, k, start, robust)[0],
                "ICP": icp_alone(case, k, start, robust)}))
        print(f"  case {i + 1}/{a.n} done", file=sys.stderr, flush=True)
    baseline = float(np.median([r.errs["coarse"].seconds for r in rows]))
    say()
    say(f"## Fine registration from the robust coarse result: {a.n} simulated cases (seed {a.seed}"
        f"{', small' if a.small else ''})")
    say()
    say("✗ = not within 0.5 deg and 3 cm; ↑ = ended worse than the coarse start.")
    say()
    say(pair_table(rows, METHODS, baseline))
    say()
    say(f"Summary (time 1.0 = the median coarse time per pair, {baseline:.2f} s: prepare, projection, matching "
        "and coarse of a case, divided by its pairs):")
    say()
    say(summary_table(rows, METHODS, baseline))
    say()
    say(failures(rows, "fine"))
    say()
    say("The paper's branch-centre error d (eq. 8) over the same pairs (robust preset's evaluation):")
    say()
    say(paper_metric_summary(metric_rows))
    say()
    say("## Fine from a perturbed truth (2-8 cm, 0.3-1 deg yaw, up to 0.2 deg tilt), same cases")
    say()
    say("The fine stage's own function from a seeded start (not `treereg register`'s path: the start replaces coarse).")
    say()
    say(summary_table(truth_rows, ("coarse", "fine", "ICP"), baseline).replace("| coarse |", "| start |"))
    say()
    say(failures(truth_rows, "fine"))
    if a.ablation:
        say()
        say("## Ablation: robust fine with one setting changed (perturbed-truth starts above)")
        say()
        say(ablation(starts))

    if a.real_seeds > 0:
        real: list[PairRow] = []
        for label, case in real_tree_cases(a.real_seeds, a.real_step):
            real += case_rows(label, "real tree", case)[0]
        say()
        say(f"## Stations simulated from real trees (step {a.real_step} deg, {a.real_seeds} station sets each)")
        say()
        say(pair_table(real, METHODS, baseline))
        say()
        say(summary_table(real, METHODS, baseline))
        say()
        say(failures(real, "fine"))

    if not a.no_timing:
        say()
        say("## Timing: 3 scans x ~300k points (robust default)")
        say()
        say(timing(a.seed))
    report.save(a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
