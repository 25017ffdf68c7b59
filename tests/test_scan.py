"""Scan and angular-step estimation against known instrument steps."""

from __future__ import annotations

import numpy as np
import pytest

from treereg_core.prepare.angular_step import estimate_angular_step
from treereg_core.errors import ScanError
from treereg_core.geometry.rigid import rotation_z
from treereg_core.scan import MIN_POINTS, Scan, spherical_angles_deg
from treereg_core.simulate.cases import simulate_case


def grid_scan(phi: float, varphi: float, seed: int = 0, dropout: float = 0.05, sigma_m: float = 0.003,
              heading_deg: float = 0.0) -> np.ndarray:
    """Ray-cast a regular (phi, varphi) grid onto a trunk-like cylinder, a thin pole in front of it
    (an occlusion shadow) and a second stem behind; 3 mm range noise along the ray, random dropouts."""
    rng = np.random.default_rng(seed)
    cylinders = [(8.0, 0.0, 0.3, 9.0), (5.0, 0.5, 0.06, 4.0), (11.0, -1.2, 0.25, 7.0)]  # x, y, r, top (m)
    a, b = np.meshgrid(np.radians(np.arange(-7.0, 7.0, phi)), np.radians(np.arange(-10.0, 45.0, varphi)))
    a, b = a.ravel(), b.ravel()
    d = np.column_stack([np.cos(b) * np.cos(a), np.cos(b) * np.sin(a), np.sin(b)])
    t = np.full(len(d), np.inf)
    for cx, cy, r, top in cylinders:
        qa = d[:, 0] ** 2 + d[:, 1] ** 2
        qb = -2 * (d[:, 0] * cx + d[:, 1] * cy)
        disc = qb**2 - 4 * qa * (cx**2 + cy**2 - r**2)
        tt = (-qb - np.sqrt(np.maximum(disc, 0))) / (2 * qa)
        z = tt * d[:, 2]
        hit = (disc > 0) & (tt > 0) & (z > -1.5) & (z < top)
        t = np.where(hit & (tt < t), tt, t)
    keep = np.isfinite(t) & (rng.random(len(t)) >= dropout)
    pts = d[keep] * (t[keep] + rng.normal(0.0, sigma_m, keep.sum()))[:, None]
    return pts @ rotation_z(heading_deg).T


def rel_err(est: tuple[float, float], true: tuple[float, float]) -> np.ndarray:
    return np.abs(np.asarray(est) / np.asarray(true) - 1.0)


@pytest.mark.parametrize("step", [0.04, 0.1, 0.25])
def test_step_estimated_within_10_percent_on_simulated_scans(step):
    case = simulate_case(seed=3, n_stations=1, angular_step_deg=step, height_m=6.0, dropout=0.05)
    scan = case.scans[0]
    est = estimate_angular_step(scan.azimuth_deg, scan.elevation_deg)
    assert rel_err(est, (step, step)).max() < 0.10, est


@pytest.mark.parametrize("step", [0.04, 0.1, 0.25])
def test_step_estimated_on_grid_with_dropouts_noise_and_occlusion(step):
    pts = grid_scan(step, step, seed=1)
    est = estimate_angular_step(*spherical_angles_deg(pts))
    assert rel_err(est, (step, step)).max() < 0.10, est


@pytest.mark.parametrize("phi, varphi", [(0.04, 0.25), (0.25, 0.04), (0.1, 0.05), (1.0, 0.04)])
def test_step_estimated_when_horizontal_and_vertical_steps_differ(phi, varphi):
    pts = grid_scan(phi, varphi, seed=2)
    est = estimate_angular_step(*spherical_angles_deg(pts))
    assert rel_err(est, (phi, varphi)).max() < 0.10, est


def test_step_estimated_on_simulated_scan_with_unequal_steps_tilt_and_leaves():
    case = simulate_case(seed=4, n_stations=1, angular_step_deg=(0.1, 0.05), height_m=6.0,
                         tilt_deg=3.0, leaves=True, ground=True)
    scan = case.scans[0]
    est = estimate_angular_step(scan.azimuth_deg, scan.elevation_deg)
    assert rel_err(est, (0.1, 0.05)).max() < 0.10, est


def test_step_estimated_when_the_tree_straddles_the_azimuth_seam():
    # heading 180: the tree sits at azimuth +-180, where alpha jumps by 360 deg
    pts = grid_scan(0.1, 0.1, seed=5, heading_deg=180.0)
    alpha, _ = spherical_angles_deg(pts)
    assert alpha.min() < -170 and alpha.max() > 170
    est = estimate_angular_step(*spherical_angles_deg(pts))
    assert rel_err(est, (0.1, 0.1)).max() < 0.10, est


def test_estimate_refuses_points_without_a_grid():
    with pytest.raises(ValueError, match="too few"):
        estimate_angular_step(np.arange(10.0), np.zeros(10))
    # a single column: no horizontal neighbours exist, so phi cannot be known
    beta = np.arange(0, 20, 0.1)
    with pytest.raises(ValueError, match="regular angular grid"):
        estimate_angular_step(np.zeros_like(beta), beta)


def test_from_points_estimates_the_steps_and_computes_angles_once():
    pts = grid_scan(0.25, 0.1, seed=6)
    scan = Scan.from_points(pts, name="s.ply")
    assert scan.step_estimated
    assert rel_err(scan.angular_step_deg, (0.25, 0.1)).max() < 0.10
    alpha, beta = spherical_angles_deg(pts)
    np.testing.assert_allclose(scan.azimuth_deg, alpha)
    np.testing.assert_allclose(scan.elevation_deg, beta)
    with pytest.raises(ValueError):
        scan.points[0, 0] = 1.0  # read-only
    given = Scan.from_points(pts, name="s.ply", angular_step_deg=(0.2, 0.2))
    assert given.angular_step_deg == (0.2, 0.2) and not given.step_estimated
    cropped = given.with_points(pts[:500])
    assert cropped.angular_step_deg == (0.2, 0.2) and cropped.n_points == 500


def test_spherical_angles_follow_the_paper_convention():
    pts = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [1.0, 0.0, 1.0], [-1.0, 0.0, -1.0]])
    alpha, beta = spherical_angles_deg(pts)
    np.testing.assert_allclose(alpha, [0.0, 90.0, 0.0, 180.0])
    np.testing.assert_allclose(beta, [0.0, 0.0, 45.0, -45.0])


def test_from_points_errors_name_the_scan():
    with pytest.raises(ScanError, match=r"^tree\.ply: only 5 points; at least 100"):
        Scan.from_points(np.ones((5, 3)), name="tree.ply")
    with pytest.raises(ScanError, match=r"N x 3"):
        Scan.from_points(np.ones((200, 2)), name="tree.ply")
    bad = np.ones((MIN_POINTS, 3))
    bad[3, 1] = np.nan
    with pytest.raises(ScanError, match="NaN"):
        Scan.from_points(bad, name="tree.ply", angular_step_deg=(0.1, 0.1))
    beta = np.arange(0, 30, 0.1)
    column = np.column_stack([np.cos(np.radians(beta)), np.zeros_like(beta), np.sin(np.radians(beta))]) * 5
    with pytest.raises(ScanError, match=r"^/data/col\.ply: cannot estimate the angular step"):
        Scan.from_points(column, name="col.ply", source="/data/col.ply")
    with pytest.raises(ScanError, match=r"angular steps 0 x 0\.1 deg are outside the allowed range \(0\.001 to 1 deg\)"):
        Scan.from_points(column, name="col.ply", angular_step_deg=(0.0, 0.1))
