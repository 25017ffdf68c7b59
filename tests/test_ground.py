"""Preparing scans: ground removal (kept away from scans without ground) and crops."""

import numpy as np

from treereg_core.prepare.ground import prepare_scan
from treereg_core.params import PrepareParams
from treereg_core.scan import Scan
from treereg_core.simulate.cases import simulate_case
from treereg_core.simulate.tree import LABEL_GROUND


def test_ground_of_a_simulated_scan_is_removed_and_the_tree_kept():
    case = simulate_case(seed=3, angular_step_deg=(0.25, 0.25), height_m=8.0, ground=True, tilt_deg=0.5)
    for scan, labels in zip(case.scans, case.labels):
        prep = prepare_scan(scan, prepare=PrepareParams())
        assert prep.ok and prep.plane is not None
        is_ground = labels == LABEL_GROUND
        assert prep.ground_mask[is_ground].mean() > 0.98
        # only the tree's lowest band (ground_band_m) goes with the ground: all of it above is kept
        height = scan.points @ np.array(prep.plane[:3]) + prep.plane[3]
        above = ~is_ground & (height > PrepareParams().ground_band_m + 0.05)
        assert prep.kept_mask[above].mean() > 0.999
        assert prep.kept_mask[~is_ground].mean() > 0.9
        assert prep.scan.n_points == prep.kept_mask.sum()
        assert np.allclose(prep.scan.points, scan.points[prep.kept_mask])


def test_scan_without_ground_is_left_alone():
    case = simulate_case(seed=4, angular_step_deg=(0.25, 0.25), height_m=8.0, ground=False)
    prep = prepare_scan(case.scans[0], prepare=PrepareParams())
    assert prep.ok and prep.plane is None and not prep.ground_mask.any() and prep.kept_mask.all()
    assert any("no ground" in str(m.value) for m in prep.metrics)


def test_the_ground_height_below_a_point_lies_on_the_ground_found():
    """`PreparedScan.ground_z` (where the app stands the stem markers): the simulated ground's own
    points lie at it (within a centimetre); without a plane it is the default given."""
    case = simulate_case(seed=3, angular_step_deg=(0.25, 0.25), height_m=8.0, ground=True, tilt_deg=0.5)
    scan, labels = case.scans[0], case.labels[0]
    prep = prepare_scan(scan, prepare=PrepareParams())
    ground = scan.points[labels == LABEL_GROUND]
    assert np.median(np.abs(prep.ground_z(ground[:, :2], 0.0) - ground[:, 2])) < 0.01
    bare = prepare_scan(simulate_case(seed=4, angular_step_deg=(0.25, 0.25), height_m=8.0, ground=False).scans[0],
                        prepare=PrepareParams())
    assert np.array_equal(bare.ground_z(np.zeros((3, 2)), -1.5), np.full(3, -1.5))


def test_crop_radius_and_heights():
    rng = np.random.default_rng(0)
    stem = np.column_stack([10 + 0.15 * rng.standard_normal(3000), 2 + 0.15 * rng.standard_normal(3000),
                            rng.uniform(-1.5, 6, 3000)])
    far = np.column_stack([rng.uniform(15, 18, 500), rng.uniform(-3, 3, 500), rng.uniform(-1.5, 6, 500)])
    scan = Scan.from_points(np.vstack([stem, far]), "s", angular_step_deg=(0.1, 0.1))
    prep = prepare_scan(scan, prepare=PrepareParams(remove_ground=False, crop_radius_m=2.0, crop_z_max_m=5.0))
    assert prep.ok and prep.stem_xy is not None
    assert np.hypot(prep.stem_xy[0] - 10, prep.stem_xy[1] - 2) < 0.2
    assert prep.kept_mask[3000:].sum() == 0
    assert (prep.scan.points[:, 2] <= 5.0).all()


def test_crop_that_leaves_nothing_is_a_result_not_an_exception():
    rng = np.random.default_rng(1)
    scan = Scan.from_points(rng.uniform(0, 5, (1000, 3)), "s", angular_step_deg=(0.1, 0.1))
    prep = prepare_scan(scan, prepare=PrepareParams(remove_ground=False, crop_z_min_m=100.0))
    assert not prep.ok and "crop" in prep.message
