"""The plot simulator: full panoramas of a target among neighbours, shrubs and ground, and stations
that look like the real RIEGL one (millimetre rounding, second returns, density falling with range)."""

import numpy as np
import pytest

from treereg_core.errors import ConfigError
from treereg_core.simulate.plots import PlotSpec, plot_cases
from treereg_core.simulate.tree import LABEL_GROUND


@pytest.fixture(scope="module")
def plot():
    return PlotSpec(seed=1, angular_step_deg=(0.3, 0.3), plot_radius_m=15.0, real_like=True, leaves=True).build()


def test_stations_are_full_panoramas_of_the_whole_plot(plot):
    assert len(plot.trees) >= 1 + 6  # target + at least six neighbours (+ shrubs)
    for k, scan in enumerate(plot.scans):
        counts, _ = np.histogram(scan.azimuth_deg, bins=72, range=(-180, 180))
        assert (counts > 0).all(), f"{scan.name}: azimuth sectors without points (not a 360 deg station)"
        assert scan.elevation_deg.min() >= -40.5 and scan.elevation_deg.max() <= 60.5
        ids = plot.tree_ids[k]
        assert (ids == 0).sum() > 1000  # the target
        assert len(np.unique(ids[ids > 0])) >= 4  # neighbours and shrubs too
        assert (plot.labels[k] == LABEL_GROUND).mean() > 0.3


def test_real_like_stations_round_to_millimetres_and_return_twice(plot):
    for k, scan in enumerate(plot.scans):
        assert np.allclose(scan.points * 1000, np.round(scan.points * 1000), atol=1e-6)
        second = plot.return_index[k] == 1
        assert second.sum() > 100
        # a second return lies behind a first one along (nearly) the same ray
        first_r = np.linalg.norm(scan.points[~second], axis=1)
        assert np.linalg.norm(scan.points[second], axis=1).mean() > first_r.mean() * 0.5


def test_density_falls_with_range(plot):
    scan = plot.scans[0]
    ground = plot.labels[0] == LABEL_GROUND
    r = np.hypot(scan.points[ground, 0], scan.points[ground, 1])
    near, far = np.sum((r > 3) & (r < 4)) / (np.pi * (16 - 9)), np.sum((r > 9) & (r < 10)) / (np.pi * (100 - 81))
    assert near > 3 * far


def test_same_seed_same_points_and_bad_specs_are_refused():
    a = PlotSpec(seed=5, angular_step_deg=(0.5, 0.5), plot_radius_m=10.0, n_shrubs=(2, 3)).build()
    b = PlotSpec(seed=5, angular_step_deg=(0.5, 0.5), plot_radius_m=10.0, n_shrubs=(2, 3)).build()
    assert np.array_equal(a.scans[1].points, b.scans[1].points)
    with pytest.raises(ConfigError, match="neighbour_distance_m"):
        PlotSpec(neighbour_distance_m=(0.5, 3.0))
    assert len(plot_cases(4, small=True)) == 4
