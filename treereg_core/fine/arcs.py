"""Separating a slice into arcs by angular connectivity in the scan's own grid (paper 2.2.2).

A terrestrial scanner samples a regular (alpha, beta) grid with steps (phi, varphi). Two points
of a slice belong to the same arc when they are neighbours on that grid: d_alpha <= c*phi and
d_beta <= c*varphi (paper: c = 3). We put the slice's points on a raster of one cell per angular
step and label connected components with `scipy.ndimage.label` — no pairwise distances.

`ndimage.label` only knows 8-connectivity, so the raster is first dilated by a box of half-width
h = floor(c / 2) cells: two occupied cells at most 2h + 1 cells apart (Chebyshev, per axis) then
touch, which for the paper's odd c = 3 is exactly d <= c steps. Labels are read back at the
occupied cells only.

Beyond the paper (`ArcParams.max_range_jump_m`): a stem and a branch far behind it can be angular
neighbours at the edge of the stem; a gap in range larger than the limit splits such an arc.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..limits import check_raster
from ..params import ArcParams
from ..results import Metric
from ..scan import Scan

#: Bytes per raster cell: the occupancy grid, its dilation (bool each) and the labels (int32).
_RASTER_CELL_BYTES = 6


@dataclass(frozen=True, kw_only=True)
class ArcResult:
    """Arcs of one slice of one scan.

    Attributes
    ----------
    ok, message, metrics
        As every stage result; `ok` is False when the slice has no arc of `min_points`.
    indices
        Indices into `scan.points` of the slice's points (as given).
    labels
        Per point of the slice, its arc number 0..n_arcs-1, or -1 (in an arc smaller than the minimum).
    n_arcs
        Number of arcs kept, numbered by decreasing size.
    """

    ok: bool
    message: str
    metrics: tuple[Metric, ...]
    indices: np.ndarray
    labels: np.ndarray
    n_arcs: int

    def arc(self, k: int) -> np.ndarray:
        """Indices into `scan.points` of arc `k`."""
        return self.indices[self.labels == k]

    def arcs(self) -> tuple[np.ndarray, ...]:
        """Indices into `scan.points` of every arc, largest first."""
        order = np.argsort(self.labels, kind="stable")
        lab = self.labels[order]
        cuts = np.searchsorted(lab, np.arange(self.n_arcs + 1))
        return tuple(self.indices[order[cuts[k]:cuts[k + 1]]] for k in range(self.n_arcs))


def _wrap_deg(a: np.ndarray) -> np.ndarray:
    return (a + 180.0) % 360.0 - 180.0


def _relative_azimuth(alpha: np.ndarray) -> np.ndarray:
    """Azimuth relative to the circular mean, so an arc never straddles the +-180 deg seam."""
    rad = np.radians(alpha)
    mean = np.degrees(np.arctan2(np.sin(rad).mean(), np.cos(rad).mean()))
    return _wrap_deg(alpha - mean)


def angular_cells(scan: Scan, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The (column, row) raster cell of each point of `indices` in the scan's own angular grid:
    one cell per angular step, azimuth relative to the points' circular mean (the raster the arcs
    are separated on, paper Fig. 6)."""
    idx = np.asarray(indices, dtype=np.int64)
    phi, varphi = scan.angular_step_deg
    alpha = _relative_azimuth(scan.azimuth_deg[idx])
    beta = scan.elevation_deg[idx]
    # Rounding (not flooring) keeps a regular grid's points one cell apart even when their angles
    # carry floating-point error of either sign.
    col = np.rint((alpha - alpha.min()) / phi).astype(np.int64)
    row = np.rint((beta - beta.min()) / varphi).astype(np.int64)
    return col, row


def _label_cells(col: np.ndarray, row: np.ndarray, h: int) -> np.ndarray:
    """Connected-component label of each (col, row) cell on a dilated raster; labels from 1."""
    c0, r0 = col.min(), row.min()
    cc, rr = col - c0 + h, row - r0 + h
    shape = (int(cc.max()) + h + 1, int(rr.max()) + h + 1)
    grid = np.zeros(shape, dtype=bool)
    grid[cc, rr] = True
    if h > 0:
        grid = ndimage.binary_dilation(grid, structure=np.ones((2 * h + 1, 2 * h + 1), dtype=bool))
    lab, _ = ndimage.label(grid, structure=np.ones((3, 3), dtype=int))
    return lab[cc, rr]


def _label_raster(col: np.ndarray, row: np.ndarray, c: float, what: str = "the slice raster") -> np.ndarray:
    """Component label per point (0-based, arbitrary order) of grid cells `col`, `row`.

    Raises `limits.RasterTooLarge` (naming `what`) before allocating a raster that cannot fit.
    """
    h = int(np.floor(c / 2.0))
    reach = 2 * h + 1
    # Split at column gaps no arc can bridge, so a wide, sparse slice never needs one huge raster.
    ucol = np.unique(col)
    breaks = np.flatnonzero(np.diff(ucol) > reach)
    starts = np.concatenate([[ucol[0]], ucol[breaks + 1]])
    group = np.searchsorted(starts, col, side="right") - 1
    labels = np.empty(len(col), dtype=np.int64)
    offset = 0
    order = np.argsort(group, kind="stable")
    cuts = np.searchsorted(group[order], np.arange(len(starts) + 1))
    for g in range(len(starts)):
        sel = order[cuts[g]:cuts[g + 1]]
        gc, gr = col[sel], row[sel]
        check_raster(what, int(gr.max() - gr.min()) + 2 * h + 1, int(gc.max() - gc.min()) + 2 * h + 1,
                     _RASTER_CELL_BYTES, "one cell per angular step: check the scan's angular step "
                     "(--angular-step, prepare.angular_step_deg) or use thinner slices (slices.thickness_m)")
        lab = _label_cells(gc, gr, h)
        _, inv = np.unique(lab, return_inverse=True)
        labels[sel] = inv + offset
        offset += int(inv.max()) + 1
    return labels


def _split_by_range(labels: np.ndarray, rng_m: np.ndarray, jump: float) -> np.ndarray:
    """Split each component where the sorted ranges of its points jump by more than `jump`."""
    order = np.lexsort((rng_m, labels))
    lab, r = labels[order], rng_m[order]
    new_run = np.ones(len(lab), dtype=bool)
    new_run[1:] = (lab[1:] != lab[:-1]) | (np.diff(r) > jump)
    out = np.empty_like(labels)
    out[order] = np.cumsum(new_run) - 1
    return out


def separate_arcs(scan: Scan, indices: np.ndarray, p: ArcParams) -> ArcResult:
    """Separate the slice `indices` of `scan` into arcs by connectivity on the scan's angular grid.

    Parameters
    ----------
    scan
        The scan the slice belongs to; its own azimuth, elevation and angular steps are used.
    indices
        Indices into `scan.points` of the slice.
    p
        Connectivity factor c, smallest arc, optional range-jump split.

    Returns
    -------
    ArcResult
        A label per point of the slice; arcs are numbered by decreasing size, -1 marks points of
        arcs smaller than `p.min_points`.
    """
    idx = np.asarray(indices, dtype=np.int64)
    if len(idx) == 0:
        return ArcResult(ok=False, message="the slice holds no points of this scan", metrics=(Metric("arcs", "", 0),),
                         indices=idx, labels=np.empty(0, dtype=np.int64), n_arcs=0)
    col, row = angular_cells(scan, idx)
    raw = _label_raster(col, row, p.connectivity, f"{scan.label}: the arcs' slice raster")
    if p.max_range_jump_m is not None:
        raw = _split_by_range(raw, np.linalg.norm(scan.points[idx], axis=1), p.max_range_jump_m)
    counts = np.bincount(raw)
    big = np.flatnonzero(counts >= p.min_points)
    big = big[np.argsort(-counts[big], kind="stable")]
    remap = np.full(len(counts), -1, dtype=np.int64)
    remap[big] = np.arange(len(big))
    labels = remap[raw]
    n = int(len(big))
    metrics = (
        Metric("arcs", "", n),
        Metric("points in arcs", "", int((labels >= 0).sum())),
        Metric("points in arcs too small", "", int((labels < 0).sum())),
    )
    msg = "" if n else f"no arc of at least {p.min_points} points (arcs.min_points) in this slice"
    return ArcResult(ok=n > 0, message=msg, metrics=metrics, indices=idx, labels=labels, n_arcs=n)


@dataclass(frozen=True, kw_only=True)
class SliceArcs:
    """The arcs stage's result for one pair: every slice of both scans separated into arcs.

    Attributes
    ----------
    ok, message, metrics
        As every stage result (ok whenever the slices could be separated; a slice without arcs is
        reported in its own `ArcResult`).
    ref, tgt
        Per slice, the arcs of the reference and of the target (indices into each scan's points).
    """

    ok: bool
    message: str
    metrics: tuple[Metric, ...]
    ref: tuple[ArcResult, ...]
    tgt: tuple[ArcResult, ...]


def separate_scan_slices(scan: Scan, slice_indices: tuple[np.ndarray, ...], p: ArcParams) -> tuple[ArcResult, ...]:
    """Every slice of one scan separated into arcs (see `separate_arcs`)."""
    return tuple(separate_arcs(scan, idx, p) for idx in slice_indices)


def separate_slices(ref: Scan, tgt: Scan, ref_indices: tuple[np.ndarray, ...], tgt_indices: tuple[np.ndarray, ...],
                    *, arcs: ArcParams, ref_arcs: tuple[ArcResult, ...] | None = None) -> SliceArcs:
    """The arcs stage (paper 2.2.2): each scan's slices separated in its own angular grid.

    `ref_arcs` passes the reference's arcs when they are already known (they depend on the
    reference alone, so several targets share them).
    """
    ra = separate_scan_slices(ref, ref_indices, arcs) if ref_arcs is None else ref_arcs
    ta = separate_scan_slices(tgt, tgt_indices, arcs)
    metrics = (
        Metric("arcs, reference", "", int(sum(a.n_arcs for a in ra))),
        Metric("arcs, target", "", int(sum(a.n_arcs for a in ta))),
        Metric("slices with arcs in both scans", "", int(sum(a.n_arcs > 0 and b.n_arcs > 0 for a, b in zip(ra, ta)))),
    )
    return SliceArcs(ok=True, message="", metrics=metrics, ref=ra, tgt=ta)
