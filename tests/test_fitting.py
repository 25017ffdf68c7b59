"""Circle and cylinder fits against the model itself: points on a known circle or cylinder, partial
arcs, seeded noise; fit; compare (as scikit-image's measure.fit tests do)."""

import numpy as np
import pytest

from treereg_core.fine.fitting import (
    CylinderFit,
    Section,
    arc_coverage_deg,
    check_taper,
    fit_circle_taubin,
    fit_cylinder,
    judge_fit,
)
from treereg_core.params import SectionsParams


def _circle(centre, r, a0, a1, n, sigma, rng):
    t = rng.uniform(np.radians(a0), np.radians(a1), n)
    return np.c_[centre[0] + r * np.cos(t), centre[1] + r * np.sin(t)] + rng.normal(0, sigma, (n, 2))


def _cylinder(point, axis, r, length, arc_deg, n, sigma, rng):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    e1 = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    s = rng.uniform(-length / 2, length / 2, n)
    t = rng.uniform(0, np.radians(arc_deg), n)
    pts = np.asarray(point) + np.outer(s, a) + r * (np.outer(np.cos(t), e1) + np.outer(np.sin(t), e2))
    return pts + rng.normal(0, sigma, pts.shape)


@pytest.mark.parametrize("arc", [360, 180, 120])
def test_taubin_recovers_centre_and_radius_of_partial_arcs(arc):
    rng = np.random.default_rng(arc)
    xy = _circle((2.0, -1.0), 0.25, 0, arc, 200, 0.002, rng)
    fit = fit_circle_taubin(xy)
    assert fit.ok
    assert np.linalg.norm(fit.centre_m - [2.0, -1.0]) < 0.01
    assert abs(fit.radius_m - 0.25) < 0.01
    assert fit.rms_m == pytest.approx(0.002, abs=0.001)
    assert fit.arc_deg == pytest.approx(arc, abs=15)


def test_taubin_flags_degenerate_input():
    assert not fit_circle_taubin(np.array([[0.0, 0.0], [1.0, 1.0]])).ok
    line = np.c_[np.linspace(0, 1, 20), np.linspace(0, 1, 20)]
    fit = fit_circle_taubin(line)
    assert not fit.ok and fit.reason == "points are collinear"  # a circle of infinite radius: refused
    assert np.isnan(fit.radius_m) and not fit.plausible


@pytest.mark.parametrize("axis,arc,length", [((0, 0, 1), 150, 0.1), ((0.6, 0.2, 0.7), 180, 0.4), ((1, 0.3, 0.2), 140, 0.6)])
def test_cylinder_fit_recovers_axis_and_radius(axis, arc, length):
    rng = np.random.default_rng(int(arc))
    point = np.array([1.0, 2.0, 3.0])
    pts = _cylinder(point, axis, 0.12, length, arc, 400, 0.002, rng)
    fit = fit_cylinder(pts)
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    assert fit.ok
    assert abs(fit.axis @ a) > np.cos(np.radians(3))
    assert fit.axis[2] >= 0  # the positive direction increases z (paper 2.2.3)
    assert abs(fit.radius_m - 0.12) < 0.01
    # The fitted axis passes within a few mm of the true one.
    d = fit.point_m - point
    assert np.linalg.norm(d - (d @ a) * a) < 0.01
    assert fit.arc_deg == pytest.approx(arc, abs=20)


def test_cylinder_fit_without_refinement_is_close_and_refinement_improves_it():
    rng = np.random.default_rng(5)
    pts = _cylinder([0, 0, 0], (0.5, 0.1, 0.8), 0.05, 0.3, 160, 300, 0.002, rng)
    rough = fit_cylinder(pts, refine=False)
    fine = fit_cylinder(pts)
    assert abs(rough.radius_m - 0.05) < 0.02
    assert fine.rms_m <= rough.rms_m + 1e-9
    assert abs(fine.radius_m - 0.05) < 0.005


def test_judge_fit_rejects_small_arcs_large_residuals_and_radii():
    p = SectionsParams(min_arc_deg=45, max_rms_m=0.01, max_radius_m=0.5)
    rng = np.random.default_rng(3)
    good = judge_fit(fit_circle_taubin(_circle((0, 0), 0.2, 0, 150, 100, 0.002, rng)), p)
    assert good.plausible and good.reason == ""
    short = judge_fit(fit_circle_taubin(_circle((0, 0), 0.2, 0, 20, 100, 0.0005, rng)), p)
    assert not short.plausible and "arc" in short.reason
    noisy = judge_fit(fit_circle_taubin(_circle((0, 0), 0.2, 0, 200, 100, 0.03, rng)), p)
    assert not noisy.plausible and "RMS" in noisy.reason


def test_arc_coverage():
    assert arc_coverage_deg(np.radians(np.arange(0, 360, 10))) == pytest.approx(350)
    assert arc_coverage_deg(np.radians([0, 90])) == pytest.approx(90)
    assert arc_coverage_deg(np.radians([350, 10])) == pytest.approx(20)


def _section(k, h, centre, r):
    fit = CylinderFit(True, np.array(centre, float), np.array([0, 0, 1.0]), r, 0.001, 180.0, 50, 0.1)
    return Section(k, 0, h, fit, np.array([centre[0], centre[1], h], float), np.array([0, 0, 1.0]), r, True, "")


def test_taper_check_drops_a_part_wider_than_the_part_below():
    # Paper 4.2: three arcs merged at Q2 look like one wide arc above a thinner stem.
    below = _section(0, 1.0, (0, 0, 1.0), 0.15)
    merged = _section(1, 2.0, (0.02, 0, 2.0), 0.30)
    elsewhere = _section(1, 2.0, (3.0, 0, 2.0), 0.30)  # no part below it: kept
    out = check_taper([below, merged, elsewhere], tolerance=0.0, gate_m=0.3)
    assert out[0].plausible and not out[1].plausible and out[2].plausible
    assert "4.2" in out[1].reason
    # A tolerance lets the natural scatter of partial-arc radii through.
    assert check_taper([below, _section(1, 2.0, (0, 0, 2.0), 0.16)], tolerance=0.3, gate_m=0.3)[1].plausible
