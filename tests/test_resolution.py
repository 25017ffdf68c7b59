"""The working resolution: dense scans reduced once, to better points, and coarse scans left alone."""

from __future__ import annotations

import numpy as np

from test_scan import grid_scan
from treereg_core.geometry.rigid import mean_displacement
from treereg_core.params import Params, ResolutionParams
from treereg_core.pipeline import register
from treereg_core.prepare.resolution import merge_cells, working_resolution
from treereg_core.scan import Scan
from treereg_core.simulate.cases import simulate_case


def dense_trunk(step: float, sigma_m: float = 0.003, seed: int = 4) -> np.ndarray:
    """A trunk (axis at x = 8 m, y = 0, radius 0.3 m) scanned on a fine (step x step) grid over a
    small window, 3 mm range noise along the ray."""
    rng = np.random.default_rng(seed)
    a, b = np.meshgrid(np.radians(np.arange(-3.0, 3.0, step)), np.radians(np.arange(0.0, 10.0, step)))
    a, b = a.ravel(), b.ravel()
    d = np.column_stack([np.cos(b) * np.cos(a), np.cos(b) * np.sin(a), np.sin(b)])
    qa = d[:, 0] ** 2 + d[:, 1] ** 2
    qb = -2 * d[:, 0] * 8.0
    disc = qb ** 2 - 4 * qa * (64.0 - 0.09)
    hit = disc > 0
    t = (-qb[hit] - np.sqrt(disc[hit])) / (2 * qa[hit])
    return d[hit] * (t + rng.normal(0.0, sigma_m, hit.sum()))[:, None]


def _radial_noise(pts: np.ndarray) -> float:
    """Std of the distance to the trunk's axis (x, y) = (8, 0), r = 0.3, over the trunk's points."""
    d = np.hypot(pts[:, 0] - 8.0, pts[:, 1]) - 0.3
    return float(d.std())


def test_a_dense_scan_is_reduced_to_fewer_and_better_points():
    raw = Scan.from_points(dense_trunk(0.01), "dense.ply", angular_step_deg=(0.01, 0.01))
    work = working_resolution(raw, resolution=ResolutionParams(spacing_m=0.01, depth_m=0.02))
    assert work.reduced and work.scan.name == "dense.ply"
    step = work.step_deg[0]
    assert work.scan.angular_step_deg == work.step_deg and step > 4 * 0.01  # 1 cm at 8 m: 0.07 deg
    # One point per cell of the working step: as many as a scanner at that step would give.
    assert 0.5 * raw.n_points * (0.01 / step) ** 2 < work.scan.n_points < 1.3 * raw.n_points * (0.01 / step) ** 2
    # Cells average the range noise of their points: the trunk's surface is sharper, not just sparser.
    assert _radial_noise(work.scan.points) < 0.6 * _radial_noise(raw.points)
    metrics = {m.description: m.value for m in work.metrics}
    assert metrics["points as read"] == raw.n_points and metrics["points at the working step"] == work.scan.n_points


def test_coarse_scans_and_spacing_off_keep_every_point():
    coarse = Scan.from_points(grid_scan(0.1, 0.1, seed=5), "coarse.ply", angular_step_deg=(0.1, 0.1))
    for p in (ResolutionParams(), ResolutionParams(spacing_m=None)):
        work = working_resolution(coarse, resolution=p)
        assert not work.reduced and work.scan is coarse


def test_a_cell_averages_its_front_points_only():
    # Two cells: one with three returns on a stem at 5 m and one behind it at 9 m; one single point.
    pts = np.array([[5.0, 0.0, 0.0], [5.01, 0.0, 0.0], [4.99, 0.0, 0.0], [9.0, 0.0, 0.0], [5.0, 1.0, 0.0]])
    alpha = np.array([0.0, 0.001, 0.002, 0.001, 11.3])
    beta = np.zeros(5)
    out = merge_cells(pts, alpha, beta, (0.1, 0.1), depth_m=0.05)
    np.testing.assert_allclose(out, [[5.0, 0.0, 0.0], [5.0, 1.0, 0.0]], atol=1e-12)


def test_a_dense_case_registers_at_the_working_resolution():
    case = simulate_case(seed=11, angular_step_deg=0.03, height_m=7.0, orders=2, station_distance_m=(6.0, 8.0))
    reg = register(case.scans, Params())
    prep = reg.pipeline.output("prepare").items
    assert all(p.scan.n_points < 0.5 * s.n_points for p, s in zip(prep, case.scans))  # reduced
    for k in (1, 2):
        T = reg.transforms[case.scans[k].name]
        assert mean_displacement(T, case.T_ref_scan[k], case.scans[k].points) < 0.003
