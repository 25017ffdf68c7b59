"""The hypotheses stage: competing coarse poses polished and scored by the surfaces."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..coarse.estimate import CoarseResult
from ..fine.pose import profile_bend, straightened
from ..fine.surface import surface_of
from ..stage import Stage, StageContext, StageResult
from ..verify.hypotheses import HypothesesResult, pass_through, score_hypotheses
from ..verify.visibility import range_image
from .common import pair_label, prepared, range_image_of, scan_of, seeds, station, surface


def run(ctx: StageContext) -> list[StageResult | None]:
    hp = ctx.params.hypotheses

    def one(k: int) -> HypothesesResult:
        p, c = ctx.pairs[k], ctx.item("coarse", k, CoarseResult)
        if not hp.enabled:
            return pass_through(c.T_ref_target)
        tgt, ref = scan_of(ctx, p.tgt), scan_of(ctx, p.ref)
        image, ref_surf = range_image_of(ctx, p.ref), surface(ctx, p.ref)
        stems = seeds(ctx, p)
        bend = profile_bend(ref, tgt, c.T_ref_target, ctx.params.wind, ctx.params.joint.loss_scale_m, stems)
        adjust = None
        if bend is not None:
            # The crown moved between the stations: every candidate is judged against the reference
            # bent as the target's tree stood (the stems' bend does not depend on the heading).
            ref_station = station(ctx, p.ref)
            h_step, v_step = ref_station.angular_step_deg
            image = range_image(bend.bend(ref_station.points), (hp.cell_steps * h_step, hp.cell_steps * v_step),
                                prepared(ctx, p.ref).mixed_points)
            ref_surf = surface_of(bend.bend(ref.points), ctx.params.surface.voxel_m)

            def adjust(T: np.ndarray) -> np.ndarray:
                return straightened(ref, tgt, T, ctx.params.joint.loss_scale_m, stems)
        found = score_hypotheses(image, ref_surf, surface(ctx, p.tgt, hp.polish_points), tgt.points, c.T_ref_target,
                                 list(c.modes), hypotheses=hp, choose=ctx.choices.get(pair_label(ctx, k)),
                                 axis_xy=_stem_xy(ctx, p.tgt), adjust=adjust, tgt_wide=surface(ctx, p.tgt, hp.wide_points))
        # A pair the user gave a start: its "coarse" candidate is that start, aligned, not RANSAC's.
        return (replace(found, message=found.message.replace("RANSAC's transform", "the start pose the user gave"))
                if c.started_from else found)
    return ctx.each(one, lambda k: pair_label(ctx, k))


def _stem_xy(ctx: StageContext, i: int) -> np.ndarray | None:
    """Scan i's stem at breast height (its frame): the found stem nearest to its points' centroid,
    when within 2 m of it; None when none was found."""
    prep = prepared(ctx, i)
    stems = prep.stems
    if len(stems) == 0:
        return None
    d = np.hypot(*(stems[:, :2] - prep.scan.points[:, :2].mean(axis=0)).T)
    return stems[int(d.argmin()), :2] if d.min() <= 2.0 else None


STAGE = Stage("hypotheses", "Hypotheses", "Competing poses (other headings, other RANSAC modes) polished and scored by the surfaces.",
              "pair", ("hypotheses", "wind"), ("coarse",), HypothesesResult, run,
              # the surfaces' voxel, and the stem profile's loss scale where the crown moved
              borrows=("surface", "joint"))
