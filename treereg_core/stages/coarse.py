"""The coarse stage: the rigid transform from the tie points, or the start pose a user gave."""

from __future__ import annotations

import numpy as np

from ..coarse.estimate import CoarseResult, estimate_coarse
from ..coarse.matching import MatchResult
from ..coarse.start import START_POINTS, align_start, from_start
from ..geometry.rigid import invert
from ..prepare.level import as_levelled
from ..stage import Stage, StageContext, StageResult
from .common import pair_label, prepared, surface


def run(ctx: StageContext) -> list[StageResult | None]:
    def one(k: int) -> CoarseResult:
        start = given_start(ctx, k)
        if start is not None:
            T0, source = start
            p = ctx.pairs[k]
            # The pipeline runs a started pair even where matching failed for it: no ties then.
            item = ctx.outputs["matching"].items[k]
            match = item if isinstance(item, MatchResult) else None
            ref_stem, tgt_stem = _stem(ctx, p.ref), _stem(ctx, p.tgt)
            T = align_start(surface(ctx, p.ref), surface(ctx, p.tgt, START_POINTS), T0, coarse=ctx.params.coarse,
                            stems=(ref_stem, tgt_stem) if ref_stem is not None and tgt_stem is not None else None,
                            match=match)
            return from_start(match, T, coarse=ctx.params.coarse, source=source, T_start=T0)
        return estimate_coarse(ctx.item("matching", k, MatchResult), coarse=ctx.params.coarse)
    return ctx.each(one, lambda k: pair_label(ctx, k))


#: Breast height above a scan's lowest points, where the prepare stage finds the stems.
BREAST_HEIGHT_M = 1.3


def _stem(ctx: StageContext, i: int) -> np.ndarray | None:
    """Scan i's target stem at breast height (its frame, as the stages see it): where the prepare
    stage put the target, else the stem it found nearest the points' centroid (within 2 m); None
    when it found none."""
    prep = prepared(ctx, i)
    pts = prep.scan.points
    xy: np.ndarray | None = None if prep.stem_xy is None else np.asarray(prep.stem_xy, dtype=float)
    if xy is None and len(prep.stems):
        d = np.hypot(*(prep.stems[:, :2] - pts[:, :2].mean(axis=0)).T)
        xy = prep.stems[int(d.argmin()), :2] if d.min() <= 2.0 else None
    if xy is None:
        return None
    return np.array([float(xy[0]), float(xy[1]), float(np.quantile(pts[:, 2], 0.01)) + BREAST_HEIGHT_M])


def given_start(ctx: StageContext, k: int) -> tuple[np.ndarray, str] | None:
    """Pair k's transform from the start poses the user gave (`ctx.starts`), between the scans as
    the stages see them (scanner frames, levelled), and where it came from; None when the user gave
    none for it. A pair with the reference takes its target's start; a pair of two other scans one
    only when both have a start (the one composed of the two)."""
    p = ctx.pairs[k]
    ref, tgt = ctx.scans[p.ref], ctx.scans[p.tgt]
    s_tgt = ctx.starts.get(tgt.name)
    s_ref = None if p.ref == 0 else ctx.starts.get(ref.name)
    if s_tgt is None or (p.ref != 0 and s_ref is None):
        return None
    return (to_stage_frames(ctx, p.ref, p.tgt, s_tgt.T_ref_scan, None if s_ref is None else s_ref.T_ref_scan),
            s_tgt.source if s_ref is None or s_ref.source == s_tgt.source else f"{s_ref.source} and {s_tgt.source}")


def to_stage_frames(ctx: StageContext, i: int, j: int, U_j: np.ndarray, U_i: np.ndarray | None = None) -> np.ndarray:
    """T_i_j between the scans as the stages see them, from the user's T_0_j (and T_0_i; None when i
    is the reference) between the scans as their files give them (transforms.json's matrices): each
    taken into the scanner frames through the scans' poses (`Scan.pose`, T_user_scan: inv(P_0) @ U @ P_x,
    undoing `io.transforms.user_frame_transforms`), composed (inv(T_0_i) @ T_0_j), then levelled
    (`prepare.level.as_levelled` with each `PreparedScan.T_level`)."""

    def pose(x: int) -> np.ndarray:
        P = ctx.scans[x].pose
        return np.eye(4) if P is None else np.asarray(P, dtype=np.float64)

    def scanner(U: np.ndarray, x: int) -> np.ndarray:  # T_0_x between scanner frames, as given
        out: np.ndarray = invert(pose(0)) @ np.asarray(U, dtype=np.float64) @ pose(x)
        return out

    T = scanner(U_j, j)
    if U_i is not None:
        T = invert(scanner(U_i, i)) @ T
    return as_levelled(T, prepared(ctx, i).T_level, prepared(ctx, j).T_level)


STAGE = Stage("coarse", "Coarse", "The rigid transform that maps the target's tie points onto the reference's (2.1.4), "
              "or the start pose the user gave for the target, aligned by the surfaces.",
              "pair", ("coarse",), ("matching",), CoarseResult, run,
              borrows=("surface",))  # the surfaces' voxel, for aligning a start the user gave
