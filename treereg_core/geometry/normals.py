"""Voxel subsampling and PCA normals: the one place every stage gets them from.

A normal is the smallest principal direction of a point's k nearest neighbours. The ICP baseline,
the fine stage's surfaces and the cylinder fit's start axis all use `pca_normals`.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

#: Neighbours per normal, unless a caller needs fewer.
NORMAL_K = 10


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


def pca_normals(cloud: np.ndarray, tree: cKDTree, at: np.ndarray, k: int = NORMAL_K) -> np.ndarray:
    """Unit normals at the points `at` from their `k` nearest neighbours in `cloud` (indexed by `tree`).

    The sign is arbitrary; callers that need it orient the normals themselves (towards the scanner).
    """
    k = min(k, len(cloud))
    _, nb = tree.query(at, k=k)
    q = cloud[nb] - cloud[nb].mean(axis=1, keepdims=True)
    return np.linalg.eigh(np.einsum("nki,nkj->nij", q, q))[1][:, :, 0]


def estimate_normals(points: np.ndarray, k: int = NORMAL_K, tree: cKDTree | None = None) -> np.ndarray:
    """Unit normals of every point, N x 3 (vertical when there are fewer than 3 points)."""
    pts = np.asarray(points, dtype=float)
    if min(k, len(pts)) < 3:
        return np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    return pca_normals(pts, tree if tree is not None else cKDTree(pts), pts, k)
