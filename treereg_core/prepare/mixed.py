"""Mixed pixels: returns strung out behind a stem's or branch's edge, removed on the scan's own grid.

Where a beam straddles an edge, part of it hits the edge and part what lies behind, and the range
the instrument reports lands in between: every silhouette trails a comet tail of points that lie on
no surface. They smear the projection images and sit in space the other station saw through. Every
instrument's software filters them first; so does the prepare stage, before anything else.

On the scan's own angular grid (a cell per angular step), a return is a mixed pixel when it is
*just behind a range jump* (some neighbouring return is nearer by more than the reach below) and
*isolated along its ray*: no neighbouring return continues it at about its own range (a real
surface, however oblique, continues in some direction). Where tails are many, two strung out side
by side behind one edge continue each other; there a return is kept only when a neighbour that is
not itself behind a jump continues it, or two do. A twig or leaf standing alone in front of
everything is kept (nothing is nearer); a surface seen at a grazing angle is kept (it continues
along its own range).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..params import PrepareParams
from ..results import Metric
from ..scan import Scan
from .angular_step import centred_azimuth_deg

#: Neighbours on the grid (the 8 cells around a return).
_OFFSETS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))
# When tails are "many" (`PrepareParams.mixed_dense_share`; clean simulated and real stations:
# 0.1-0.8%, a tenth of the edge returns mixed: 2.5-5%) and when the filter stands down
# (`PrepareParams.mixed_max_share`) are parameters.
#: A dense grid of the cells' nearest returns is used while it has at most this many cells per return.
_DENSE_CELLS_PER_POINT = 16
#: Composite sort key: cell index times this plus the range (m); ranges beyond it are not expected.
_RANGE_SPAN_M = 10_000.0


@dataclass(frozen=True, eq=False)
class MixedPixels:
    """What the filter found in one scan: `mixed` marks the removed returns; `scan` is the rest;
    `not_filtered` says why the filter stood down on it ("" when it ran, or was switched off)."""

    scan: Scan
    mixed: np.ndarray
    metrics: tuple[Metric, ...]
    not_filtered: str = ""

    @property
    def n_removed(self) -> int:
        return int(self.mixed.sum())


def find_mixed(points: np.ndarray, azimuth_deg: np.ndarray, elevation_deg: np.ndarray,
               step_deg: tuple[float, float], tolerance_m: float, slope: float,
               min_continuing: int | None = None,
               dense_share: float = PrepareParams.mixed_dense_share) -> np.ndarray:
    """Mask of the mixed pixels among `points` (scanner frame) on the grid of `step_deg` cells.

    A neighbour one cell away continues the return's surface when their ranges differ by at most
    `tolerance_m + slope * range * step` (`slope` = tan of the steepest incidence kept). A return
    behind a jump is kept when any neighbour continues it; where tails are many (the returns
    behind a jump that nothing continues are at least `dense_share` of the scan), only when
    a neighbour not behind a jump does, or two do (`min_continuing`: 1 or 2 to choose).
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
    nearer = np.zeros(n, dtype=bool)
    n_cells = (int(col.max()) + 2) * n_rows
    if n_cells <= _DENSE_CELLS_PER_POINT * n + 1_000_000:
        # Each cell's nearest return on a dense grid: eight lookups instead of eight searches.
        first = np.flatnonzero(np.r_[True, key_s[1:] != key_s[:-1]])
        nearest = np.full(n_cells, np.inf)
        nearest[key_s[first]] = r_s[first]
        for off in (dc * n_rows + dr for dc, dr in _OFFSETS):
            nearer |= nearest[key + off] < r - tol
        del nearest
    else:
        for nk in (key + dc * n_rows + dr for dc, dr in _OFFSETS):
            at = np.clip(np.searchsorted(key_s, nk, side="left"), 0, n - 1)
            nearer |= (key_s[at] == nk) & (r_s[at] < r - tol)
    # Where tails are many, two strung out side by side behind one edge continue each other (the
    # chance grows with the square of their share); a surface continues through a neighbour not
    # itself behind a jump, or through two. Where they are few, a real fragment behind a jump (a
    # leaf behind a leaf) is likelier than such a pair: any continuation keeps a return. Only the
    # returns behind a jump (a few per cent) need asking.
    cand = np.flatnonzero(nearer)
    kc, rc, tc = key[cand], r[cand], tol[cand]
    continuing = np.zeros(len(cand), dtype=np.int8)
    solid = np.zeros(len(cand), dtype=bool)
    for nk in (kc + dc * n_rows + dr for dc, dr in _OFFSETS):
        q = nk.astype(np.float64) * _RANGE_SPAN_M + np.minimum(rc, _RANGE_SPAN_M - 1.0)
        i = np.searchsorted(comp_s, q)
        # The returns of that cell on either side of this range: the closer one decides continuity.
        best, at = np.full(len(cand), np.inf), np.zeros(len(cand), dtype=np.int64)
        for j in (i - 1, i):
            jj = np.clip(j, 0, n - 1)
            same = (key_s[jj] == nk) & (j >= 0) & (j < n)
            d = np.where(same, np.abs(r_s[jj] - rc), np.inf)
            take = d < best
            best, at = np.where(take, d, best), np.where(take, order[jj], at)
        hit = best <= tc
        continuing += hit
        solid |= hit & ~nearer[at]
    if min_continuing is None:
        min_continuing = 2 if np.count_nonzero(continuing == 0) >= dense_share * n else 1
    out = np.zeros(n, dtype=bool)
    out[cand[~solid & (continuing < min_continuing)]] = True
    return out


def remove_mixed(scan: Scan, *, enabled: bool, tolerance_m: float, slope: float,
                 dense_share: float = PrepareParams.mixed_dense_share,
                 max_share: float = PrepareParams.mixed_max_share) -> MixedPixels:
    """`scan` without its mixed pixels (on its own angular grid), with what was removed counted
    (the arguments are `PrepareParams`' mixed_* fields; the defaults theirs)."""
    if not enabled:
        return MixedPixels(scan, np.zeros(scan.n_points, dtype=bool), (Metric("mixed pixels removed", "", "off"),))
    if scan.step is not None and scan.step.low:
        # Without the instrument's grid (a merged cloud, a scan not in its scanner frame) a
        # neighbour on the estimated grid is no neighbour on the beam's: the filter would guess.
        why = f"off: no regular angular grid ({scan.step.describe()})"
        return MixedPixels(scan, np.zeros(scan.n_points, dtype=bool), (Metric("mixed pixels removed", "", why),), why)
    mixed = find_mixed(scan.points, scan.azimuth_deg, scan.elevation_deg, scan.angular_step_deg, tolerance_m, slope,
                       dense_share=dense_share)
    n = int(mixed.sum())
    if n > max_share * scan.n_points:
        # Half the edge returns mixed leaves a quarter of a scan in tails; more is a surface rougher
        # than the grid (foliage sampled coarser than its leaves, a thinned cloud): removing it
        # would take the tree itself.
        why = (f"none: {n / scan.n_points:.0%} of the returns lie behind a range jump, too many to be tails (the "
               "surface is rougher than the angular grid)")
        return MixedPixels(scan, np.zeros(scan.n_points, dtype=bool), (Metric("mixed pixels removed", "", why),), why)
    metrics = (Metric("mixed pixels removed", "", n),
               Metric("mixed pixels removed, share of the points", "", n / max(scan.n_points, 1)))
    return MixedPixels(scan.with_points(scan.points[~mixed]) if n else scan, mixed, metrics)
