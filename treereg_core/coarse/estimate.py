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
from ..params import CoarseParams, set_flag
from ..results import Metric
from .matching import MatchResult

#: What brings more tie points, each with the key and the flag that sets it.
MORE_PAIRS = f"more image pairs ({set_flag('matching.n_pairs', 15)})"
MORE_TIES = (f"{MORE_PAIRS} or matches per pair ({set_flag('matching.matches_per_pair', 60)}), or a smaller "
             f"projection.theta_deg ({set_flag('projection.theta_deg', 5.0)})")
NO_GROUND = f"removing the ground ({set_flag('prepare.remove_ground', True)})"

@dataclass(frozen=True, eq=False, kw_only=True)
class CoarseResult:
    """The coarse transform of a target onto the reference.

    Attributes
    ----------
    ok, message, metrics : as every stage result.
    T_ref_target : 4x4 mapping target points into the reference frame (identity when not ok).
    inliers : (N,) bool per tie point: agrees with the transform within `inlier_m`.
    inlier_m : the inlier distance `inliers` refers to: RANSAC's last one when it narrowed its
        distance down towards `final_inlier_m` (NaN when no transform). After a 6-DOF refit the
        residuals moved a little since the inliers were chosen, so a few may sit across it.
    residuals_m : (N,) |T tgt - ref| per tie point, metres (NaN when no transform).
    n_ties, n_inliers : counts.
    match : the MatchResult the transform came from.
    seconds : wall time of the estimate.
    modes : (T, inliers) of RANSAC's distinct solutions, best first (the first is `T_ref_target`);
        empty for plain SVD. Competing headings of a round crown show up here.
    chance_inliers : the most ties RANSAC makes agree when the pairing is shuffled (what chance
        reaches on these ties; -1 when not measured).
    started_from : where the transform came from when a user gave it (`StartPose.source`: the
        file of `register --initial`, "the app"); "" when it was estimated from the tie points.
    """

    ok: bool
    message: str
    metrics: tuple[Metric, ...]
    T_ref_target: np.ndarray
    inliers: np.ndarray
    inlier_m: float
    residuals_m: np.ndarray
    n_ties: int
    n_inliers: int
    match: MatchResult | None = None
    seconds: float = 0.0
    modes: tuple[tuple[np.ndarray, int], ...] = ()
    chance_inliers: int = -1
    started_from: str = ""


def _coarse_fail(message: str, match: MatchResult, metrics: tuple[Metric, ...], t0: float) -> CoarseResult:
    n = match.n_ties
    return CoarseResult(ok=False, message=message, metrics=metrics, T_ref_target=np.eye(4),
                        inliers=np.zeros(n, dtype=bool), inlier_m=float("nan"), residuals_m=np.full(n, np.nan),
                        n_ties=n, n_inliers=0, match=match, seconds=time.perf_counter() - t0)


def _ransac_settings(p: CoarseParams, min_inliers: int) -> robust.RansacSettings:
    return robust.RansacSettings(dof=p.dof, inlier_m=p.inlier_m, iterations=p.iterations, seed=p.seed,
                                 final_inlier_m=p.final_inlier_m, min_inliers=min_inliers)


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
            f"only {n} tie points, at least {p.min_ties} are needed; try {MORE_TIES}", match,
            (Metric("tie points", "", n),), t0)
    modes: tuple[tuple[np.ndarray, int], ...] = ()
    chance = -1
    if p.estimator == "svd":
        if robust.is_degenerate(src, p.dof):
            return _coarse_fail(f"the {n} tie points lie on one line: the transform is undetermined; "
                                f"try {MORE_PAIRS}", match, (Metric("tie points", "", n),), t0)
        T = robust.fit(src, dst, p.dof)
        res = robust.residuals(T, src, dst)
        inl = res < p.inlier_m
        inlier_m = p.inlier_m
        how = f"SVD over all ties ({p.dof} DOF)"
    else:
        found = robust.ransac_modes(src, dst, _ransac_settings(p, p.min_ties), max_modes=p.modes)
        fit = found[0] if found else None
        if fit is None:
            return _coarse_fail(f"no usable sample among {n} tie points (all too close together); "
                                f"try {MORE_TIES}", match,
                                (Metric("tie points", "", n),), t0)
        T, inl, inlier_m = fit.T, fit.inliers, fit.inlier_m
        how = f"RANSAC {p.dof} DOF"
        if fit.n_inliers < p.min_ties:
            return _coarse_fail(
                f"only {fit.n_inliers} of {n} tie points agree on one transform (within {p.inlier_m:g} m), "
                f"at least {p.min_ties} are needed; try {MORE_TIES}; or {NO_GROUND}; or a larger coarse.inlier_m "
                f"(e.g. {set_flag('coarse.inlier_m', 0.8)})", match,
                (Metric("tie points", "", n), Metric("inliers", "", fit.n_inliers)), t0)
        if p.refit_6dof and p.dof == 4 and not robust.is_degenerate(src[inl], 6):
            T = robust.fit(src[inl], dst[inl], 6)
            how += " + 6-DOF refit"
        res = robust.residuals(T, src, dst)
        modes = ((T, int(inl.sum())),) + tuple((m.T, m.n_inliers) for m in found[1:])
        # The shuffled runs stop narrowing their inlier distance at RansacSettings' default of 6
        # inliers, not at min_ties: as they always have (the chance level the verdicts were tuned on).
        chance = robust.chance_inliers(src, dst, _ransac_settings(p, robust.RansacSettings.min_inliers),
                                       shuffles=p.chance_shuffles) if p.chance_shuffles else -1
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
    return CoarseResult(ok=not problem, message=problem, metrics=metrics, T_ref_target=T, inliers=inl,
                        inlier_m=inlier_m, residuals_m=res, n_ties=n, n_inliers=n_in, match=match,
                        seconds=time.perf_counter() - t0, modes=modes, chance_inliers=chance)


def _implausible(n_inliers: int, n_ties: int, tilt_deg: float, p: CoarseParams) -> str:
    """Why a computed transform cannot be trusted ('' when it can).

    Plain SVD (the paper) always returns a transform, even when wrong matches dominate and the scan
    comes out upside down: a result is only kept when enough ties agree with it, and when it leaves
    the scanner nearly level (TLS instruments level themselves).
    """
    fix = (f"plain SVD has no defence against wrong matches: try RANSAC ({set_flag('coarse.estimator', 'ransac')})"
           if p.estimator == "svd" else f"try {MORE_TIES}, or {NO_GROUND}")
    if n_inliers < p.min_ties:
        return (f"only {n_inliers} of {n_ties} tie points agree with the transform within {p.inlier_m:g} m "
                f"(at least {p.min_ties} needed), so it is unreliable; {fix}")
    if p.max_tilt_deg is not None and tilt_deg > p.max_tilt_deg:
        return (f"the transform tilts the scan by {tilt_deg:.1f} deg, but scanners stand nearly level "
                f"(max_tilt_deg = {p.max_tilt_deg:g}), so its tie points are wrong; {fix}")
    return ""

