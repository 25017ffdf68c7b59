"""Preparing a scan before projection: height crop, ground removal, radius crop around the stem.

The ground matters for the coarse stage: it fills the lower part of every projection image, where
it carries no structure ORB can match, and it drags the rotation centre (x_mean, y_mean) of the
image sequence away from the tree. It is found as a robust plane through the lowest point of each
horizontal grid cell; points within a band above that plane (and any below it) are removed.

A scan without ground (a tree cut out of a larger cloud) must come through untouched: the plane is
accepted only when it is nearly level, holds many cells, and has almost no points below it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..params import PrepareParams
from ..results import Metric
from ..scan import MIN_POINTS, Scan

#: A ground plane may be tilted at most this much from level (terrain slope + scanner tilt).
MAX_GROUND_SLOPE_DEG = 30.0
#: A ground plane needs at least this many cells, and this fraction of all cells, within tolerance.
MIN_GROUND_CELLS = 8
MIN_GROUND_CELL_FRACTION = 0.3
#: At most this fraction of the points may lie more than the band below an accepted plane.
MAX_BELOW_FRACTION = 0.01
#: Points used to find the ground plane.
GROUND_SAMPLE = 100_000


@dataclass(frozen=True, eq=False)
class PreparedScan:
    """A scan ready for projection.

    Attributes
    ----------
    ok, message, metrics : as every stage result.
    scan : the prepared scan (kept points only; same station, steps and source).
    kept_mask : (N,) bool over the original points: kept in `scan`.
    ground_mask : (N,) bool over the original points: removed as ground.
    plane : (a, b, c, d) with a x + b y + c z + d = 0, (a, b, c) unit and c > 0, or None (no ground found
        or ground removal off).
    stem_xy : horizontal position of the stem used for the radius crop, or None when not cropped.
    """

    ok: bool
    message: str
    metrics: tuple[Metric, ...]
    scan: Scan
    kept_mask: np.ndarray
    ground_mask: np.ndarray
    plane: tuple[float, float, float, float] | None
    stem_xy: tuple[float, float] | None


def cell_minima(points: np.ndarray, cell_m: float) -> np.ndarray:
    """Indices of the lowest point of every occupied `cell_m` x `cell_m` horizontal cell."""
    ij = np.floor(points[:, :2] / cell_m).astype(np.int64)
    ij -= ij.min(axis=0)
    key = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    order = np.lexsort((points[:, 2], key))
    k = key[order]
    first = np.r_[True, k[1:] != k[:-1]]
    return order[first]


def fit_plane_ransac(
    pts: np.ndarray, tol_m: float, iterations: int = 300, seed: int = 0
) -> tuple[np.ndarray, np.ndarray] | None:
    """Robust plane (unit normal with n_z >= 0, offset d) through `pts`, and its inlier mask.

    Hypotheses from random triples, the one with most points within `tol_m` wins, then a least-squares
    refit (SVD) on its inliers.
    """
    n = len(pts)
    if n < 3:
        return None
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, n, size=(iterations, 3))
    a, b, c = pts[idx[:, 0]], pts[idx[:, 1]], pts[idx[:, 2]]
    nrm = np.cross(b - a, c - a)
    length = np.linalg.norm(nrm, axis=1)
    good = length > 1e-9
    if not good.any():
        return None
    nrm = nrm[good] / length[good, None]
    d = -(nrm * a[good]).sum(axis=1)
    counts = (np.abs(pts @ nrm.T + d) < tol_m).sum(axis=0)
    h = int(np.argmax(counts))
    inl = np.abs(pts @ nrm[h] + d[h]) < tol_m
    centre = pts[inl].mean(axis=0)
    _, _, vt = np.linalg.svd(pts[inl] - centre, full_matrices=False)
    normal = vt[2] if vt[2, 2] >= 0 else -vt[2]
    d0 = -float(normal @ centre)
    return np.r_[normal, d0], np.abs(pts @ normal + d0) < tol_m


def find_ground(points: np.ndarray, cell_m: float, band_m: float) -> tuple[np.ndarray | None, str]:
    """The ground plane (a, b, c, d) of a scan, or None with the reason it was rejected."""
    # A plane needs no more than ~100k points: lowest points of a strided subset are as good.
    sub = points[:: max(1, len(points) // GROUND_SAMPLE)]
    low = sub[cell_minima(sub, cell_m)]
    tol = max(band_m / 2.0, 0.05)
    fitted = fit_plane_ransac(low, tol)
    if fitted is None:
        return None, "too few cells for a ground plane"
    plane, inl = fitted
    slope = float(np.degrees(np.arccos(min(abs(plane[2]), 1.0))))
    if slope > MAX_GROUND_SLOPE_DEG:
        return None, f"lowest points lie on a plane tilted {slope:.0f} deg: not ground"
    n_in = int(inl.sum())
    if n_in < MIN_GROUND_CELLS or n_in < MIN_GROUND_CELL_FRACTION * len(low):
        return None, f"only {n_in} of {len(low)} cells have their lowest point on one plane"
    height = points @ plane[:3] + plane[3]
    below = float(np.mean(height < -band_m))
    if below > MAX_BELOW_FRACTION:
        return None, f"{below:.1%} of the points lie below the candidate plane: not ground"
    return plane, ""


def stem_position(points: np.ndarray, heights: np.ndarray, cell_m: float = 0.25) -> np.ndarray:
    """Horizontal stem position: the densest cell among the lowest 2 m of points (or lowest 20%)."""
    cut = max(float(np.quantile(heights, 0.2)), float(heights.min()) + 2.0)
    low = points[heights <= cut, :2]
    ij = np.floor(low / cell_m).astype(np.int64)
    ij -= ij.min(axis=0)
    key = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    best = np.bincount(key).argmax()
    return np.median(low[key == best], axis=0)


def prepare_scan(scan: Scan, *, prepare: PrepareParams) -> PreparedScan:
    """Crop a scan by height, remove its ground, crop it to a radius around the stem.

    Parameters
    ----------
    scan : the station as read.
    prepare : preparation parameters (angular steps when given, ground removal on/off, cell, band, crop
        radius and heights).

    Returns
    -------
    PreparedScan; `ok` is False (with the scan left as it was) when fewer than MIN_POINTS points
    would remain.
    """
    p = prepare
    if p.angular_step_deg is not None and tuple(p.angular_step_deg) != scan.angular_step_deg:
        scan = scan.with_angular_step(p.angular_step_deg)  # the instrument's steps, as given, over the estimate
    pts = scan.points
    n = len(pts)
    kept = np.ones(n, dtype=bool)
    if p.crop_z_min_m is not None:
        kept &= pts[:, 2] >= p.crop_z_min_m
    if p.crop_z_max_m is not None:
        kept &= pts[:, 2] <= p.crop_z_max_m
    ground = np.zeros(n, dtype=bool)
    plane: np.ndarray | None = None
    note = "ground removal off"
    if p.remove_ground and kept.sum() >= MIN_POINTS:
        plane, why = find_ground(pts[kept], p.ground_cell_m, p.ground_band_m)
        if plane is not None:
            height = pts @ plane[:3] + plane[3]
            ground = kept & (height < p.ground_band_m)
            kept &= ~ground
            note = f"ground plane found, slope {np.degrees(np.arccos(min(abs(plane[2]), 1.0))):.1f} deg"
        else:
            note = f"no ground removed ({why})"
    stem = None
    if p.crop_radius_m is not None and kept.sum() >= MIN_POINTS:
        heights = pts[kept] @ plane[:3] + plane[3] if plane is not None else pts[kept, 2]
        stem = stem_position(pts[kept], heights)
        kept &= np.hypot(pts[:, 0] - stem[0], pts[:, 1] - stem[1]) <= p.crop_radius_m
    n_kept = int(kept.sum())
    metrics = (
        Metric("points in", "", n),
        Metric("points kept", "", n_kept),
        Metric("ground points removed", "", int(ground.sum())),
        Metric("ground", "", note),
    )
    plane_t = None if plane is None else tuple(float(v) for v in plane)
    stem_t = None if stem is None else (float(stem[0]), float(stem[1]))
    if n_kept < MIN_POINTS:
        return PreparedScan(
            ok=False,
            message=(f"{scan.label}: only {n_kept} of {n} points left after cropping and ground removal; "
                     "widen the crop (radius, z range) or lower the ground band"),
            metrics=metrics, scan=scan, kept_mask=np.ones(n, dtype=bool),
            ground_mask=np.zeros(n, dtype=bool), plane=plane_t, stem_xy=stem_t,
        )
    return PreparedScan(
        ok=True, message="", metrics=metrics, scan=scan.with_points(pts[kept]), kept_mask=kept,
        ground_mask=ground, plane=plane_t, stem_xy=stem_t,
    )
