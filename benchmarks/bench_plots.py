"""Whole stations of a plot: accuracy, time and memory of `register` on simulated plots and on the
real RIEGL station with simulated companions.

1. Simulated plots (`simulate.plots.plot_cases`): the target tree among 6-10 neighbours 3-8 m away,
   shrubs, a sloping ground, full 360 deg stations of 0.5-2 M points; every other plot real-like
   (millimetre rounding, second returns), every third with leaves. Default parameters: the target
   is the stem the stations surround. Per pair: rotation error and mean displacement against the
   simulator's truth, over the target region (the points the prepare stage kept: the target and
   its surroundings) and over the whole station; whether the right tree was taken; time and peak
   memory of the whole `register` call.
2. The real station (../shared/data/real_trees/rtls_single_scan_scanner_at_origin.xyz.gz) with
   companions: stations simulated from its own points from positions 3-6 m away (nearest point per
   angular cell of the real station's step, range noise, millimetre rounding, a random heading),
   registered onto it. A companion only sees what the real station saw, from elsewhere: a hard,
   one-sided case.

Success = rotation error < 0.5 deg and mean displacement < 3 cm (over the target region).
Times are ratios to the median time per case of this run (printed in seconds below the table).

    python benchmarks/bench_plots.py                  # 12 plots at 0.1 deg (1.4 M points a station)
    python benchmarks/bench_plots.py --n 4 --small    # quick look
"""

from __future__ import annotations

import sys
import time
import tracemalloc
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from treereg_core.geometry.rigid import apply_transform, invert, make_transform, mean_displacement, rotation_error_deg, rotation_z  # noqa: E402
from treereg_core.io.atomic import write_text_atomic  # noqa: E402
from treereg_core.io.scans import read_scans  # noqa: E402
from treereg_core.params import Params  # noqa: E402
from treereg_core.pipeline import register  # noqa: E402
from treereg_core.scan import Scan  # noqa: E402
from treereg_core.simulate.plots import plot_cases, target_in_scan  # noqa: E402
from treereg_core.simulate.scanner import visible_points  # noqa: E402

REAL_STATION = Path(__file__).resolve().parents[2] / "shared" / "data" / "real_trees" / "rtls_single_scan_scanner_at_origin.xyz.gz"
MAX_ROT_DEG = 0.5
MAX_DISP_M = 0.03


@dataclass
class Row:
    case: str
    pair: str
    points: int
    kept: int
    right_tree: str
    ok: bool
    rot_deg: float
    disp_m: float
    disp_all_m: float
    verdict: str
    seconds: float
    peak_mb: float

    @property
    def success(self) -> bool:
        return self.ok and self.rot_deg < MAX_ROT_DEG and self.disp_m < MAX_DISP_M


def measure(label: str, scans: list[Scan], truth: dict[str, np.ndarray], target_xy: list[np.ndarray] | None,
            params: Params) -> list[Row]:
    """Register `scans` once (time, peak memory) and score every pair against `truth`."""
    tracemalloc.start()
    t0 = time.perf_counter()
    reg = register(scans, params)  # through verification and placement, as `treereg register`
    seconds = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    prep = reg.pipeline.output("prepare").items
    verdicts = reg.pipeline.verdicts()
    rows = []
    for k in range(1, len(scans)):
        s = scans[k]
        T, T_true = reg.transforms.get(s.name), truth[s.name]
        kept = prep[k].scan.points if prep[k].ok else s.points
        right = "-"
        if target_xy is not None:
            got = prep[k].stem_xy
            right = "yes" if got is not None and np.hypot(*(np.asarray(got) - target_xy[k])) < 0.5 else "no"
            got0 = prep[0].stem_xy
            if got0 is None or np.hypot(*(np.asarray(got0) - target_xy[0])) >= 0.5:
                right = "no (reference)"
        if T is None:
            rows.append(Row(label, f"{s.name} -> {scans[0].name}", s.n_points, len(kept), right, False,
                            float("nan"), float("nan"), float("nan"), verdicts[s.name][0], seconds, peak))
            continue
        rows.append(Row(label, f"{s.name} -> {scans[0].name}", s.n_points, len(kept), right, True,
                        rotation_error_deg(T, T_true), mean_displacement(T, T_true, kept),
                        mean_displacement(T, T_true, s.points), verdicts[s.name][0], seconds, peak))
    return rows


def companions(n: int, seed: int) -> tuple[list[Scan], dict[str, np.ndarray], list[np.ndarray]]:
    """The real station and `n` companions simulated from its points, 3-6 m away, random headings."""
    real = read_scans(REAL_STATION)[0]
    rng = np.random.default_rng(seed)
    pts = real.points
    scans = [real.with_points(pts, name="real")]
    truth = {"real": np.eye(4)}
    for k in range(n):
        a, d = rng.uniform(0, 2 * np.pi), rng.uniform(3.0, 6.0)
        pos = np.array([d * np.cos(a), d * np.sin(a), rng.uniform(-0.3, 0.3)])
        T_real_comp = make_transform(rotation_z(rng.uniform(0, 360)), pos)
        local = apply_transform(invert(T_real_comp), pts)
        vis, _ = visible_points(local, real.angular_step_deg, rng)
        name = f"companion{k + 1}"
        scans.append(Scan.from_points(np.round(vis, 3), name=name, angular_step_deg=real.angular_step_deg))
        truth[name] = T_real_comp
    return scans, truth, None  # the real scene's target is not known: no right-tree column


def table(report: list[str], rows: list[Row]) -> None:
    base = float(np.median([r.seconds for r in rows])) if rows else 1.0
    report.append("| case | pair | points | target region | right tree | rotation error (deg) | mean displacement, target region (mm) | mean displacement, whole station (mm) | verdict | time (x median) | peak memory (MB) | within 0.5 deg, 3 cm |")
    report.append("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        report.append(f"| {r.case} | {r.pair} | {r.points:,} | {r.kept:,} | {r.right_tree} | {r.rot_deg:.3f} | {r.disp_m * 1000:.1f} | "
                      f"{r.disp_all_m * 1000:.1f} | {r.verdict} | {r.seconds / base:.2f} | {r.peak_mb:.0f} | {'yes' if r.success else 'NO'} |")
    good = [r for r in rows if r.success]
    disp = [r.disp_m for r in rows if r.ok]
    wrong_verified = [r for r in rows if r.verdict == "verified" and not r.success]
    report.append("")
    report.append(f"{len(wrong_verified)} verified but outside {MAX_ROT_DEG} deg and {MAX_DISP_M * 100:.0f} cm; "
                  f"{sum(r.verdict == 'verified' for r in rows)} / {len(rows)} verified.")
    report.append(f"{len(good)} / {len(rows)} pairs within {MAX_ROT_DEG} deg and {MAX_DISP_M * 100:.0f} cm; "
                  f"median mean displacement (target region) {np.median(disp) * 1000 if disp else float('nan'):.1f} mm; "
                  f"median time per case {base:.1f} s (= 1.0), peak memory up to {max(r.peak_mb for r in rows):.0f} MB.")


def main() -> None:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=12, help="simulated plots (default 12)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--small", action="store_true", help="coarser steps, smaller plots (quick look)")
    ap.add_argument("--companions", type=int, default=2, help="simulated companions of the real station (0 = skip)")
    ap.add_argument("--out", type=Path, help="also write the report to this file")
    args = ap.parse_args()

    report: list[str] = []
    params = Params()
    rows: list[Row] = []
    report.append(f"### Simulated plots ({args.n}, seed {args.seed}{', small' if args.small else ''})")
    report.append("")
    for spec in plot_cases(args.n, args.seed, small=args.small):
        t0 = time.perf_counter()
        case = spec.build()
        sim = time.perf_counter() - t0
        targets = [target_in_scan(case, k) for k in range(len(case.scans))]
        r = measure(spec.label, list(case.scans), case.truth(), targets, params)
        rows += r
        print(f"{spec.label}: simulated in {sim:.1f} s; " + "; ".join(
            f"{x.pair}: {x.rot_deg:.3f} deg {x.disp_m * 1000:.1f} mm, tree {x.right_tree}" for x in r), file=sys.stderr, flush=True)
    if rows:
        table(report, rows)
    if args.companions and REAL_STATION.exists():
        report.append("")
        report.append(f"### The real RIEGL station with {args.companions} simulated companions")
        report.append("")
        scans, truth, _ = companions(args.companions, args.seed)
        steps = scans[0].step
        report.append(f"Angular step of the real station: {steps.describe()} (documented: 0.622 x 0.048 deg).")
        report.append("")
        table(report, measure("real station", scans, truth, None, params))
    text = "\n".join(report)
    print(text)
    if args.out:
        write_text_atomic(args.out, text + "\n")


if __name__ == "__main__":
    main()
