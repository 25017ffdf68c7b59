"""Arc separation by angular connectivity (paper 2.2.2) on scans ray-cast from vertical stems."""

import numpy as np

from treereg_core.fine.arcs import separate_arcs
from treereg_core.params import ArcParams
from treereg_core.scan import Scan

STEP = 0.1  # degrees, both directions


def _scan_stems(stems, azimuth_deg=(-15.0, 15.0), elevation_deg=(-0.4, 0.4)):
    """Ray-cast vertical stems (x, y, radius) from the origin on a regular angular grid.

    Returns the scan and, per point, which stem it hit.
    """
    a = np.radians(np.arange(*azimuth_deg, STEP))
    b = np.radians(np.arange(*elevation_deg, STEP))
    A, B = np.meshgrid(a, b)
    d = np.c_[(np.cos(B) * np.cos(A)).ravel(), (np.cos(B) * np.sin(A)).ravel(), np.sin(B).ravel()]
    h = np.hypot(d[:, 0], d[:, 1])
    best = np.full(len(d), np.inf)
    which = np.full(len(d), -1)
    for k, (x, y, r) in enumerate(stems):
        # Ray-circle intersection in the horizontal plane, parameterised by horizontal distance.
        u = d[:, :2] / h[:, None]
        proj = u @ np.array([x, y])
        disc = proj ** 2 - (x * x + y * y - r * r)
        t = np.where(disc > 0, proj - np.sqrt(np.maximum(disc, 0)), np.inf)
        hit = (t > 0) & (t < best)
        best[hit], which[hit] = t[hit], k
    ok = np.isfinite(best)
    pts = d[ok] * (best[ok] / h[ok])[:, None]
    return Scan.from_points(pts, "stems", angular_step_deg=(STEP, STEP)), which[ok]


def _purity(res, which):
    """For each arc, the fraction of its points that hit its majority stem."""
    out = []
    for k in range(res.n_arcs):
        w = which[res.labels == k]
        out.append(np.bincount(w).max() / len(w))
    return out


def test_two_nearby_stems_are_two_arcs():
    # Two stems 10 m away with an 8 cm gap between them: 0.46 deg, more than 3 steps of 0.1 deg.
    scan, which = _scan_stems([(10.0, -0.19, 0.15), (10.0, 0.19, 0.15)])
    res = separate_arcs(scan, np.arange(scan.n_points), ArcParams(connectivity=3.0, min_points=5))
    assert res.ok and res.n_arcs == 2
    assert min(_purity(res, which)) == 1.0
    assert (res.labels >= 0).all()
    arcs = res.arcs()
    assert sorted(len(a) for a in arcs) == sorted(np.bincount(which).tolist())


def test_stems_closer_than_the_connectivity_merge_as_in_the_paper():
    # A 2 cm gap is 0.11 deg, within 3 steps: the paper's rule joins them (its Fig. 19 problem).
    scan, _ = _scan_stems([(10.0, -0.16, 0.15), (10.0, 0.16, 0.15)])
    assert separate_arcs(scan, np.arange(scan.n_points), ArcParams(connectivity=3.0, min_points=5)).n_arcs == 1
    # A connectivity of one step keeps them apart.
    assert separate_arcs(scan, np.arange(scan.n_points), ArcParams(connectivity=1.0, min_points=5)).n_arcs == 2


def test_a_stem_behind_another_is_split_by_the_range_jump():
    # The far stem peeks out beside the near one: angular neighbours, 3 m apart in range.
    scan, which = _scan_stems([(8.0, 0.0, 0.15), (11.0, 0.3, 0.2)])
    idx = np.arange(scan.n_points)
    paper = separate_arcs(scan, idx, ArcParams(connectivity=3.0, min_points=5, max_range_jump_m=None))
    ours = separate_arcs(scan, idx, ArcParams(connectivity=3.0, min_points=5, max_range_jump_m=0.3))
    assert paper.n_arcs == 1
    assert ours.n_arcs == 2 and min(_purity(ours, which)) == 1.0


def test_small_arcs_are_dropped_and_a_subset_of_indices_is_respected():
    scan, which = _scan_stems([(10.0, -0.5, 0.15), (10.0, 0.5, 0.01)])
    idx = np.arange(scan.n_points)
    res = separate_arcs(scan, idx, ArcParams(connectivity=3.0, min_points=15))
    assert res.n_arcs == 1
    assert (res.labels[which == 1] == -1).all()
    sub = idx[which == 0][::2]
    res_sub = separate_arcs(scan, sub, ArcParams(connectivity=3.0, min_points=5))
    assert res_sub.n_arcs == 1 and np.array_equal(np.sort(res_sub.arc(0)), np.sort(sub))


def test_an_arc_across_the_azimuth_seam_stays_whole():
    # The stem straddles alpha = +-180 deg in the scanner frame.
    scan, _ = _scan_stems([(-10.0, 0.0, 0.2)], azimuth_deg=(175.0, 185.0))
    assert scan.azimuth_deg.max() > 179 and scan.azimuth_deg.min() < -179
    assert separate_arcs(scan, np.arange(scan.n_points), ArcParams(min_points=5)).n_arcs == 1


def test_empty_slice_is_not_ok():
    scan, _ = _scan_stems([(10.0, 0.0, 0.2)])
    res = separate_arcs(scan, np.array([], dtype=int), ArcParams())
    assert not res.ok and res.n_arcs == 0 and "no points" in res.message
