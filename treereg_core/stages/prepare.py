"""The prepare stage: each station at the working resolution, its mixed pixels removed, the ground
removed, the target tree found (across all scans at once) and the scan cropped to it."""

from __future__ import annotations

from dataclasses import replace

from ..prepare.ground import PreparedScan, prepare_scans
from ..prepare.mixed import remove_mixed
from ..prepare.resolution import working_resolution
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
    ctx.progress(0.9, "ground, stems and the target tree")
    preps = prepare_scans([m.scan for m in mixed], **ctx.params.pick("prepare", "target"))
    return [replace(p, station=m.scan, mixed_points=w.scan.points[m.mixed], mixed_not_filtered=m.not_filtered,
                    metrics=(w.metrics if w.reduced else ()) + m.metrics + p.metrics)
            for w, m, p in zip(work, mixed, preps)]


STAGE = Stage("prepare", "Scans", "Each station at the working resolution; the ground removed, the target tree found and the scan cropped to it.",
              "scan", ("prepare", "resolution", "target"), (), PreparedScan, run, stop_on_failure=True)
