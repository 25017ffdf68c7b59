"""How well the scans agree where they overlap: each point's distance to the other scans' surface.

The residual a person judges a registration by: after a good registration every scan's points lie
on the surface the other scans measured; after a poor one a stem shows two skins a few centimetres
apart. For a point p, its nearest neighbour q among the other scans' points and the surface normal
n there (PCA of q's neighbours, `geometry.normals.pca_normals`) give the point-to-plane distance
|(p - q) . n|. Where q is farther than `reach_m` the other scans did not see that part of the tree;
those points get NaN (not a residual of the registration).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

from ..geometry.normals import pca_normals

#: Neighbours for the surface normal of the other scans.
SURFACE_K = 8


def surface_distances(points: np.ndarray, surface: np.ndarray, *, reach_m: float, tree: cKDTree | None = None,
                      k: int = SURFACE_K) -> np.ndarray:
    """Distance (m) of each of `points` to the surface sampled by `surface` (both in one frame).

    NaN where the nearest surface point is farther than `reach_m`.

    Examples
    --------
    >>> g = np.stack(np.meshgrid(np.arange(20) * 0.01, np.arange(20) * 0.01), -1).reshape(-1, 2)
    >>> plane = np.c_[g, np.zeros(len(g))]
    >>> surface_distances(np.array([[0.1, 0.1, 0.004], [0.1, 0.1, 1.0]]), plane, reach_m=0.05).round(4)
    array([0.004,   nan])
    """
    pts = np.asarray(points, dtype=float)
    surf = np.asarray(surface, dtype=float)
    out = np.full(len(pts), np.nan)
    if len(pts) == 0 or len(surf) < 3:
        return out
    tree = tree if tree is not None else cKDTree(surf)
    dist, nn = tree.query(pts, k=1, distance_upper_bound=reach_m)
    near = np.isfinite(dist)
    if not near.any():
        return out
    normals = pca_normals(surf, tree, surf[nn[near]], k)
    out[near] = np.abs(np.einsum("ij,ij->i", pts[near] - surf[nn[near]], normals))
    return out


def overlap_residuals(clouds: Sequence[np.ndarray], samples: Sequence[np.ndarray] | None = None, *,
                      reach_m: float = 0.05) -> list[np.ndarray]:
    """For every cloud (all in the reference frame), the distance of its points to the surface of
    all the other clouds together (`surface_distances`).

    Parameters
    ----------
    clouds
        One N_i x 3 array per scan, registered into one frame.
    samples
        Per cloud, the indices of the points to evaluate (e.g. the points a viewer shows); all when None.
    reach_m
        Farther than this from every other scan's point: not seen by them (NaN).
    """
    out = []
    for i, cloud in enumerate(clouds):
        others = [c for j, c in enumerate(clouds) if j != i and len(c)]
        pts = cloud if samples is None else cloud[samples[i]]
        if not others:
            out.append(np.full(len(pts), np.nan))
            continue
        out.append(surface_distances(pts, np.concatenate(others), reach_m=reach_m))
    return out
