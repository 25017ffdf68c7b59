"""ORB input images, keypoint snapping, the beta check (4.1) and image similarity."""

import numpy as np
import pytest

from treereg_core.coarse import similarity
from treereg_core.coarse.features import beta_check, detect, match, orb_input, snap_to_occupied
from treereg_core.params import MatchingParams, ProjectionParams
from treereg_core.coarse.projection import EMPTY, OCCUPIED, wrap_deg
from treereg_core.coarse.sequences import build_sequence
from treereg_core.simulate.cases import simulate_case


def _image_with_branches() -> np.ndarray:
    im = np.full((120, 90), EMPTY, dtype=np.uint8)
    im[10:110, 44:47] = OCCUPIED                   # trunk
    for r0, dc in ((40, 1), (60, -1), (80, 1)):     # three branches
        for t in range(30):
            im[r0 - t // 2, 45 + dc * t] = OCCUPIED
    return im


def test_ramp_is_zero_on_occupied_pixels_and_saturates_far_away():
    im = _image_with_branches()
    ramp = orb_input(im, "ramp", 8.0)
    assert (ramp[im == OCCUPIED] == 0).all()
    assert ramp[5, 5] == 255 and 0 < ramp[50, 49] < 255
    assert np.array_equal(orb_input(im, "binary", 8.0), im)


def test_keypoints_snap_to_the_nearest_occupied_pixel_or_are_dropped():
    im = _image_with_branches()
    xy = np.array([[48.0, 20.0], [45.0, 20.0], [80.0, 100.0]])  # 2 px right of the trunk, on it, far
    rc, found = snap_to_occupied(im, xy, 3)
    assert found.tolist() == [True, True, False]
    assert rc[0].tolist() == [20, 46] and rc[1].tolist() == [20, 45]
    assert (im[rc[found, 0], rc[found, 1]] == OCCUPIED).all()


def test_orb_features_lie_on_occupied_pixels_and_match_a_shifted_copy():
    im = _image_with_branches()
    shifted = np.full_like(im, EMPTY)
    shifted[:, 5:] = im[:, :-5]
    p = MatchingParams()
    fa, fb = detect(im, p), detect(shifted, p)
    assert len(fa) > 10
    assert (im[fa.pixel_rc[:, 0], fa.pixel_rc[:, 1]] == OCCUPIED).all()
    ia, ib, ham = match(fa, fb, 20)
    assert np.all(np.diff(ham) >= 0)
    shift = fb.xy[ib] - fa.xy[ia]
    assert np.median(np.abs(shift[:, 0] - 5.0)) < 1.0 and np.median(np.abs(shift[:, 1])) < 1.0


def test_beta_check_keeps_matches_within_one_sd_of_the_mean():
    b1 = np.full(6, 10.0)
    # d = 0 3 3 3 3 6: mean 3, sd sqrt(3) = 1.73 -> keep d in (1.27, 4.73), both ends go
    keep = beta_check(b1, b1 + np.array([0.0, 3.0, -3.0, 3.0, -3.0, 6.0]))
    assert keep.tolist() == [False, True, True, True, True, False]
    # d = .5 .4 .6 .5 4 8: one far outlier inflates sd, so only it is dropped
    keep = beta_check(b1, np.array([10.5, 10.4, 10.6, 10.5, 14.0, 2.0]))
    assert keep.tolist() == [True, True, True, True, True, False]
    assert beta_check(b1, b1).all()


@pytest.mark.parametrize("measure", similarity.MEASURES)
def test_identical_views_are_the_most_similar(measure):
    case = simulate_case(seed=2, angular_step_deg=(0.3, 0.3), height_m=7.0)
    seq = build_sequence(case.scans[0], projection=ProjectionParams(theta_deg=20.0), n_scans=3)
    sim = similarity.similarity_matrix(seq, seq, measure)
    assert sim.shape == (len(seq), len(seq))
    assert (np.argmax(sim, axis=1) == np.arange(len(seq))).mean() > 0.9


def test_most_similar_pairs_show_the_same_view_of_the_tree():
    case = simulate_case(seed=5, angular_step_deg=(0.25, 0.25), height_m=8.0)
    seqs = [build_sequence(s, projection=ProjectionParams(), n_scans=3) for s in case.scans[:2]]
    T = case.T_ref_scan[1]
    yaw = np.degrees(np.arctan2(T[1, 0], T[0, 0]))
    sim = similarity.similarity_matrix(seqs[0], seqs[1], "chamfer")
    pairs = similarity.most_similar_pairs(sim, 10)
    assert sim[pairs[0]] == sim.max()
    err = [abs(wrap_deg(similarity.implied_yaw_deg(seqs[0], seqs[1], i, j) - yaw)) for i, j in pairs]
    assert np.mean(np.array(err) < 15.0) >= 0.6
