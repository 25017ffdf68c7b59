"""The coarse rigid transform from tie points (paper 2.1.4), and the checks that refuse a wrong one.

Plain SVD over all ties (the paper) or RANSAC with 4 DOF (yaw + translation, levelled scanners)
and an optional 6-DOF refit on the inliers.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..geometry import robust
from ..geometry.rigid import rotation_angle_deg
from ..params import CoarseParams
from ..results import Metric
from .matching import MatchResult

@dataclass(frozen=True, eq=False)
class CoarseResult:
    """The coarse transform of a target onto the reference.

    Attributes
    ----------
    ok, message, metrics : as every stage result.
    T_ref_target : 4x4 mapping target points into the reference frame (identity when not ok).
    inliers : (N,) bool per tie point: agrees with the transform within the inlier distance.
    residuals_m : (N,) |T tgt - ref| per tie point, metres (NaN when no transform).
    n_ties, n_inliers : counts.
    match : the MatchResult the transform came from.
    seconds : wall time of the estimate.
    modes : (T, inliers) of RANSAC's distinct solutions, best first (the first is `T_ref_target`);
        empty for plain SVD. Competing headings of a round crown show up here.
    chance_inliers : the most ties RANSAC makes agree when the pairing is shuffled (what chance
        reaches on these ties; -1 when not measured).
    """

    ok: bool
    message: str
    metrics: tuple[Metric, ...]
    T_ref_target: np.ndarray
    inliers: np.ndarray
    residuals_m: np.ndarray
    n_ties: int
    n_inliers: int
    match: MatchResult | None = None
    seconds: float = 0.0
    modes: tuple[tuple[np.ndarray, int], ...] = ()
    chance_inliers: int = -1


def _coarse_fail(message: str, match: MatchResult, metrics: tuple[Metric, ...], t0: float) -> CoarseResult:
    n = match.n_ties
    return CoarseResult(False, message, metrics, np.eye(4), np.zeros(n, dtype=bool), np.full(n, np.nan),
                        n, 0, match, time.perf_counter() - t0)


def estimate_coarse(match: MatchResult, *, coarse: CoarseParams) -> CoarseResult:
    """The coarse rigid transform from a MatchResult's tie points.

    `estimator="svd"` (paper): one least-squares fit over all ties (6 DOF, or 4 with `dof=4`).
    `estimator="ransac"`: RANSAC with `dof` degrees of freedom and inlier distance `inlier_m`, then
    (with `refit_6dof`) a full rigid least-squares refit on the inliers, which absorbs a small scanner
    tilt that the 4-DOF model cannot.
    """
    p = coarse
    t0 = time.perf_counter()
    src, dst = match.tgt_xyz, match.ref_xyz
    n = len(src)
    if not match.ok:
        return _coarse_fail(match.message, match, (Metric("tie points", "", n),), t0)
    if n < p.min_ties:
        return _coarse_fail(
            f"only {n} tie points, at least {p.min_ties} are needed; use more image pairs or matches "
            "per pair, or a smaller theta (e.g. 5 deg)", match, (Metric("tie points", "", n),), t0)
    modes: tuple[tuple[np.ndarray, int], ...] = ()
    chance = -1
    if p.estimator == "svd":
        if robust.is_degenerate(src, p.dof):
            return _coarse_fail(f"the {n} tie points lie on one line: the transform is undetermined; "
                                "use more image pairs", match, (Metric("tie points", "", n),), t0)
        T = robust.fit(src, dst, p.dof)
        res = robust.residuals(T, src, dst)
        inl = res < p.inlier_m
        how = f"SVD over all ties ({p.dof} DOF)"
    else:
        found = robust.ransac_modes(src, dst, p.dof, p.inlier_m, p.iterations, p.seed,
                                    final_inlier_m=p.final_inlier_m, min_inliers=p.min_ties, max_modes=p.modes)
        fit = found[0] if found else None
        if fit is None:
            return _coarse_fail(f"no usable sample among {n} tie points (all too close together); "
                                "use more image pairs or matches per pair", match,
                                (Metric("tie points", "", n),), t0)
        T, inl = fit.T, fit.inliers
        how = f"RANSAC {p.dof} DOF"
        if fit.n_inliers < p.min_ties:
            return _coarse_fail(
                f"only {fit.n_inliers} of {n} tie points agree on one transform (within {p.inlier_m:g} m), "
                f"at least {p.min_ties} are needed; try more image pairs, more matches per pair, "
                "removing the ground, or a larger inlier distance", match,
                (Metric("tie points", "", n), Metric("inliers", "", fit.n_inliers)), t0)
        if p.refit_6dof and p.dof == 4 and not robust.is_degenerate(src[inl], 6):
            T = robust.fit(src[inl], dst[inl], 6)
            how += " + 6-DOF refit"
        res = robust.residuals(T, src, dst)
        modes = ((T, int(inl.sum())),) + tuple((m.T, m.n_inliers) for m in found[1:])
        chance = robust.chance_inliers(src, dst, p.dof, p.inlier_m, p.iterations, p.final_inlier_m,
                                       shuffles=p.chance_shuffles, seed=p.seed) if p.chance_shuffles else -1
    R = T[:3, :3]
    tilt = float(np.degrees(np.arccos(np.clip(R[2, 2], -1.0, 1.0))))
    yaw = float(np.degrees(np.arctan2(R[1, 0], R[0, 0])))
    n_in = int(inl.sum())
    metrics = (
        Metric("estimator", "", how),
        Metric("tie points", "", n),
        Metric("inliers", "", n_in),
        Metric("inlier ratio", "", n_in / n),
        Metric("inlier RMS residual", "m", float(np.sqrt(np.mean(res[inl] ** 2))) if n_in else float("nan")),
        Metric("yaw", "deg", yaw),
        Metric("tilt", "deg", tilt),
        Metric("rotation angle", "deg", rotation_angle_deg(R)),
    ) + ((Metric("inliers by chance (ties re-paired at random)", "", chance),) if chance >= 0 else ()) + (
        (Metric("distinct RANSAC modes", "", len(modes)),) if modes else ())
    problem = _implausible(n_in, n, tilt, p)
    # A failed check keeps its transform, so the app can show how wrong it is.
    return CoarseResult(not problem, problem, metrics, T, inl, res, n, n_in, match, time.perf_counter() - t0,
                        modes, chance)


def _implausible(n_inliers: int, n_ties: int, tilt_deg: float, p: CoarseParams) -> str:
    """Why a computed transform cannot be trusted ('' when it can).

    Plain SVD (the paper) always returns a transform, even when wrong matches dominate and the scan
    comes out upside down: a result is only kept when enough ties agree with it, and when it leaves
    the scanner nearly level (TLS instruments level themselves).
    """
    fix = ("plain SVD has no defence against wrong matches: use estimator = ransac"
           if p.estimator == "svd" else
           "try more image pairs or matches per pair, or removing the ground")
    if n_inliers < p.min_ties:
        return (f"only {n_inliers} of {n_ties} tie points agree with the transform within {p.inlier_m:g} m "
                f"(at least {p.min_ties} needed), so it is unreliable; {fix}")
    if p.max_tilt_deg is not None and tilt_deg > p.max_tilt_deg:
        return (f"the transform tilts the scan by {tilt_deg:.1f} deg, but scanners stand nearly level "
                f"(max_tilt_deg = {p.max_tilt_deg:g}), so its tie points are wrong; {fix}")
    return ""
