"""The verify stage: the evidence that each registration is right, and the pair's verdict."""

from __future__ import annotations

import numpy as np

from ..coarse.estimate import CoarseResult
from ..fine.pose import FineResult
from ..fine.surface import surface_of
from ..prepare.ground import stem_position
from ..stage import Stage, StageContext, StageResult
from ..verify.evidence import PairResults, PairScene, PairVerification, assess, gather_evidence, verification
from ..verify.hypotheses import HypothesesResult
from .common import pair_label, prepared, range_image_of, scan_of, station, surface

#: Target surface points the verify stage uses (its residual is a trimmed mean: more change nothing).
SURFACE_SAMPLE = 20_000


def run(ctx: StageContext) -> list[StageResult | None]:
    hp = ctx.params.hypotheses

    def one(k: int) -> PairVerification:
        p, f = ctx.pairs[k], ctx.item("fine", k, FineResult)
        tgt = scan_of(ctx, p.tgt)
        # With wind, the surfaces compared are the target's unbent (as the reference's tree stood).
        tgt_surf = (surface(ctx, p.tgt, SURFACE_SAMPLE) if f.bend is None else
                    surface_of(f.bend.warp(tgt, f.T_ref_target).points, ctx.params.surface.voxel_m, SURFACE_SAMPLE))
        scene = PairScene(ref_image=range_image_of(ctx, p.ref), ref_surface=surface(ctx, p.ref), tgt_surface=tgt_surf,
                          tgt_points=tgt.points, ref_plane=prepared(ctx, p.ref).plane, tgt_plane=prepared(ctx, p.tgt).plane,
                          ref_stem_xy=_ref_stem_xy(ctx, p.ref), ref_station=station(ctx, p.ref).points,
                          tgt_station=station(ctx, p.tgt).points)
        found = PairResults(coarse=ctx.item("coarse", k, CoarseResult), hypotheses=ctx.item("hypotheses", k, HypothesesResult),
                            T_ref_target=f.T_ref_target, bend=f.bend, profile=f.profile, turn_held=f.turn_held,
                            fine_kept=f.accepted)
        e = gather_evidence(scene, found, verify=ctx.params.verify, hypotheses=hp, acceptance=ctx.params.acceptance,
                            wind=ctx.params.wind,
                            support_inlier_m=ctx.params.coarse.final_inlier_m or ctx.params.coarse.inlier_m)
        return verification(f.T_ref_target, e, assess(e, verify=ctx.params.verify, coarse=ctx.params.coarse,
                                                      acceptance=ctx.params.acceptance, target=tgt.name,
                                                      reference=scan_of(ctx, p.ref).name, wind=ctx.params.wind))
    return ctx.each(one, lambda k: pair_label(ctx, k))


def _ref_stem_xy(ctx: StageContext, i: int) -> np.ndarray:
    """Scan i's stem at its base (its own frame): what a turn about the stem turns about (the
    target's, where the prepare stage chose one)."""
    chosen = prepared(ctx, i).stem_xy
    if chosen is not None:
        return np.asarray(chosen, dtype=float)
    pts = scan_of(ctx, i).points
    return stem_position(pts, pts[:, 2] - float(np.quantile(pts[:, 2], 0.001)))


STAGE = Stage("verify", "Verify", "The evidence that each registration is right: support, free space, residual, ambiguity, plausibility.",
              "pair", ("verify",), ("fine",), PairVerification, run,
              borrows=("hypotheses", "acceptance", "wind", "coarse", "surface"))
