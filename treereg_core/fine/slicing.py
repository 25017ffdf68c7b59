"""Horizontal slices of the reference and the target after coarse registration (paper 2.2.1).

The paper slices both scans at the quartiles of tree height, 10 cm thick. Heights are taken in the
reference frame: the tree's vertical extent is read from the reference scan's points, and each
target point is mapped by the current transform before its height is compared. Which points fall
into a slice is all this step decides; separating them into arcs happens in each scan's own
angular grid (`arcs.py`), so a slice keeps *indices* into each scan, not copied points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..params import SlicesParams
from ..results import Metric
from ..geometry.rigid import apply_transform
from ..scan import Scan

#: The tree's vertical extent ignores this fraction of the lowest and highest points (stray returns).
_EXTENT_TRIM = 0.001


@dataclass(frozen=True, kw_only=True)
class SliceResult:
    """Slices of both scans at the same heights of the reference frame.

    Attributes
    ----------
    ok, message, metrics
        As every stage result; `ok` is False when no slice holds points of both scans.
    heights_m
        Slice centre heights z in the reference frame, ascending (one per slice).
    thickness_m
        Slice thickness; a slice holds the points with |z - height| <= thickness / 2.
    z_extent_m
        (lowest, highest) z of the tree in the reference frame, from which the quantiles are taken.
    ref_indices, tgt_indices
        Per slice, indices into `ref.points` and into `tgt.points` of the points in that slice.
    """

    ok: bool
    message: str
    metrics: tuple[Metric, ...]
    heights_m: np.ndarray
    thickness_m: float
    z_extent_m: tuple[float, float]
    ref_indices: tuple[np.ndarray, ...]
    tgt_indices: tuple[np.ndarray, ...]

    @property
    def n_slices(self) -> int:
        return int(len(self.heights_m))


def tree_extent(z: np.ndarray) -> tuple[float, float]:
    """Lowest and highest z of a tree, ignoring a sliver of stray returns at either end."""
    lo, hi = np.quantile(z, [_EXTENT_TRIM, 1.0 - _EXTENT_TRIM])
    return float(lo), float(hi)


def slice_heights(z_extent: tuple[float, float], quantiles: tuple[float, ...]) -> np.ndarray:
    """Heights at the given quantiles of the tree's height (paper: quartiles 0.25, 0.5, 0.75)."""
    lo, hi = z_extent
    q = np.clip(np.sort(np.asarray(quantiles, dtype=float)), 0.0, 1.0)
    return lo + q * (hi - lo)


def _band_members(z: np.ndarray, heights: np.ndarray, half: float) -> tuple[np.ndarray, ...]:
    """Indices of `z` within `half` of each height, without a Python loop over points.

    Sorting once and cutting with `searchsorted` costs O(N log N) however many slices there are.
    """
    order = np.argsort(z, kind="stable")
    zs = z[order]
    lo = np.searchsorted(zs, heights - half, side="left")
    hi = np.searchsorted(zs, heights + half, side="right")
    return tuple(np.sort(order[a:b]) for a, b in zip(lo, hi))


def slice_scans(ref: Scan, tgt: Scan, T_ref_target: np.ndarray, *, slices: SlicesParams) -> SliceResult:
    """Slice `ref` and `tgt` (mapped by `T_ref_tgt`) at quantiles of the reference tree's height.

    Parameters
    ----------
    ref, tgt
        The reference scan and the target scan, each in its own scanner frame.
    T_ref_target
        Current 4x4 estimate mapping target points into the reference frame (coarse, or the
        previous fine iteration).
    slices
        Slice heights (quantiles of tree height) and thickness.

    Returns
    -------
    SliceResult
        Per slice, indices into each scan's points.
    """
    p = slices
    z_ref = ref.points[:, 2]
    z_tgt = apply_transform(np.asarray(T_ref_target, dtype=float), tgt.points)[:, 2]
    extent = tree_extent(z_ref)
    heights = slice_heights(extent, p.quantiles)
    half = p.thickness_m / 2.0
    ref_idx = _band_members(z_ref, heights, half)
    tgt_idx = _band_members(z_tgt, heights, half)
    both = sum(1 for a, b in zip(ref_idx, tgt_idx) if len(a) and len(b))
    ok = both > 0
    msg = "" if ok else (
        "no slice holds points of both scans: the coarse transform may be far off, or the slices "
        "(slices.quantiles, slices.thickness_m) miss the overlap of the two scans"
    )
    metrics = (
        Metric("slices", "", len(heights)),
        Metric("slices with points of both scans", "", both),
        Metric("tree height (reference)", "m", extent[1] - extent[0]),
        Metric("sliced points, reference", "", int(sum(len(a) for a in ref_idx))),
        Metric("sliced points, target", "", int(sum(len(b) for b in tgt_idx))),
    )
    return SliceResult(ok=ok, message=msg, metrics=metrics, heights_m=heights, thickness_m=float(p.thickness_m),
                       z_extent_m=extent, ref_indices=ref_idx, tgt_indices=tgt_idx)
