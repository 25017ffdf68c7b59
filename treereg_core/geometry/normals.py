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
    q = cloud[nb]
    q -= q.mean(axis=1, keepdims=True)
    return smallest_eigenvectors(np.einsum("nki,nkj->nij", q, q))


def smallest_eigenvectors(C: np.ndarray) -> np.ndarray:
    """Unit eigenvectors of the smallest eigenvalues of symmetric 3 x 3 matrices `C` (N x 3 x 3),
    sign arbitrary.

    In closed form (the eigenvalue by the trigonometric solution of the characteristic cubic, the
    vector as the longest cross product of two rows of C - lambda I): an order of magnitude faster
    than LAPACK's `eigh` over the tens of thousands of matrices a surface's normals are. Where
    the smallest eigenvalue is not separated from the next (a line, a single point: no plane to
    speak of) LAPACK decides, as before. Each row's answer depends on that row alone, never on
    how many were asked together (the pairs computed side by side fill a surface's normals in
    batches that differ from run to run).
    """
    C = np.asarray(C, dtype=float)
    if len(C) == 0:
        return np.zeros((0, 3))
    a, b, c = C[:, 0, 0], C[:, 1, 1], C[:, 2, 2]
    d, e, f = C[:, 0, 1], C[:, 0, 2], C[:, 1, 2]
    mean = (a + b + c) / 3.0
    off = d * d + e * e + f * f
    p = np.sqrt(((a - mean) ** 2 + (b - mean) ** 2 + (c - mean) ** 2 + 2.0 * off) / 6.0)
    safe = np.where(p > 0, p, 1.0)
    b11, b22, b33 = (a - mean) / safe, (b - mean) / safe, (c - mean) / safe
    b12, b13, b23 = d / safe, e / safe, f / safe
    det = b11 * (b22 * b33 - b23 * b23) - b12 * (b12 * b33 - b23 * b13) + b13 * (b12 * b23 - b22 * b13)
    phi = np.arccos(np.clip(det / 2.0, -1.0, 1.0)) / 3.0
    lam = mean + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    r0 = np.stack([a - lam, d, e], axis=1)
    r1 = np.stack([d, b - lam, f], axis=1)
    r2 = np.stack([e, f, c - lam], axis=1)
    crosses = np.stack([np.cross(r0, r1), np.cross(r0, r2), np.cross(r1, r2)], axis=1)
    norms = np.einsum("nij,nij->ni", crosses, crosses)
    best = norms.argmax(axis=1)
    rows = np.arange(len(C))
    v = crosses[rows, best]
    size = np.sqrt(norms[rows, best])
    out = v / np.where(size > 0, size, 1.0)[:, None]
    # The cross products vanish with the gap to the next eigenvalue: there the closed form loses
    # its digits (relative to the matrix's own scale) and LAPACK takes over.
    scale = np.maximum(p, 1e-300)
    weak = ~(size > 1e-6 * scale * scale)
    if weak.any():
        out[weak] = np.linalg.eigh(C[weak])[1][:, :, 0]
    return out


def estimate_normals(points: np.ndarray, k: int = NORMAL_K, tree: cKDTree | None = None) -> np.ndarray:
    """Unit normals of every point, N x 3 (vertical when there are fewer than 3 points)."""
    pts = np.asarray(points, dtype=float)
    if min(k, len(pts)) < 3:
        return np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    return pca_normals(pts, tree if tree is not None else cKDTree(pts), pts, k)
