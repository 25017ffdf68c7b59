"""Which section of the target is which section of the reference (fine registration, step 4).

After coarse registration the same stem or branch appears in both scans close to the same place.
Sections correspond one-to-one, nearest centres first, and only when their centres are within a
gate in metres; sections of different slices never correspond. The assignment minimises the sum
of distances (`scipy.optimize.linear_sum_assignment`), which equals "nearest centres" whenever the
nearest choices do not compete, and resolves them consistently when they do.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..results import Metric

#: Cost given to forbidden pairs (beyond the gate or in different slices); never chosen over a real one.
_FORBIDDEN = 1e6


@dataclass(frozen=True)
class Correspondences:
    """Corresponding sections.

    Attributes
    ----------
    ok, message, metrics
        As every stage result; `ok` is False when no pair is within the gate.
    pairs
        K x 2 ints: (index into the reference's sections, index into the target's sections).
    distances_m
        Distance between the two centres of each pair.
    """

    ok: bool
    message: str
    metrics: tuple[Metric, ...]
    pairs: np.ndarray
    distances_m: np.ndarray


def match_sections(ref_centres: np.ndarray, tgt_centres: np.ndarray, gate_m: float,
                   ref_groups: np.ndarray | None = None, tgt_groups: np.ndarray | None = None,
                   ref_radii: np.ndarray | None = None, tgt_radii: np.ndarray | None = None,
                   max_radius_ratio: float | None = None) -> Correspondences:
    """One-to-one matching of section centres (both in the reference frame), gated in metres.

    Parameters
    ----------
    ref_centres, tgt_centres
        N x 3 and M x 3 centres (rows with NaN never match).
    gate_m
        Largest centre distance of a pair.
    ref_groups, tgt_groups
        Optional group per centre (the slice index); only equal groups may correspond.
    ref_radii, tgt_radii, max_radius_ratio
        Optional radii; when given with a ratio, sections whose radii differ by more than that
        factor never correspond (a stem is not a twig, however close their centres).

    Returns
    -------
    Correspondences
    """
    a = np.asarray(ref_centres, dtype=float).reshape(-1, 3)
    b = np.asarray(tgt_centres, dtype=float).reshape(-1, 3)
    empty = Correspondences(False, f"no pair of sections within {gate_m} m (sections.gate_m)",
                            (Metric("corresponding sections", "", 0),), np.empty((0, 2), dtype=np.int64),
                            np.empty(0))
    if len(a) == 0 or len(b) == 0:
        return empty
    d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2)
    cost = np.where(np.isfinite(d) & (d <= gate_m), d, _FORBIDDEN)
    if ref_groups is not None and tgt_groups is not None:
        cost = np.where(np.asarray(ref_groups)[:, None] == np.asarray(tgt_groups)[None, :], cost, _FORBIDDEN)
    if ref_radii is not None and tgt_radii is not None and max_radius_ratio is not None:
        ra, rb = np.asarray(ref_radii, dtype=float), np.asarray(tgt_radii, dtype=float)
        ratio = np.maximum(ra[:, None], rb[None, :]) / np.maximum(np.minimum(ra[:, None], rb[None, :]), 1e-9)
        cost = np.where(ratio <= max_radius_ratio, cost, _FORBIDDEN)
    rows, cols = linear_sum_assignment(cost)
    keep = cost[rows, cols] < _FORBIDDEN
    rows, cols = rows[keep], cols[keep]
    if len(rows) == 0:
        return empty
    dist = d[rows, cols]
    metrics = (
        Metric("corresponding sections", "", int(len(rows))),
        Metric("median centre distance", "m", float(np.median(dist))),
    )
    return Correspondences(True, "", metrics, np.c_[rows, cols].astype(np.int64), dist)
