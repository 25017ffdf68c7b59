"""The sections stage: circles and cylinders fitted to the arcs, corresponding sections paired (the
last step of `fine.sections.fit_at_pose`)."""

from __future__ import annotations

import numpy as np

from ..fine.arcs import SliceArcs
from ..fine.sections import PoseFit, ScanSections, SectionsResult, fit_scan_sections
from ..fine.slicing import SliceResult
from ..stage import Stage, StageContext, StageResult
from .common import pair_label, pose_fit, scan_of


def run(ctx: StageContext) -> list[StageResult | None]:
    shared: dict[int, ScanSections] = {}  # as for arcs: one fit of the reference's sections

    def one(k: int) -> SectionsResult:
        p, sl, ar = ctx.pairs[k], ctx.item("slices", k, SliceResult), ctx.item("arcs", k, SliceArcs)
        if p.ref not in shared:
            shared[p.ref] = fit_scan_sections(scan_of(ctx, p.ref), ar.ref, sl.heights_m, np.eye(4), ctx.params.sections)
        fit = pose_fit(ctx, k, until="sections", done=PoseFit(slices=sl, arcs=ar), ref_sections=shared[p.ref])
        assert fit.sections is not None  # the pair's slices succeeded (a hard dependency): its sections are made
        return fit.sections
    return ctx.each(one, lambda k: pair_label(ctx, k))


STAGE = Stage("sections", "Fits", "Circles and cylinders fitted to the arcs, and corresponding sections paired (2.2.3, 4.2).",
              "pair", ("sections",), ("arcs",), SectionsResult, run, processes=True)
