"""ICP baseline (paper 3.3 compares it with fine registration), started from the coarse result.

Point-to-point (Besl and McKay) or point-to-plane (Chen and Medioni; linearised, small angles),
with a scipy `cKDTree` of the reference, voxel subsampling and trimming: each iteration keeps the
closest fraction `trim` of the correspondences within `max_distance_m`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..geometry.normals import estimate_normals, voxel_downsample
from ..geometry.rigid import apply_transform, kabsch, make_transform, rotation_from_vector
from ..params import IcpParams
from ..results import Metric, Progress, no_progress

#: Stop when an iteration rotates less than this (rad) and translates less than _STOP_M.
_STOP_RAD = 1e-6
_STOP_M = 1e-5


@dataclass(frozen=True, kw_only=True)
class IcpResult:
    """ICP outcome.

    Attributes
    ----------
    ok, message, metrics
        As every stage result; `ok` is False when too few correspondences were found.
    T_ref_target
        Final 4x4 (the initial transform when not ok).
    rmse_m
        RMS distance of the kept correspondences at the end (point-to-plane distance for that metric).
    overlap
        Fraction of the target's (subsampled) points with a reference point within
        `icp.max_distance_m` at the end: a measurement (the share kept, `icp.trim` of those, is a setting).
    iterations
        Iterations run.
    converged
        True when the last update was below the stopping threshold.
    ran
        False when the baseline is switched off (`icp.enabled`); the rest is then the start.
    """

    ok: bool
    message: str
    metrics: tuple[Metric, ...]
    T_ref_target: np.ndarray
    rmse_m: float
    overlap: float
    iterations: int
    converged: bool
    ran: bool = True


def icp_off(T_init: np.ndarray) -> IcpResult:
    """The result when the ICP baseline is switched off: nothing ran, the start stands."""
    return IcpResult(ok=True, message="the ICP baseline is off (icp.enabled)", metrics=(),
                     T_ref_target=np.asarray(T_init, dtype=float).copy(), rmse_m=float("nan"), overlap=0.0,
                     iterations=0, converged=False, ran=False)


def point_to_plane_step(src: np.ndarray, dst: np.ndarray, normals: np.ndarray,
                        weights: np.ndarray | None = None) -> np.ndarray:
    """The 4x4 (small-angle, linearised) minimising sum w ((R src + t - dst) . n)^2."""
    w = np.ones(len(src)) if weights is None else weights
    A = np.c_[np.cross(src, normals), normals]
    b = -np.einsum("ij,ij->i", src - dst, normals)
    H = A.T @ (A * w[:, None])
    g = A.T @ (b * w)
    try:
        x = np.linalg.solve(H + 1e-9 * np.eye(6), g)
    except np.linalg.LinAlgError:
        return np.eye(4)
    return make_transform(rotation_from_vector(x[:3]), x[3:])


def align_icp(ref_points: np.ndarray, tgt_points: np.ndarray, T_init: np.ndarray, *, icp: IcpParams,
              progress: Progress | None = None) -> IcpResult:
    """Trimmed ICP of the target onto the reference, from `T_init` (T_ref_target).

    Parameters
    ----------
    ref_points, tgt_points
        N x 3 and M x 3 points, each in its own scanner frame.
    T_init
        Start transform (the coarse result).
    icp
        Metric, iterations, trimming, distance limit, voxel size.

    Returns
    -------
    IcpResult
    """
    p = icp
    progress = progress or no_progress
    T = np.asarray(T_init, dtype=float).copy()
    ref = voxel_downsample(ref_points, p.voxel_m)
    src = voxel_downsample(tgt_points, p.voxel_m)
    tree = cKDTree(ref)
    normals = estimate_normals(ref, tree=tree) if p.method == "point_to_plane" else None
    rmse, overlap, it, converged = np.nan, 0.0, 0, False
    for it in range(1, p.max_iterations + 1):
        progress(it / p.max_iterations, f"ICP iteration {it}")
        moved = apply_transform(T, src)
        d, j = tree.query(moved, distance_upper_bound=p.max_distance_m)
        valid = np.isfinite(d)
        if valid.sum() < 6:
            return IcpResult(ok=False, message="ICP found fewer than 6 correspondences within icp.max_distance_m; "
                             "the start transform is too far off", metrics=(Metric("ICP iterations", "", it),),
                             T_ref_target=np.asarray(T_init, dtype=float).copy(), rmse_m=np.nan, overlap=0.0,
                             iterations=it, converged=False)
        idx = np.flatnonzero(valid)
        # Trim by the residual the metric minimises: for point-to-plane that is the distance along
        # the normal (trimming by point distance would keep a sliding, biased subset).
        if normals is not None:
            err = np.abs(np.einsum("ij,ij->i", moved[idx] - ref[j[idx]], normals[j[idx]]))
        else:
            err = d[idx]
        n_keep = max(6, int(np.ceil(p.trim * len(idx))))
        keep = np.argsort(err, kind="stable")[:n_keep]
        idx, resid = idx[keep], err[keep]
        if normals is not None:
            step = point_to_plane_step(moved[idx], ref[j[idx]], normals[j[idx]])
        else:
            step = kabsch(moved[idx], ref[j[idx]])
        rmse = float(np.sqrt(np.mean(resid ** 2)))
        overlap = float(valid.sum()) / len(src)
        T = step @ T
        ang = np.arccos(np.clip((np.trace(step[:3, :3]) - 1) / 2, -1, 1))
        if ang < _STOP_RAD and np.linalg.norm(step[:3, 3]) < _STOP_M:
            converged = True
            break
    metrics = (
        Metric("ICP iterations", "", it),
        Metric("ICP RMSE", "m", rmse),
        Metric("ICP overlap (target points within icp.max_distance_m)", "", overlap),
        Metric("ICP converged", "", "yes" if converged else f"no (stopped at icp.max_iterations = {p.max_iterations})"),
    )
    return IcpResult(ok=True, message="", metrics=metrics, T_ref_target=T, rmse_m=rmse, overlap=overlap, iterations=it,
                     converged=converged)
