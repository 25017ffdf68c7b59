"""A start pose the user gave for a scan (`register --initial`, later the app), as the coarse result
of its pairs: aligned by the surfaces from wide pairing gates down to a coarse pose, its tie points
measured against it as against an estimated transform. The stages after it judge it as any pose."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..fine.surface import Surface, align_narrowing, surface_fitness
from ..geometry import robust
from ..geometry.rigid import apply_transform, rotation_angle_deg
from ..params import CoarseParams
from ..results import Metric
from .estimate import CoarseResult, _ransac_settings
from .matching import MatchResult

#: Points of the target's surface the start's alignment uses (finding the basin needs no more).
START_POINTS = 4000
#: Of the poses `align_start` weighs, those whose surface fitness is at least this share of the best
#: one's compete by their tie points; the others are out.
START_FITNESS_SHARE = 0.5


@dataclass(frozen=True, eq=False)
class StartPose:
    """A start pose a user gave for one scan (`register --initial SCAN=FILE`, later the app): it
    replaces the coarse result of the scan's pairs, and everything after runs from it and judges it
    as any other pose.

    T_ref_scan : 4x4 rigid, mapping the scan's points *as its file gives them* onto the reference's
        points as its file gives them (what transforms.json and the CloudCompare matrices hold:
        through `Scan.pose`, of the scans before levelling).
    source : where it came from, for the user to read ("start.txt", "the app").
    reference : the reference the source names (a transforms.json's "reference"), None when it
        names none: a start naming another reference is refused (`Pipeline.start`).
    """

    T_ref_scan: np.ndarray
    source: str
    reference: str | None = None


def tie_start(match: MatchResult | None, T: np.ndarray, *, coarse: CoarseParams) -> np.ndarray | None:
    """The coarse stage's RANSAC (its settings, and its 6-DOF refit) on the tie points `T` puts within
    `coarse.start_ties_m` of their partners: where the ties agree near the start (None when too few
    do). The start steers it: a heading the ties favour elsewhere is out of its reach."""
    if match is None or not match.ok or match.n_ties < coarse.min_ties:
        return None
    src, dst = np.asarray(match.tgt_xyz, dtype=float), np.asarray(match.ref_xyz, dtype=float)
    near = robust.residuals(T, src, dst) < coarse.start_ties_m
    if np.count_nonzero(near) < coarse.min_ties:
        return None
    src, dst = src[near], dst[near]
    fit = robust.ransac(src, dst, _ransac_settings(coarse, coarse.min_ties))
    if fit is None or fit.n_inliers < coarse.min_ties:
        return None
    if coarse.refit_6dof and coarse.dof == 4 and not robust.is_degenerate(src[fit.inliers], 6):
        return robust.fit(src[fit.inliers], dst[fit.inliers], 6)
    return np.asarray(fit.T, dtype=np.float64)


def align_start(ref: Surface, tgt: Surface, T: np.ndarray, *, coarse: CoarseParams,
                stems: tuple[np.ndarray, np.ndarray] | None = None, match: MatchResult | None = None) -> np.ndarray:
    """A start `T` (a person's, degrees and decimetres off) aligned point-to-plane by the surfaces
    (`tgt` a sample of `START_POINTS`), the pairing gate narrowing through `coarse.start_gates_m`
    (`coarse.start_iterations` at each): where a right coarse transform would start the stages after
    it. The start itself when the alignment breaks down (too few pairs within the widest gate).

    `stems`: the target tree's stem in each scan (reference, target: x, y, z at breast height, each in
    its frame). A start turned about another point than the tree (a matrix typed or composed by
    hand) moves the tree by metres, beyond the widest gate: the start shifted so that the stems meet
    (when they are within `coarse.start_snap_m`) is aligned too, and so is the transform RANSAC finds
    on the tie points of `match` the start puts near their partners (`tie_start`). Of these (the
    last two also as they are, unaligned), among those that put at least `START_FITNESS_SHARE` of what
    the best one puts of the target on the reference's surface (within the last gate), the one more
    ties agree with (within `coarse.final_inlier_m`, when at least `coarse.min_ties` do) is kept, else
    the one that puts more of the target on that surface (a pose turned about the stem pairs its
    stem as well as the right one, its few ties tell them apart)."""
    gates = tuple(sorted(coarse.start_gates_m, reverse=True))
    T = np.asarray(T, dtype=np.float64)
    if not gates:
        return T
    starts = [T]
    if stems is not None:
        shift = np.asarray(stems[0], dtype=float) - apply_transform(T, np.asarray(stems[1], dtype=float)[None])[0]
        shift[2] = 0.0
        if 0.0 < np.linalg.norm(shift) <= coarse.start_snap_m:
            S = np.eye(4)
            S[:3, 3] = shift
            starts.append(S @ T)
    from_ties = tie_start(match, T, coarse=coarse)
    if from_ties is not None:
        starts.append(from_ties)

    def aligned(T0: np.ndarray) -> np.ndarray:
        centre = apply_transform(T0, tgt.points).mean(axis=0)
        out = align_narrowing(ref, tgt, T0, centre, np.eye(6), gates[-1], coarse.start_iterations, gates[-1] / 4,
                              gates_m=gates[:-1], gate_iterations=coarse.start_iterations)
        return out if np.isfinite(out).all() else T0

    ties = match is not None and match.ok and match.n_ties > 0
    near = coarse.final_inlier_m or coarse.inlier_m

    def agree(A: np.ndarray) -> int:
        n = int(np.count_nonzero(robust.residuals(A, match.tgt_xyz, match.ref_xyz) < near)) if ties else 0
        return n if n >= coarse.min_ties else 0

    # Each start and its alignment compete (a leafy crown's surfaces can drag a pose the ties put
    # right by a degree): the person's own start only through its alignment.
    found = [aligned(T0) for T0 in starts] + starts[1:]
    if len(found) == 1:
        return found[0]
    score = [(agree(A), surface_fitness(ref, tgt, A, gates[-1], gates[-1] / 2)) for A in found]
    # Ties decide among the poses the surfaces find plausible: a pose the tie points favour that puts
    # a fraction of the target on the reference's surface the best one does (a wrong RANSAC mode near
    # the start, in a leafy plot: 29 ties against 22, an eighth of the surface) is not a rival.
    best = max(f for _, f in score)
    plausible = [k for k in range(len(found)) if score[k][1] >= START_FITNESS_SHARE * best]
    return found[max(plausible, key=lambda k: score[k])]


def from_start(match: MatchResult | None, T: np.ndarray, *, coarse: CoarseParams, source: str,
               T_start: np.ndarray | None = None) -> CoarseResult:
    """The coarse result of a pair whose start the user gave (`T`, between the scans as the stages
    see them; `T_start` the user's own when `T` is it aligned, `align_start`): its tie points measured
    against it as against an estimated transform (their residuals, the inliers within the distance
    RANSAC narrows to, `coarse.final_inlier_m`, and what chance reaches on them), so the verify stage
    judges the tie support the same way. Always ok: the stages after it judge it. `match` None or
    failed: no ties."""
    t0 = time.perf_counter()
    T = np.asarray(T, dtype=np.float64)
    ties = match is not None and match.ok and match.n_ties > 0
    src = match.tgt_xyz if ties else np.zeros((0, 3))
    dst = match.ref_xyz if ties else np.zeros((0, 3))
    res = robust.residuals(T, src, dst)
    inlier_m = coarse.final_inlier_m or coarse.inlier_m
    inl = res < inlier_m
    n, n_in = len(src), int(inl.sum())
    chance = (robust.chance_inliers(src, dst, _ransac_settings(coarse, robust.RansacSettings.min_inliers),
                                    shuffles=coarse.chance_shuffles)
              if ties and coarse.estimator == "ransac" and coarse.chance_shuffles and n >= 3 else -1)
    R = T[:3, :3]
    metrics = (
        Metric("estimator", "", f"the start pose given in {source}"),
        Metric("tie points", "", n),
        Metric("inliers", "", n_in),
        Metric("inlier RMS residual", "m", float(np.sqrt(np.mean(res[inl] ** 2))) if n_in else float("nan")),
        Metric("yaw", "deg", float(np.degrees(np.arctan2(R[1, 0], R[0, 0])))),
        Metric("tilt", "deg", float(np.degrees(np.arccos(np.clip(R[2, 2], -1.0, 1.0))))),
        Metric("rotation angle", "deg", rotation_angle_deg(R)),
    ) + ((Metric("inliers by chance (ties re-paired at random)", "", chance),) if chance >= 0 else ())
    if T_start is not None:  # how far the surfaces moved the person's start
        D = T @ np.linalg.inv(T_start)
        metrics += (Metric("turned from the start pose", "deg", rotation_angle_deg(D[:3, :3])),
                    Metric("scanner moved from the start pose", "m", float(np.linalg.norm(T[:3, 3] - T_start[:3, 3]))))
    return CoarseResult(ok=True, message=f"started from the pose given in {source}, not estimated", metrics=metrics,
                        T_ref_target=T, inliers=inl, inlier_m=inlier_m, residuals_m=res, n_ties=n,
                        n_inliers=n_in, match=match, seconds=time.perf_counter() - t0,
                        modes=((T, n_in),), chance_inliers=chance, started_from=source)
