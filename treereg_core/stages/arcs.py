"""The arcs stage: each slice separated into arcs (the second step of `fine.sections.fit_at_pose`)."""

from __future__ import annotations

from ..fine.arcs import ArcResult, SliceArcs, separate_scan_slices
from ..fine.sections import PoseFit
from ..fine.slicing import SliceResult
from ..stage import Stage, StageContext, StageResult
from .common import pair_label, pose_fit, scan_of


def run(ctx: StageContext) -> list[StageResult | None]:
    shared: dict[int, tuple[ArcResult, ...]] = {}  # a reference's arcs depend on it alone: shared by its pairs

    def one(k: int) -> SliceArcs:
        p, sl = ctx.pairs[k], ctx.item("slices", k, SliceResult)
        if p.ref not in shared:
            shared[p.ref] = separate_scan_slices(scan_of(ctx, p.ref), sl.ref_indices, ctx.params.arcs)
        fit = pose_fit(ctx, k, until="arcs", done=PoseFit(slices=sl), ref_arcs=shared[p.ref])
        assert fit.arcs is not None  # the pair's slices succeeded (a hard dependency): its arcs are made
        return fit.arcs
    return ctx.each(one, lambda k: pair_label(ctx, k))


STAGE = Stage("arcs", "Arcs", "Each slice separated into arcs by angular connectivity (2.2.2).",
              "pair", ("arcs",), ("slices",), SliceArcs, run)
