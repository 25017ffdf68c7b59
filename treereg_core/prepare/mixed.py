"""Mixed pixels: returns strung out behind a stem's or branch's edge, removed on the scan's own grid.

Where a beam straddles an edge, part of it hits the edge and part what lies behind, and the range
the instrument reports lands in between: every silhouette trails a comet tail of points that lie on
no surface. They smear the projection images and sit in space the other station saw through. Every
instrument's software filters them first; so does the prepare stage, before anything else.

On the scan's own angular grid (a cell per angular step), a return is a mixed pixel when it is
*isolated along its ray* (no neighbouring return at a range within reach of its own: a real
surface, however oblique, continues in some direction at about the same range) and *just behind a
range jump* (some neighbouring return is nearer by more than that). A twig or leaf standing alone in
front of everything is kept (nothing is nearer); a surface seen at a grazing angle is kept (it
continues along its own range).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..results import Metric
from ..scan import Scan
from .angular_step import centred_azimuth_deg

#: Neighbours on the grid (the 8 cells around a return).
_OFFSETS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))
#: Composite sort key: cell index times this plus the range (m); ranges beyond it are not expected.
_RANGE_SPAN_M = 10_000.0


@dataclass(frozen=True, eq=False)
class MixedPixels:
    """What the filter found in one scan: `mixed` marks the removed returns; `scan` is the rest."""

    scan: Scan
    mixed: np.ndarray
    metrics: tuple[Metric, ...]

    @property
    def n_removed(self) -> int:
        return int(self.mixed.sum())


def find_mixed(points: np.ndarray, azimuth_deg: np.ndarray, elevation_deg: np.ndarray,
               step_deg: tuple[float, float], tolerance_m: float, slope: float) -> np.ndarray:
    """Mask of the mixed pixels among `points` (scanner frame) on the grid of `step_deg` cells.

    A neighbour one cell away continues the return's surface when their ranges differ by at most
    `tolerance_m + slope * range * step` (`slope` = tan of the steepest incidence kept).
    """
    n = len(points)
    if n == 0:
        return np.zeros(0, dtype=bool)
    r = np.sqrt(np.einsum("ij,ij->i", points, points))
    col = np.round(centred_azimuth_deg(np.asarray(azimuth_deg, dtype=float)) / step_deg[0]).astype(np.int64)
    row = np.round(np.asarray(elevation_deg, dtype=float) / step_deg[1]).astype(np.int64)
    col -= col.min() - 1  # a margin of one cell, so neighbours never wrap
    row -= row.min() - 1
    n_rows = int(row.max()) + 2
    key = col * n_rows + row
    # Sorted by cell, then range: a neighbour cell's return nearest to a given range is one search.
    comp = key.astype(np.float64) * _RANGE_SPAN_M + np.minimum(r, _RANGE_SPAN_M - 1.0)
    order = np.argsort(comp, kind="stable")
    comp_s, key_s, r_s = comp[order], key[order], r[order]
    tol = tolerance_m + slope * r * np.radians(max(step_deg))
    continuous = np.zeros(n, dtype=bool)
    nearer = np.zeros(n, dtype=bool)
    for dc, dr in _OFFSETS:
        nk = key + dc * n_rows + dr
        q = nk.astype(np.float64) * _RANGE_SPAN_M + np.minimum(r, _RANGE_SPAN_M - 1.0)
        i = np.searchsorted(comp_s, q)
        # The returns of that cell on either side of this range: the closer one decides continuity.
        best = np.full(n, np.inf)
        for j in (i - 1, i):
            jj = np.clip(j, 0, n - 1)
            same = (key_s[jj] == nk) & (j >= 0) & (j < n)
            best = np.minimum(best, np.where(same, np.abs(r_s[jj] - r), np.inf))
        continuous |= best <= tol
        first = np.clip(np.searchsorted(key_s, nk, side="left"), 0, n - 1)
        nearer |= (key_s[first] == nk) & (r_s[first] < r - tol)
    return nearer & ~continuous


def remove_mixed(scan: Scan, *, enabled: bool, tolerance_m: float, slope: float) -> MixedPixels:
    """`scan` without its mixed pixels (on its own angular grid), with what was removed counted."""
    if not enabled:
        return MixedPixels(scan, np.zeros(scan.n_points, dtype=bool), (Metric("mixed pixels removed", "", "off"),))
    mixed = find_mixed(scan.points, scan.azimuth_deg, scan.elevation_deg, scan.angular_step_deg, tolerance_m, slope)
    n = int(mixed.sum())
    metrics = (Metric("mixed pixels removed", "", n),
               Metric("mixed pixels removed, share of the points", "", n / max(scan.n_points, 1)))
    return MixedPixels(scan.with_points(scan.points[~mixed]) if n else scan, mixed, metrics)
