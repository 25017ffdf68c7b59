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
printed with the summary.

    python benchmarks/bench_fine.py                      # full run (several minutes)
    python benchmarks/bench_fine.py --n 6 --small --real-seeds 1 --no-timing   # quick look
"""

from __future__ import annotations

import sys
import time
import tracemalloc
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import Report, parser, real_tree_cases  # noqa: E402

from treereg_core.coarse import register_coarse  # noqa: E402
from treereg_core.evaluation import evaluate_pair  # noqa: E402
from treereg_core.fine import register_fine  # noqa: E402
from treereg_core.ground import prepare_scan  # noqa: E402
from treereg_core.icp import icp  # noqa: E402
from treereg_core.params import PRESETS, Params  # noqa: E402
from treereg_core.rigid import mean_displacement, rotation_error_deg  # noqa: E402
from treereg_core.scan import Scan  # noqa: E402
from treereg_core.simulate import CaseSpec, SimulatedCase, benchmark_cases, coarse_like_error  # noqa: E402

MAX_ROT_DEG = 0.5
MAX_DISP_M = 0.03
METHODS = ("coarse", "fine", "fine (paper)", "ICP")


@dataclass
class Err:
    rot_deg: float
    disp_m: float
    seconds: float = 0.0
    note: str = ""

    @property
    def success(self) -> bool:
        return self.rot_deg < MAX_ROT_DEG and self.disp_m < MAX_DISP_M


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


def features_of(spec: CaseSpec) -> str:
    f = [name for name in ("leaves", "bent", "ground") if getattr(spec, name)]
    if spec.tilt_deg:
        f.append(f"tilt {spec.tilt_deg:g}")
    if spec.lean_deg:
        f.append(f"lean {spec.lean_deg:g}")
    return ", ".join(f) or "plain"


def prepared(scans: tuple[Scan, ...], params: Params) -> list[Scan]:
    """The scans as the pipeline hands them to fine registration."""
    return [prepare_scan(s, params.prepare).scan for s in scans]


def run_pair(case: SimulatedCase, k: int, start: np.ndarray | None, methods: tuple[str, ...],
             fine_params: Params | None = None) -> tuple[dict[str, Err], dict[str, np.ndarray]]:
    """Coarse (or the given start), then fine / fine (paper) / ICP from it, with errors and transforms."""
    T_true = case.T_ref_scan[k]
    raw = case.scans[k].points
    errs: dict[str, Err] = {}
    Ts: dict[str, np.ndarray] = {}
    robust, paper = PRESETS["robust"], PRESETS["paper"]
    if start is None:
        t0 = time.perf_counter()
        c = register_coarse(case.scans[0], case.scans[k], robust, n_scans=len(case.scans))
        start = c.T_ref_target
        errs["coarse"] = Err(rotation_error_deg(start, T_true), mean_displacement(start, T_true, raw),
                             time.perf_counter() - t0, "" if c.ok else c.message)
    else:
        errs["coarse"] = Err(rotation_error_deg(start, T_true), mean_displacement(start, T_true, raw))
    Ts["coarse"] = start
    prep_r = prepared(case.scans, robust)
    for m in methods:
        t0 = time.perf_counter()
        if m == "fine":
            r = register_fine(prep_r[0], prep_r[k], start, fine_params or robust)
            T, note = r.T_ref_tgt, r.message
        elif m == "fine (paper)":
            prep_p = prepared(case.scans, paper)
            t0 = time.perf_counter()
            r = register_fine(prep_p[0], prep_p[k], start, paper)
            T, note = r.T_ref_tgt, r.message
        elif m == "ICP":
            r = icp(prep_r[0].points, prep_r[k].points, start, robust.icp)
            T, note = r.T, r.message
        else:
            continue
        errs[m] = Err(rotation_error_deg(T, T_true), mean_displacement(T, T_true, raw), time.perf_counter() - t0, note)
        Ts[m] = T
    return errs, Ts


def pair_table(rows: list[PairRow], methods: tuple[str, ...], baseline_s: float) -> str:
    head = "| case | features | points | pair |"
    sub = "|---|---|---|---|"
    for m in methods:
        head += f" {m}: rot (deg) | disp (m) | time (x) |"
        sub += "---|---|---|"
    lines = [head, sub]
    for r in rows:
        line = f"| {r.case} | {r.features} | {r.points} | {r.pair} |"
        for m in methods:
            e = r.errs[m]
            mark = "" if e.success else " ✗"
            worse = " ↑" if m != "coarse" and r.worse(m) else ""
            t = f"{e.seconds / baseline_s:.2f}" if e.seconds else "-"
            line += f" {e.rot_deg:.3f}{mark} | {e.disp_m:.4f}{worse} | {t} |"
        lines.append(line)
    return "\n".join(lines)


def summary_table(rows: list[PairRow], methods: tuple[str, ...], baseline_s: float) -> str:
    lines = ["| method | pairs | success (<0.5 deg, <3 cm) | median disp (m) | p90 disp (m) | max disp (m) | "
             "median rot (deg) | max rot (deg) | worse than start | median time (x) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for m in methods:
        es = [r.errs[m] for r in rows]
        d = np.array([e.disp_m for e in es])
        a = np.array([e.rot_deg for e in es])
        ok = sum(e.success for e in es)
        worse = "-" if m == "coarse" else str(sum(r.worse(m) for r in rows))
        t = [e.seconds for e in es if e.seconds]
        tt = f"{np.median(t) / baseline_s:.2f}" if t else "-"
        lines.append(f"| {m} | {len(es)} | {ok} ({ok / len(es):.0%}) | {np.median(d):.4f} | {np.quantile(d, 0.9):.4f} | "
                     f"{d.max():.4f} | {np.median(a):.3f} | {a.max():.3f} | {worse} | {tt} |")
    return "\n".join(lines)


def failures(rows: list[PairRow], method: str) -> str:
    bad = [r for r in rows if not r.errs[method].success or r.worse(method)]
    if not bad:
        return f"No failures of {method}, and no pair ended worse than it started."
    return "\n".join(
        f"- {r.case} {r.pair} ({r.features}): start {r.errs['coarse'].rot_deg:.2f} deg / {r.errs['coarse'].disp_m:.3f} m"
        f" -> {method} {r.errs[method].rot_deg:.2f} deg / {r.errs[method].disp_m:.3f} m. {r.errs[method].note}"
        for r in bad)


def table2(trees: list[tuple[str, SimulatedCase]]) -> str:
    """The paper's Table 2: branch-centre error d (m) of coarse, fine and ICP, both presets."""
    lines = ["| tree, pair | preset | coarse d (m) | fine d (m) | ICP d (m) | branches | "
             "coarse rot / disp | fine rot / disp | ICP rot / disp |", "|---|---|---|---|---|---|---|---|---|"]
    for name, case in trees:
        for k in range(1, len(case.scans)):
            T_true = case.T_ref_scan[k]
            for preset in ("robust", "paper"):
                p = PRESETS[preset]
                c = register_coarse(case.scans[0], case.scans[k], p, n_scans=len(case.scans))
                prep = prepared(case.scans, p)
                f = register_fine(prep[0], prep[k], c.T_ref_target, p)
                i = icp(prep[0].points, prep[k].points, c.T_ref_target, p.icp)
                cells, errs, nb = [], [], 0
                for T in (c.T_ref_target, f.T_ref_tgt, i.T):
                    ev = evaluate_pair(prep[0], prep[k], T, p.evaluation, T_true)
                    cells.append(f"{ev.mean_distance_m:.3f}" if ev.ok else "n/a")
                    nb = max(nb, len(ev.branches))
                    errs.append(f"{rotation_error_deg(T, T_true):.2f}° / {mean_displacement(T, T_true, case.scans[k].points):.3f} m")
                lines.append(f"| {name} {k + 1}-1 | {preset} | {' | '.join(cells)} | {nb} | {' | '.join(errs)} |")
    return "\n".join(lines)


def paper_metric_summary(rows: list[tuple[str, dict[str, float]]]) -> str:
    """Median of the paper's branch-centre error per method over the set."""
    lines = ["| method | pairs evaluated | median d (m) | mean d (m) |", "|---|---|---|---|"]
    for m in METHODS:
        v = np.array([d[m] for _, d in rows if m in d and np.isfinite(d[m])])
        if len(v):
            lines.append(f"| {m} | {len(v)} | {np.median(v):.4f} | {v.mean():.4f} |")
    return "\n".join(lines)


#: One setting of the robust fine changed at a time: (label, section, field, value).
ABLATIONS: tuple[tuple[str, str, str, object], ...] = (
    ("tie points + RANSAC (paper estimator, robust rest)", "fine", "method", "ties"),
    ("no influence check of pairs", "fine", "influence_factor", None),
    ("3 slices at the quartiles", "slicing", "quantiles", (0.25, 0.5, 0.75)),
    ("one iteration", "fine", "max_iterations", 1),
    ("no surface refinement of weak directions", "fine", "surface_refine", False),
    ("soft-L1 loss throughout", "fine", "refine_loss", "soft_l1"),
    ("no adaptive gate", "fine", "gate_factor", None),
    ("no radius-ratio gate", "fitting", "max_radius_ratio", None),
    ("no range-jump split of arcs", "arcs", "max_range_jump_m", None),
    ("slices 0.2 m thick", "slicing", "thickness_m", 0.2),
    ("no acceptance test", "fine", "accept_test", False),
    ("surfaces polish all six directions", "fine", "surface_polish", True),
    ("surfaces only (no sections: fallback forced)", "fine", "min_pairs", 1000),
)


def ablation(starts: list[tuple[SimulatedCase, int, np.ndarray]]) -> str:
    lines = ["| variant | pairs | success | median disp (m) | p90 disp (m) | max rot (deg) | worse than start | "
             "median seconds |", "|---|---|---|---|---|---|---|---|"]
    base = PRESETS["robust"]
    for label, section, name, value in (("robust default", "", "", None),) + ABLATIONS:
        params = base if not section else base.with_value(section, name, value)
        res = []
        for case, k, start in starts:
            prep = prepared(case.scans, base)
            t0 = time.perf_counter()
            r = register_fine(prep[0], prep[k], start, params)
            dt = time.perf_counter() - t0
            T_true, raw = case.T_ref_scan[k], case.scans[k].points
            rot, disp = rotation_error_deg(r.T_ref_tgt, T_true), mean_displacement(r.T_ref_tgt, T_true, raw)
            worse = disp > mean_displacement(start, T_true, raw) + 5e-4 or rot > rotation_error_deg(start, T_true) + 0.01
            res.append((rot < MAX_ROT_DEG and disp < MAX_DISP_M, disp, rot, worse, dt))
        a = np.array(res, dtype=float)
        lines.append(f"| {label} | {len(a)} | {int(a[:, 0].sum())} | {np.median(a[:, 1]):.4f} | "
                     f"{np.quantile(a[:, 1], 0.9):.4f} | {a[:, 2].max():.3f} | {int(a[:, 3].sum())} | {np.median(a[:, 4]):.2f} |")
        print(f"  ablation {label} done", file=sys.stderr, flush=True)
    return "\n".join(lines)


def timing(seed: int, target_points: int = 300_000) -> str:
    """Coarse, fine, ICP and evaluation on 3 scans of ~`target_points` points; fine's peak memory."""
    spec = CaseSpec(seed=seed, height_m=13.0, angular_step_deg=(0.03, 0.03))
    n0 = np.mean([s.n_points for s in spec.build(None).scans])
    step = round(0.03 * float(np.sqrt(n0 / target_points)), 4)
    case = CaseSpec(seed=seed, height_m=13.0, angular_step_deg=(step, step)).build(None)
    p = PRESETS["robust"]
    n = len(case.scans)
    t = {"prepare x3": 0.0, "coarse 2->1, 3->1 (incl. its own prepare)": 0.0, "fine 2->1, 3->1": 0.0,
         "ICP 2->1, 3->1": 0.0, "evaluation (paper model) 2->1, 3->1": 0.0}
    t0 = time.perf_counter()
    prep = prepared(case.scans, p)
    t["prepare x3"] = time.perf_counter() - t0
    coarse, fine_T, errs = [], [], []
    for k in range(1, n):
        t0 = time.perf_counter()
        coarse.append(register_coarse(case.scans[0], case.scans[k], p, n_scans=n).T_ref_target)
        t["coarse 2->1, 3->1 (incl. its own prepare)"] += time.perf_counter() - t0
    for k in range(1, n):
        t0 = time.perf_counter()
        f = register_fine(prep[0], prep[k], coarse[k - 1], p)
        t["fine 2->1, 3->1"] += time.perf_counter() - t0
        fine_T.append(f.T_ref_tgt)
        errs.append(mean_displacement(f.T_ref_tgt, case.T_ref_scan[k], case.scans[k].points))
    for k in range(1, n):
        t0 = time.perf_counter()
        icp(prep[0].points, prep[k].points, coarse[k - 1], p.icp)
        t["ICP 2->1, 3->1"] += time.perf_counter() - t0
    for k in range(1, n):
        t0 = time.perf_counter()
        evaluate_pair(prep[0], prep[k], fine_T[k - 1], p.evaluation)
        t["evaluation (paper model) 2->1, 3->1"] += time.perf_counter() - t0
    tracemalloc.start()
    tracemalloc.reset_peak()
    register_fine(prep[0], prep[1], coarse[0], p)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    pts = ", ".join(str(s.n_points) for s in case.scans)
    lines = [f"3 scans of {pts} points (13 m tree, step {step} deg); wall time on this 2-core machine, "
             "shared with other jobs.", "", "| stage | seconds |", "|---|---|"]
    lines += [f"| {k} | {v:.2f} |" for k, v in t.items()]
    lines += [f"| **coarse + fine (register)** | **{t['prepare x3'] + t['coarse 2->1, 3->1 (incl. its own prepare)'] + t['fine 2->1, 3->1']:.2f}** |",
              "", f"Peak memory allocated during one fine registration (tracemalloc): {peak / 2**20:.0f} MiB.",
              f"Fine result: mean displacement {', '.join(f'{e * 1000:.1f} mm' for e in errs)}."]
    return "\n".join(lines)


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
        say("Coarse is each preset's own coarse stage; fine and ICP start from it. d is the paper's model "
            "(branches found in the reference, three layers each; target points picked under the truth). "
            "Rotation error / mean displacement against the truth beside it. Paper: fine 0.023-0.030 m.")
        say()
        say(table2([(n, s.build(None)) for n, s in trees]))
        print("  table 2 done", file=sys.stderr, flush=True)

    rows: list[PairRow] = []
    truth_rows: list[PairRow] = []
    metric_rows: list[tuple[str, dict[str, float]]] = []
    starts: list[tuple[SimulatedCase, int, np.ndarray]] = []
    for i, spec in enumerate(benchmark_cases(a.n, a.seed, small=a.small)):
        case = spec.build(None)
        rng = np.random.default_rng(1000 + i)
        for k in range(1, len(case.scans)):
            name, pts = f"c{i:02d}", case.scans[k].n_points
            errs, Ts = run_pair(case, k, None, METHODS[1:])
            rows.append(PairRow(name, features_of(spec), pts, f"{k + 1}->1", errs))
            p = PRESETS["robust"]
            prep = prepared(case.scans, p)
            d = {}
            for m in ("coarse", "fine", "ICP"):
                ev = evaluate_pair(prep[0], prep[k], Ts[m], p.evaluation, case.T_ref_scan[k])
                d[m] = ev.mean_distance_m if ev.ok else float("nan")
            metric_rows.append((name, d))
            start = coarse_like_error(case.T_ref_scan[k], case.scans[k].points, rng)
            starts.append((case, k, start))
            errs_t, _ = run_pair(case, k, start, ("fine", "ICP"))
            truth_rows.append(PairRow(name, features_of(spec), pts, f"{k + 1}->1", errs_t))
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
    say(f"Summary (time 1.0 = median coarse pair, {baseline:.2f} s, incl. preparing both scans):")
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
            for k in range(1, len(case.scans)):
                errs, _ = run_pair(case, k, None, METHODS[1:])
                real.append(PairRow(label, "real tree", case.scans[k].n_points, f"{k + 1}->1", errs))
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
