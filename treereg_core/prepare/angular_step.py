"""Estimating a scan's angular steps phi (horizontal) and varphi (vertical) from its points.

A terrestrial scanner samples a regular grid in azimuth alpha and elevation beta. Where the beam
hits something, neighbouring points therefore sit exactly one step apart in alpha (same row) or
in beta (same column); dropouts and occlusion shadows only add larger gaps. So, for each point, we
take its nearest neighbour to the right that lies roughly in the same row (and the nearest one
above that lies roughly in the same column) and read the step off as the *mode* of those gaps:
gaps of 2, 3, ... steps (dropouts) and huge gaps (occlusion) are a minority and do not move it.

Rows and columns are told apart by the direction of the neighbour: a horizontal neighbour has
|d_beta| < 0.5 |d_alpha|. When phi and varphi differ a lot (e.g. 0.04 x 0.25 deg), the first pass
over a generous neighbourhood gives a rough ratio; a second pass in a space where beta is rescaled
by that ratio (so the grid is square) gives the final values.

Limits: the angles must be close to the grid, i.e. noise across the beam well below a step (range
noise along the beam does not matter; 3 mm of noise on x, y, z at 8 m is half of a 0.04 deg step
and biases the estimate by ~25 %). Clouds that were not sampled on a grid (e.g. the nearest point
per angular cell of a sparse merged cloud) give the typical point spacing, not an instrument step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial import cKDTree

#: Points queried per pass (the mode of 10 000 gaps is as sharp as that of 100 000).
MAX_QUERY_POINTS = 10_000
#: Points the k-d tree holds at most. A larger scan is cut to whole angular patches (all their
#: points), so that a queried point's neighbours stay its true neighbours.
MAX_TREE_POINTS = 100_000
#: Points per patch, on average.
_PATCH_POINTS = 2500
#: Gaps below this (degrees) are repeated angles (several returns of one pulse), not grid steps.
_MIN_GAP_DEG = 1e-6
#: Fewest usable gaps per direction before we trust a mode.
_MIN_SUPPORT = 20
#: A neighbour is "in the same row" when |d_beta| < _DIRECTION_RATIO * |d_alpha| (and vice versa).
_DIRECTION_RATIO = 0.5
#: A gap within this fraction of the step counts as one grid step (for the confidence).
_STEP_TOLERANCE = 0.2
#: Below this confidence an estimated step is not trusted: the user is told to give it.
LOW_CONFIDENCE = 0.5


@dataclass(frozen=True)
class StepEstimate:
    """The angular steps of a scan and how far to trust them.

    phi_deg, varphi_deg : horizontal and vertical steps, degrees.
    confidence : fraction (0-1) of row and column neighbour gaps that lie within 20 % of one step
        (the lower of the two directions); a scanner's grid gives 0.7-0.95, points that were not
        sampled on a grid (a merged cloud, a scan not in its scanner frame) 0.2-0.4. 1 for steps
        given or read off a grid.
    source : "given" (by the user), "grid" (the file's row/column indices) or "estimated".
    """

    phi_deg: float
    varphi_deg: float
    confidence: float
    source: str

    @property
    def steps(self) -> tuple[float, float]:
        return (self.phi_deg, self.varphi_deg)

    @property
    def low(self) -> bool:
        return self.confidence < LOW_CONFIDENCE

    def describe(self) -> str:
        """E.g. '0.622 x 0.0473 deg (estimated, confidence 0.72)'."""
        what = self.source if self.source != "estimated" else f"estimated, confidence {self.confidence:.2f}"
        return f"{self.phi_deg:.4g} x {self.varphi_deg:.4g} deg ({what})"


def centred_azimuth_deg(alpha_deg: np.ndarray) -> np.ndarray:
    """Azimuth relative to the circular mean, in (-180, 180]: a tree never straddles the +-180 seam."""
    a = np.radians(alpha_deg[:: max(1, len(alpha_deg) // 100_000)])  # the mean direction of a subset
    centre = np.degrees(np.arctan2(np.sin(a).mean(), np.cos(a).mean()))
    out = alpha_deg - centre  # within (-360, 360): wrap by one turn (cheaper than a float modulo)
    out[out >= 180.0] -= 360.0
    out[out < -180.0] += 360.0
    return out


def patches(alpha: np.ndarray, beta: np.ndarray, max_points: int, seed: int = 0) -> np.ndarray:
    """Indices of the points in a seeded random choice of angular patches, about `max_points` in all.

    Patches are square cells holding `_PATCH_POINTS` points on average (sized from the occupied
    area of a coarse 0.5 deg grid); every point of a chosen patch is kept, so only points on a
    patch's edge lose neighbours.
    """
    n = len(alpha)
    coarse = 0.5
    stride = max(1, n // 200_000)
    ci = np.floor(alpha[::stride] / coarse).astype(np.int64)
    cj = np.floor(beta[::stride] / coarse).astype(np.int64)
    occupied = len(np.unique(ci * 1_000_003 + cj))
    density = n / (occupied * coarse * coarse)  # points per square degree where there are points
    inv = 1.0 / float(np.sqrt(_PATCH_POINTS / density))
    # Patch (i, j) is drawn when frac((i * 100003 + j) * golden ratio + seed offset) < the fraction
    # wanted: a Weyl sequence, equidistributed over the patches, in a few float passes over the points.
    key = np.floor(alpha * inv)
    key *= 100_003.0
    key += np.floor(beta * inv)
    key *= 0.6180339887498949
    key += 0.1234567 * seed
    key -= np.floor(key)
    return np.flatnonzero(key < max_points / n)


def _peak(x: np.ndarray, bin_width: float) -> float:
    """Centre of the highest bin of a histogram of `x` smoothed over ~2 bins."""
    lo, hi = float(x.min()), float(x.max())
    n_bins = max(int(np.ceil((hi - lo) / bin_width)), 1)
    counts, edges = np.histogram(x, bins=n_bins, range=(lo, hi + 1e-12))
    smooth = gaussian_filter1d(counts.astype(float), sigma=2.0, mode="constant")
    i = int(np.argmax(smooth))
    return 0.5 * float(edges[i] + edges[i + 1])


def _mode(values: np.ndarray) -> float:
    """The most common value of positive `values`, robust to a sharp spike or a broad peak.

    A histogram of log values (1 % bins, so 0.04 deg and 0.25 deg get the same relative
    resolution; junk gaps from repeated returns spread over decades there and make no peak) finds
    the peak. Noisy or rounded coordinates turn the spike into a broad, ragged bump whose highest
    bin can sit well off its centre, so the peak is then moved to the median of the values within
    25 % of it until it settles (gaps of two steps, from dropouts, lie outside that window).
    """
    peak = float(np.exp(_peak(np.log(values), 0.01)))
    for _ in range(10):
        near = values[np.abs(values / peak - 1.0) <= 0.25]
        if near.size == 0:
            break
        new = float(np.median(near))
        settled = abs(new / peak - 1.0) < 1e-4
        peak = new
        if settled:
            break
    return peak


def _neighbour_gaps(
    alpha: np.ndarray, beta: np.ndarray, scale: float, k: int, n_query: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Per queried point: the gap to its nearest right-hand row neighbour and to its nearest upper
    column neighbour (degrees of alpha, and of beta), found among the k nearest in (alpha, scale*beta).

    Points without such a neighbour among the k nearest are left out.
    """
    xy = np.column_stack([alpha, beta * scale])
    tree = cKDTree(xy, balanced_tree=False, compact_nodes=False)  # faster to build, same answers
    n = len(xy)
    idx_q = rng.choice(n, size=n_query, replace=False) if n_query < n else np.arange(n)
    k_eff = min(k + 1, n)  # +1: the point itself comes back first
    _, nbr = tree.query(xy[idx_q], k=k_eff)
    d = xy[nbr] - xy[idx_q][:, None, :]  # (q, k, 2) displacements in the scaled space
    da, db = d[..., 0], d[..., 1]
    horizontal = (da > _MIN_GAP_DEG) & (np.abs(db) < _DIRECTION_RATIO * da)
    vertical = (db > _MIN_GAP_DEG * scale) & (np.abs(da) < _DIRECTION_RATIO * db)
    # The *nearest* qualifying neighbour (neighbours come sorted by distance), not the smallest
    # gap: with a little angular noise the minimum over the next column's points is biased low.
    rows = np.arange(len(idx_q))
    h_gap = da[rows, np.argmax(horizontal, axis=1)][horizontal.any(axis=1)]
    v_gap = db[rows, np.argmax(vertical, axis=1)][vertical.any(axis=1)] / scale
    return h_gap, v_gap


def estimate_angular_step(
    azimuth_deg: np.ndarray, elevation_deg: np.ndarray, seed: int = 0
) -> tuple[float, float]:
    """(phi, varphi) in degrees; see `estimate_steps` (which also says how far to trust them).

    Examples
    --------
    >>> a, b = np.meshgrid(np.arange(0, 5, 0.1), np.arange(0, 3, 0.05))
    >>> phi, varphi = estimate_angular_step(a.ravel(), b.ravel())
    >>> round(phi, 3), round(varphi, 3)
    (0.1, 0.05)
    """
    return estimate_steps(azimuth_deg, elevation_deg, seed).steps


def estimate_steps(azimuth_deg: np.ndarray, elevation_deg: np.ndarray, seed: int = 0) -> StepEstimate:
    """Estimate the instrument's angular steps (phi horizontal, varphi vertical), in degrees.

    Parameters
    ----------
    azimuth_deg, elevation_deg
        Per-point azimuth alpha and elevation beta in degrees, in the scanner's own frame
        (as `scan.spherical_angles_deg` computes them).
    seed
        Seed of the choice of query points and patches (used only for scans over `MAX_QUERY_POINTS`).

    Returns
    -------
    StepEstimate
        Horizontal and vertical angular steps in degrees, with a confidence: the share of row and
        column neighbours that sit one step apart.

    Raises
    ------
    ValueError
        When the points do not show a grid (too few points, or no row/column neighbours), so the
        caller should ask the user for the steps.
    """
    alpha = np.asarray(azimuth_deg, dtype=np.float64).ravel()
    beta = np.asarray(elevation_deg, dtype=np.float64).ravel()
    if alpha.shape != beta.shape:
        raise ValueError(f"azimuth and elevation differ in length ({alpha.size} vs {beta.size})")
    if alpha.size > MAX_TREE_POINTS:
        keep = patches(alpha, beta, MAX_TREE_POINTS, seed)
        alpha, beta = alpha[keep], beta[keep]
    ok = np.isfinite(alpha) & np.isfinite(beta)
    alpha, beta = centred_azimuth_deg(alpha[ok]), beta[ok]
    if alpha.size < 2 * _MIN_SUPPORT:
        raise ValueError(f"only {alpha.size} points: too few to estimate the angular step")
    rng = np.random.default_rng(seed)

    # Pass 1: a wide neighbourhood (24), so that even when one step is ~10x the other the nearest
    # neighbour along the coarse direction is among those found. If one direction still finds
    # (almost) nothing, the steps differ even more: stretch the other direction and look again.
    scale, n1 = 1.0, min(alpha.size, MAX_QUERY_POINTS // 4)
    for _ in range(3):
        h, v = _neighbour_gaps(alpha, beta, scale, 24, n1, rng)
        if h.size < _MIN_SUPPORT <= v.size:
            scale *= 5.0  # rows look empty: beta steps are tiny, spread them out
        elif v.size < _MIN_SUPPORT <= h.size:
            scale /= 5.0
        else:
            break
    if h.size < _MIN_SUPPORT or v.size < _MIN_SUPPORT:
        raise ValueError(
            f"the points do not lie on a regular angular grid ({h.size} row and {v.size} column "
            "neighbours found); give the steps explicitly"
        )
    phi, varphi = _mode(h), _mode(v)

    # Pass 2: rescale beta so the grid is square, then a compact neighbourhood is enough and rows
    # and columns separate cleanly.
    h2, v2 = _neighbour_gaps(alpha, beta, phi / varphi, 12, min(alpha.size, MAX_QUERY_POINTS), rng)
    if h2.size >= _MIN_SUPPORT and v2.size >= _MIN_SUPPORT:
        h, v = h2, v2
        phi, varphi = _mode(h), _mode(v)
    # On a grid most neighbours sit one step apart; off a grid the gaps spread widely.
    confidence = min(float(np.mean(np.abs(h / phi - 1.0) <= _STEP_TOLERANCE)),
                     float(np.mean(np.abs(v / varphi - 1.0) <= _STEP_TOLERANCE)))
    return StepEstimate(phi, varphi, confidence, "estimated")


def grid_steps(azimuth_deg: np.ndarray, elevation_deg: np.ndarray, row: np.ndarray, col: np.ndarray) -> StepEstimate:
    """The angular steps read off a scan's row/column grid (PTX, structured E57).

    Two points of one grid line that are k cells apart are k steps apart in angle, however many
    cells between them are empty, so the step is the median angle change per cell between
    successive valid points of a line. Which index runs along azimuth is read off the data (files
    differ): the index whose successive points change azimuth more than elevation.

    Raises
    ------
    ValueError
        When no grid line holds two valid points in either direction.
    """
    alpha = np.asarray(azimuth_deg, dtype=np.float64)
    beta = np.asarray(elevation_deg, dtype=np.float64)
    row = np.asarray(row, dtype=np.int64)
    col = np.asarray(col, dtype=np.int64)

    def per_cell(line: np.ndarray, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        order = np.lexsort((pos, line))
        same = line[order][1:] == line[order][:-1]
        dk = np.diff(pos[order])[same]
        da = (np.diff(alpha[order])[same] + 180.0) % 360.0 - 180.0  # across the +-180 seam too
        db = np.diff(beta[order])[same]
        ok = dk > 0
        return np.abs(da[ok]) / dk[ok], np.abs(db[ok]) / dk[ok]

    a_along_col, b_along_col = per_cell(row, col)  # successive columns of one row
    a_along_row, b_along_row = per_cell(col, row)  # successive rows of one column
    if a_along_col.size < _MIN_SUPPORT or a_along_row.size < _MIN_SUPPORT:
        raise ValueError("the row/column grid has too few neighbouring valid points")
    if np.median(a_along_col) >= np.median(b_along_col):  # columns run along azimuth
        phi, varphi = float(np.median(a_along_col)), float(np.median(b_along_row))
    else:
        phi, varphi = float(np.median(a_along_row)), float(np.median(b_along_col))
    if not (phi > 0 and varphi > 0):
        raise ValueError("the row/column grid gives a zero angular step")
    return StepEstimate(phi, varphi, 1.0, "grid")
