"""ICP baseline (paper 3.3 compares it with fine registration), started from the coarse result.

Point-to-point (Besl and McKay) or point-to-plane (Chen and Medioni; linearised, small angles),
with a scipy `cKDTree` of the reference, voxel subsampling and trimming: each iteration keeps the
closest fraction `trim` of the correspondences within `max_distance_m`. The helpers
`voxel_downsample` and `estimate_normals` are shared with the fine stage's alignment measure.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .params import IcpParams
from .results import Metric, Progress, no_progress
from .rigid import apply_transform, kabsch, make_transform

#: Stop when an iteration rotates less than this (rad) and translates less than _STOP_M.
_STOP_RAD = 1e-6
_STOP_M = 1e-5
#: Neighbours for normals (point-to-plane).
NORMAL_K = 10


@dataclass(frozen=True)
class IcpResult:
    """ICP outcome.

    Attributes
    ----------
    ok, message, metrics
        As every stage result; `ok` is False when too few correspondences were found.
    T
        Final 4x4 T_ref_tgt (the initial transform when not ok).
    rmse_m
        RMS distance of the kept correspondences at the end (point-to-plane distance for that metric).
    fitness
        Fraction of the target's (subsampled) points with a kept correspondence at the end.
    iterations
        Iterations run.
    converged
        True when the last update was below the stopping threshold.
    """

    ok: bool
    message: str
    metrics: tuple[Metric, ...]
    T: np.ndarray
    rmse_m: float
    fitness: float
    iterations: int
    converged: bool


def voxel_downsample(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """Centroid of the points in each occupied voxel (all points when `voxel_m` <= 0)."""
    pts = np.asarray(points, dtype=float)
    if voxel_m <= 0 or len(pts) == 0:
        return pts.copy()
    keys = np.floor((pts - pts.min(axis=0)) / voxel_m).astype(np.int64)
    # One int64 per voxel: a 1-D unique is far faster than unique over rows.
    dims = keys.max(axis=0) + 1
    flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
    _, inv, counts = np.unique(flat, return_inverse=True, return_counts=True)
    out = np.empty((len(counts), 3))
    for k in range(3):
        out[:, k] = np.bincount(inv, weights=pts[:, k], minlength=len(counts)) / counts
    return out


def estimate_normals(points: np.ndarray, k: int = NORMAL_K, tree: cKDTree | None = None) -> np.ndarray:
    """Unit normals (smallest principal direction of the k nearest neighbours), N x 3."""
    pts = np.asarray(points, dtype=float)
    k = min(k, len(pts))
    if k < 3:
        return np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    tree = tree if tree is not None else cKDTree(pts)
    _, nb = tree.query(pts, k=k)
    q = pts[nb] - pts[nb].mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", q, q)
    return np.linalg.eigh(cov)[1][:, :, 0]


def rotation_from_vector(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector `w` (Rodrigues)."""
    th = float(np.linalg.norm(w))
    if th < 1e-15:
        return np.eye(3)
    k = w / th
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(th) * K + (1.0 - np.cos(th)) * (K @ K)


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


def icp(ref_points: np.ndarray, tgt_points: np.ndarray, T_init: np.ndarray, p: IcpParams,
        progress: Progress | None = None) -> IcpResult:
    """Trimmed ICP of the target onto the reference, from `T_init` (T_ref_tgt).

    Parameters
    ----------
    ref_points, tgt_points
        N x 3 and M x 3 points, each in its own scanner frame.
    T_init
        Start transform (the coarse result).
    p
        Metric, iterations, trimming, distance limit, voxel size.

    Returns
    -------
    IcpResult
    """
    progress = progress or no_progress
    T = np.asarray(T_init, dtype=float).copy()
    ref = voxel_downsample(ref_points, p.voxel_m)
    src = voxel_downsample(tgt_points, p.voxel_m)
    tree = cKDTree(ref)
    normals = estimate_normals(ref, tree=tree) if p.method == "point_to_plane" else None
    rmse, fit, it, converged = np.nan, 0.0, 0, False
    for it in range(1, p.max_iterations + 1):
        progress(it / p.max_iterations, f"ICP iteration {it}")
        moved = apply_transform(T, src)
        d, j = tree.query(moved, distance_upper_bound=p.max_distance_m)
        valid = np.isfinite(d)
        if valid.sum() < 6:
            return IcpResult(False, "ICP found fewer than 6 correspondences within icp.max_distance_m; "
                             "the start transform is too far off", (Metric("ICP iterations", "", it),),
                             np.asarray(T_init, dtype=float).copy(), np.nan, 0.0, it, False)
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
        fit = len(idx) / len(src)
        T = step @ T
        ang = np.arccos(np.clip((np.trace(step[:3, :3]) - 1) / 2, -1, 1))
        if ang < _STOP_RAD and np.linalg.norm(step[:3, 3]) < _STOP_M:
            converged = True
            break
    metrics = (
        Metric("ICP iterations", "", it),
        Metric("ICP RMSE", "m", rmse),
        Metric("ICP fitness", "", fit),
    )
    return IcpResult(True, "", metrics, T, rmse, fit, it, converged)
