"""The fine stage: the fine transform from the corresponding sections, iterated (re-sliced and
re-fitted at each new pose by `fine.sections.fit_at_pose`) and checked against the surfaces."""

from __future__ import annotations

import numpy as np

from ..fine.arcs import SliceArcs
from ..fine.pose import FINE_SECTIONS, FineResult, FineSections, Grounds, register_fine
from ..fine.sections import PoseFit, SectionsResult
from ..fine.slicing import SliceResult
from ..stage import Stage, StageContext, StageResult
from .common import pair_label, prepared, scan_of, seeds, start_pose


def ground_of(ctx: StageContext, i: int) -> np.ndarray:
    """The points the prepare stage took as scan i's ground (its frame, levelled as its scan)."""
    pr = prepared(ctx, i)
    station = pr.station if pr.station is not None else ctx.scans[i]
    mask = pr.ground_mask
    if mask is None or len(mask) != station.n_points or not mask.any():
        return np.zeros((0, 3))
    ground: np.ndarray = station.points[mask]
    return ground


def run(ctx: StageContext) -> list[StageResult | None]:
    def one(k: int) -> FineResult:
        p = ctx.pairs[k]
        sl = ctx.outputs["slices"].items[k]
        start = (PoseFit(slices=sl, arcs=ctx.ok_item("arcs", k, SliceArcs), sections=ctx.ok_item("sections", k, SectionsResult))
                 if isinstance(sl, SliceResult) else None)
        return register_fine(scan_of(ctx, p.ref), scan_of(ctx, p.tgt), start_pose(ctx, k), start=start,
                             seeds=seeds(ctx, p), grounds=Grounds(ref=ground_of(ctx, p.ref), tgt=ground_of(ctx, p.tgt)),
                             params=FineSections.of(ctx.params))
    return ctx.each(one, lambda k: pair_label(ctx, k))


#: Its own sections of the eight `register_fine` reads (the others are the slices, arcs, sections
#: and hypotheses stages', whose folders in the app show them).
_OWN = ("fine", "joint", "surface", "acceptance")

STAGE = Stage("fine", "Fine", "The fine transform from the corresponding sections, iterated and checked against the surfaces.",
              "pair", _OWN, ("hypotheses",), FineResult, run, uses=("slices", "arcs", "sections"),
              processes=True, borrows=tuple(s for s in FINE_SECTIONS if s not in _OWN))
