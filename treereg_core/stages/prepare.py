"""The prepare stage: each station at the working resolution, its mixed pixels removed, levelled when
its up is not its z (`prepare.level`: `PreparedScan.T_level`), the ground removed, the target tree
found (across all scans at once) and the scan cropped to it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..prepare.ground import PreparedScan, prepare_scans
from ..prepare.level import Levelling, find_levelling, levelled
from ..prepare.mixed import remove_mixed
from ..prepare.resolution import working_resolution
from ..results import Metric
from ..scan import Scan
from ..parallel import SIDE_BY_SIDE_POINTS
from ..stage import Stage, StageContext, StageResult


def run(ctx: StageContext) -> list[StageResult | None]:
    # First each station at the working resolution (prepare/resolution.py); then ground and crops,
    # across scans: the target tree of a plot is chosen from every station's stems at once.
    given = ctx.params.prepare.angular_step_deg

    def station(i: int) -> Scan:
        # The instrument's steps, when given (e.g. typed in the app after loading), over the estimate.
        s = ctx.scans[i]
        return s.with_angular_step(given) if given is not None and tuple(given) != s.angular_step_deg else s

    pp = ctx.params.prepare
    # prepare depends on nothing: every scan is live
    # Large stations one at a time: a reduction's temporaries are the size of its station, and two
    # at once raised the peak memory of three 3 M-point stations by a sixth.
    small = max(s.n_points for s in ctx.scans) <= SIDE_BY_SIDE_POINTS
    work = [w for w in ctx.each(lambda i: working_resolution(station(i), resolution=ctx.params.resolution),
                    lambda i: f"working resolution: {ctx.scans[i].name}", side_by_side=small) if w is not None]
    ctx.progress(0.8, "mixed pixels")
    mixed = [remove_mixed(w.scan, enabled=pp.mixed_pixels, tolerance_m=pp.mixed_tolerance_m, slope=pp.mixed_slope,
                          dense_share=pp.mixed_dense_share, max_share=pp.mixed_max_share)
             for w in work]
    # A scan whose up is not its z is turned about its scanner so that it is (prepare/level.py): every
    # later stage works on levelled scans; the transforms users see are composed back (`as_given`).
    ctx.progress(0.85, "levelling")
    levels = [find_levelling(m.scan.points, m.scan.pose, min_deg=pp.level_min_deg,
                             stem_margin_deg=pp.level_stem_margin_deg)
              if pp.level else Levelling(None, float("nan"), "") for m in mixed]
    stations = [levelled(m.scan, lv.R) if lv.R is not None else m.scan for m, lv in zip(mixed, levels)]
    ctx.progress(0.9, "ground, stems and the target tree")
    target = ctx.params.target
    if levels[0].R is not None and target.tree_at is not None:  # given in the reference's frame as given
        x, y = (float(v) for v in (levels[0].R @ [*target.tree_at, 0.0])[:2])
        target = replace(target, tree_at=(x, y))
    preps = prepare_scans(stations, prepare=pp, target=target)
    return [replace(p, station=st, mixed_points=_turned(w.scan.points[m.mixed], lv.R), mixed_not_filtered=m.not_filtered,
                    T_level=lv.T, metrics=(w.metrics if w.reduced else ()) + m.metrics + _level_metrics(lv) + p.metrics)
            for w, m, p, st, lv in zip(work, mixed, preps, stations, levels)]


def _turned(points: np.ndarray, R: np.ndarray | None) -> np.ndarray:
    return points if R is None else points @ R.T


def _level_metrics(lv: Levelling) -> tuple[Metric, ...]:
    """A levelled scan says by how much and from what (a scan left as given says nothing)."""
    if lv.R is None:
        return ()
    return (Metric(f"levelled (up from its {lv.how})", "deg", round(lv.off_deg, 3)),)


STAGE = Stage("prepare", "Scans", "Each station at the working resolution, levelled when its up is not z; the ground removed, the target tree found and the scan cropped to it.",
              "scan", ("prepare", "resolution", "target"), (), PreparedScan, run, stop_on_failure=True)
