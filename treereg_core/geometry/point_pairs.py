"""The rigid fit of point pairs a person picked (the app's *Align by hand*): Kabsch on the pairs, each
pair's residual, and the fit taken from the frames the pairs were picked in (the scans as the stages
see them: scanner frames, levelled) to the frames a start pose is given in (the scans as their files
give them: `coarse.start.StartPose`, transforms.json).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .rigid import invert, kabsch

#: Pairs a rigid fit needs (three points not on one line fix a rotation and a shift).
MIN_PAIRS = 3
#: Picked points closer to one line than this (m, the second-largest spread of either side's points
#: about their centroid) fix no rotation about that line.
MIN_SPREAD_M = 0.05


@dataclass(frozen=True, kw_only=True)
class PairFit:
    """The rigid transform that maps the picked target points onto their reference points.

    ok : a fit was made (at least `MIN_PAIRS` pairs, not all on one line).
    message : what the fit says, or what to pick next (a sentence).
    T_ref_tgt : 4x4, the fit (the identity when not ok).
    residuals_m : each pair's distance after the fit, in the pairs' order (empty when not ok).
    rms_m : the root mean square of `residuals_m` (nan when not ok).
    """

    ok: bool
    message: str
    T_ref_tgt: np.ndarray
    residuals_m: tuple[float, ...] = ()
    rms_m: float = float("nan")

    @property
    def worst(self) -> int | None:
        """The index of the pair the fit agrees with least (None when not ok)."""
        return int(np.argmax(self.residuals_m)) if self.ok and self.residuals_m else None


def _spread_m(points: np.ndarray) -> float:
    """The second-largest spread of `points` about their centroid (0 for points on one line)."""
    if len(points) < 2:
        return 0.0
    s = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return float(s[1] / np.sqrt(len(points))) if len(s) > 1 else 0.0


def fit_point_pairs(ref_points: np.ndarray, tgt_points: np.ndarray) -> PairFit:
    """Kabsch fit of `tgt_points` onto `ref_points` (both N x 3, row i a pair), with each pair's residual.

    Examples
    --------
    >>> ref = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    >>> fit = fit_point_pairs(ref, ref - [2.0, 0, 0])
    >>> fit.ok, round(float(fit.T_ref_tgt[0, 3]), 6), round(fit.rms_m, 9)
    (True, 2.0, 0.0)
    >>> fit_point_pairs(ref[:2], ref[:2]).ok
    False
    """
    ref = np.asarray(ref_points, dtype=np.float64).reshape(-1, 3)
    tgt = np.asarray(tgt_points, dtype=np.float64).reshape(-1, 3)
    if len(ref) != len(tgt):
        raise ValueError(f"{len(ref)} reference points but {len(tgt)} target points")
    n = len(ref)
    if n < MIN_PAIRS:
        return PairFit(ok=False, T_ref_tgt=np.eye(4),
                       message=f"{n} point pair(s) picked: pick at least {MIN_PAIRS}, spread over the tree "
                               "(the stem low and high, a branch to one side).")
    if not (np.isfinite(ref).all() and np.isfinite(tgt).all()):
        raise ValueError("picked points must be finite")
    if min(_spread_m(ref), _spread_m(tgt)) < MIN_SPREAD_M:
        return PairFit(ok=False, T_ref_tgt=np.eye(4),
                       message=f"The {n} picked points lie nearly on one line, which leaves the turn about it "
                               "open: pick a pair off that line (a branch to one side, the ground).")
    T = kabsch(tgt, ref)
    res = np.linalg.norm(tgt @ T[:3, :3].T + T[:3, 3] - ref, axis=1)
    rms = float(np.sqrt(np.mean(res ** 2)))
    worst = int(np.argmax(res))
    return PairFit(ok=True, T_ref_tgt=T, residuals_m=tuple(float(r) for r in res), rms_m=rms,
                   message=f"{n} pairs fitted: RMS residual {rms:.3f} m, the largest {res[worst]:.3f} m "
                           f"(pair {worst + 1}).")


def as_file_frames(T_ref_tgt: np.ndarray, *, ref_pose: np.ndarray | None, tgt_pose: np.ndarray | None,
                   ref_level: np.ndarray | None, tgt_level: np.ndarray | None) -> np.ndarray:
    """A transform between the scans as the stages see them (scanner frames, levelled by
    `PreparedScan.T_level`) as one between the scans as their files give them (`Scan.pose`:
    T_user_scan), what a start pose holds: P_ref @ inv(L_ref) @ T @ L_tgt @ inv(P_tgt) — the inverse of
    the coarse stage's `to_stage_frames` for a pair with the reference. None: the identity."""
    eye = np.eye(4)
    P_ref = eye if ref_pose is None else np.asarray(ref_pose, dtype=np.float64)
    P_tgt = eye if tgt_pose is None else np.asarray(tgt_pose, dtype=np.float64)
    L_ref = eye if ref_level is None else np.asarray(ref_level, dtype=np.float64)
    L_tgt = eye if tgt_level is None else np.asarray(tgt_level, dtype=np.float64)
    out: np.ndarray = P_ref @ invert(L_ref) @ np.asarray(T_ref_tgt, dtype=np.float64) @ L_tgt @ invert(P_tgt)
    return out
