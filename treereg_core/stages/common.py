"""What several stages' run functions share: a pair's label, each scan as prepared, its station,
surface and range image, where the stems stand, and where fine registration starts."""

from __future__ import annotations

from typing import Literal

import numpy as np

from ..fine.arcs import ArcResult
from ..fine.pose import StemSeeds
from ..fine.sections import PoseFit, ScanSections, fit_at_pose
from ..fine.surface import Surface, scan_surface
from ..prepare.ground import PreparedScan
from ..scan import Scan
from ..stage import Pair, StageContext
from ..verify.hypotheses import HypothesesResult
from ..verify.visibility import RangeImage, scan_range_image


def prepared(ctx: StageContext, i: int) -> PreparedScan:
    return ctx.item("prepare", i, PreparedScan)


def scan_of(ctx: StageContext, i: int) -> Scan:
    """Scan `i` as prepared (ground removed, cropped): what every stage after preparation uses."""
    return prepared(ctx, i).scan


def pair_label(ctx: StageContext, k: int) -> str:
    p = ctx.pairs[k]
    return f"{ctx.scans[p.tgt].name} -> {ctx.scans[p.ref].name}"


def surface(ctx: StageContext, i: int, max_points: int | None = None) -> Surface:
    """Scan i's (prepared) surface at the voxel size of the surfaces section, shared by every stage."""
    scan = scan_of(ctx, i)
    return scan_surface(scan, scan.points, ctx.params.surface.voxel_m, max_points)


def station(ctx: StageContext, i: int) -> Scan:
    """Scan i's whole station at the working resolution (ground and neighbours included): what the
    free-space test compares with."""
    return prepared(ctx, i).station or ctx.scans[i]


def range_image_of(ctx: StageContext, i: int) -> RangeImage:
    """Scan i's station as a range image for the free-space test, blind where its mixed pixels were."""
    return scan_range_image(station(ctx, i), ctx.params.hypotheses.cell_steps, prepared(ctx, i).mixed_points)


def seeds(ctx: StageContext, pair: Pair) -> StemSeeds:
    """Where the prepare stage put each scan's stem (the target's, in a plot): the stem profile
    traces from there, not from a neighbour's."""
    return StemSeeds(ref_xy=prepared(ctx, pair.ref).stem_xy, tgt_xy=prepared(ctx, pair.tgt).stem_xy)


def start_pose(ctx: StageContext, k: int) -> np.ndarray:
    """Where fine registration starts for pair k: the hypothesis the surfaces preferred."""
    return ctx.item("hypotheses", k, HypothesesResult).T_ref_target


def pose_fit(ctx: StageContext, k: int, *, until: Literal["slices", "arcs", "sections"], done: PoseFit | None = None,
             ref_arcs: tuple[ArcResult, ...] | None = None, ref_sections: ScanSections | None = None) -> PoseFit:
    """Pair k sliced, separated and fitted at its start pose (`fine.sections.fit_at_pose`), up to `until`.
    Only the sections of the steps made here are read: the slices stage reads no arcs parameter."""
    p, par = ctx.pairs[k], ctx.params
    steps = ("slices", "arcs", "sections")
    first = "slices" if done is None else "arcs" if done.arcs is None else "sections"
    made = steps[steps.index(first):steps.index(until) + 1]
    return fit_at_pose(scan_of(ctx, p.ref), scan_of(ctx, p.tgt), start_pose(ctx, k),
                       slices=par.slices if "slices" in made else None, arcs=par.arcs if "arcs" in made else None,
                       sections=par.sections if "sections" in made else None, done=done, ref_arcs=ref_arcs,
                       ref_sections=ref_sections, until=until)
