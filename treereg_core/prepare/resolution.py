"""The working resolution: a scan sampled finer than the stages need is reduced once, first.

A station of 10-40 M points samples a tree at a millimetre or less, far finer than any stage uses:
the projection images have pixels of ~0.1 deg, the fits take at most a few hundred points per
section, the surfaces are 1 cm voxels. So before anything else each scan is reduced to one point
per cell of an angular grid at the *working step*: the angle under which `spacing_m` is seen at the
scan's median range (5 mm at 10 m is 0.029 deg). That is what a scanner set to that step would
have measured, so every later stage (angular arcs included) works on it unchanged, and their cost
no longer grows with the raw count.

A cell's point is not its nearest point but the mean of the points within `depth_m` of the nearest
one in range: the nearest of many noisy returns sits about a noise sigma or more in front of the
surface (a bias towards each scanner, different per station), while their mean averages the range
noise away. Points further behind (another branch seen past an edge) stay out of it. A dense scan
thus gives *better* points at the working step, not just fewer.

Scans already as coarse as the working step (within `MIN_REDUCTION`) are kept as they are.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..params import ResolutionParams
from ..results import Metric
from ..scan import Scan
from .angular_step import centred_azimuth_deg

#: Reduce only when a cell holds at least this many grid steps on average (else keep the scan).
MIN_REDUCTION = 2.0
#: Points whose range is used for the median range (a strided subset is as good as all).
_RANGE_SAMPLE = 100_000
#: A dense cell grid (one float per cell) is used up to this many cells; beyond, cells are found by sorting.
_MAX_DENSE_CELLS = 60_000_000


@dataclass(frozen=True, eq=False)
class WorkingScan:
    """A scan at the working resolution.

    Attributes
    ----------
    scan : the scan the stages use (the input itself when it was not reduced).
    reduced : whether points were merged.
    step_deg : (phi, varphi) of the working scan (its cell size when reduced).
    metrics : what the reduction did (for the prepare stage's table).
    """

    scan: Scan
    reduced: bool
    step_deg: tuple[float, float]
    metrics: tuple[Metric, ...]


def working_step_deg(scan: Scan, spacing_m: float) -> float:
    """The angle under which `spacing_m` is seen at the scan's median range, degrees."""
    pts = scan.points[:: max(1, scan.n_points // _RANGE_SAMPLE)]
    r = float(np.median(np.sqrt(np.einsum("ij,ij->i", pts, pts))))
    return float(np.degrees(spacing_m / max(r, 1e-6)))


def _cell_keys(alpha: np.ndarray, beta: np.ndarray, cell: tuple[float, float]) -> tuple[np.ndarray, int]:
    """Flat cell index of every point on a (cell[0] x cell[1]) degree grid, and the number of cells."""
    a0, b0 = float(alpha.min()), float(beta.min())
    col = ((alpha - a0) / cell[0]).astype(np.int64)
    row = ((beta - b0) / cell[1]).astype(np.int64)
    n_rows = int(row.max()) + 1
    col *= n_rows
    col += row
    return col, (int(col.max()) + 1 if len(col) else 0)


def merge_cells(points: np.ndarray, alpha: np.ndarray, beta: np.ndarray, cell: tuple[float, float],
                depth_m: float) -> np.ndarray:
    """One point per occupied (alpha, beta) cell: the mean of its points within `depth_m` of its
    nearest point in range. Returns M x 3 float64, cells in index order."""
    key, n_cells = _cell_keys(alpha, beta, cell)
    rng = np.einsum("ij,ij->i", points, points)
    np.sqrt(rng, out=rng)
    if n_cells > _MAX_DENSE_CELLS:
        # A sparse, very wide grid (a whole 360 deg station): number the occupied cells by sorting.
        _, key = np.unique(key, return_inverse=True)
        n_cells = int(key.max()) + 1
    nearest = np.full(n_cells, np.inf)
    np.minimum.at(nearest, key, rng)
    # Weight 1 for the points in front (within depth of the nearest), 0 behind: sums without a
    # masked copy of the points.
    w = nearest[key]
    w += depth_m
    w = (rng <= w).astype(np.float64)
    del rng
    # The occupied cells numbered in index order: the sums go to an array of them (a few hundred
    # thousand), not to one of every cell of the grid (millions, mostly empty: four passes of page
    # faults and cache misses). The same sums, in the same order.
    occupied = np.flatnonzero(np.isfinite(nearest))
    del nearest
    number = np.zeros(n_cells, dtype=np.int64)
    number[occupied] = np.arange(len(occupied))
    key = number[key]
    del number
    count = np.bincount(key, weights=w, minlength=len(occupied))
    out = np.empty((len(occupied), 3))
    for i in range(3):
        out[:, i] = np.bincount(key, weights=points[:, i] * w, minlength=len(occupied))
    out /= count[:, None]
    return out


def working_resolution(scan: Scan, *, resolution: ResolutionParams) -> WorkingScan:
    """`scan` reduced to the working resolution (or as it is, when it is not finer than that).

    Parameters
    ----------
    scan : the station as read (full resolution).
    resolution : the working spacing at the tree and the depth a cell averages over.

    Returns
    -------
    WorkingScan; its scan has the same name, source and (when not reduced) the same steps.
    """
    p = resolution
    phi, varphi = scan.angular_step_deg
    n = scan.n_points
    if p.spacing_m is None:
        return WorkingScan(scan, False, (phi, varphi), (Metric("working resolution", "", "off (every point kept)"),))
    step = working_step_deg(scan, p.spacing_m)
    cell = (max(step, phi), max(step, varphi))
    factor = cell[0] * cell[1] / (phi * varphi)
    if factor < MIN_REDUCTION:
        return WorkingScan(scan, False, (phi, varphi), (
            Metric("working resolution", "", f"full ({phi:.3g} x {varphi:.3g} deg is not finer than {step:.3g} deg)"),))
    alpha = centred_azimuth_deg(scan.azimuth_deg)  # a tree never straddles the +-180 deg seam
    pts = merge_cells(scan.points, alpha, scan.elevation_deg, cell, p.depth_m)
    del alpha
    scan.forget_angles()  # 16 bytes a point, not needed again: the stages use the working scan
    reduced = Scan(points=pts, name=scan.name, angular_step_deg=cell, source=scan.source,
                   step_estimated=scan.step_estimated)
    metrics = (
        Metric("points as read", "", n),
        Metric("working step", "deg", step),
        Metric("points at the working step", "", reduced.n_points),
    )
    return WorkingScan(reduced, True, cell, metrics)
