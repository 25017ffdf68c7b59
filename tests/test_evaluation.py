"""The paper's evaluation model (3.3, eq. 8): ~0 at the true transform, grows with an offset."""

import numpy as np
import pytest

from treereg_core.evaluate.branches import evaluate_pair, find_branches
from treereg_core.params import EvaluationParams
from treereg_core.geometry.rigid import make_transform, rotation_z
from treereg_core.simulate.cases import benchmark_cases


@pytest.fixture(scope="module")
def case():
    return benchmark_cases(3, seed=0, small=True)[2].build()  # a plain leaf-off tree


def test_branch_error_is_small_at_the_truth_and_tracks_a_shift(case):
    ref, tgt, T = case.scans[0], case.scans[1], case.T_ref_scan[1]
    p = EvaluationParams()
    at_truth = evaluate_pair(ref, tgt, T, evaluation=p, T_true=T)
    assert at_truth.ok and len(at_truth.branches) >= 3
    # Fits to one scan's partial arcs carry mm-level centre errors, so "zero" is a few mm.
    assert at_truth.mean_distance_m < 0.01
    assert at_truth.rotation_error_deg == pytest.approx(0.0, abs=1e-4)  # arccos near 1
    assert at_truth.mean_displacement_m == pytest.approx(0.0, abs=1e-12)
    previous = at_truth.mean_distance_m
    for shift in (0.02, 0.05, 0.1):
        T_off = make_transform(np.eye(3), [shift, 0.0, 0.0]) @ T
        ev = evaluate_pair(ref, tgt, T_off, evaluation=p, T_true=T)
        # A horizontal shift moves every branch centre by the shift (up to the fit errors).
        assert ev.mean_distance_m == pytest.approx(shift, abs=0.01)
        assert ev.mean_distance_m > previous
        assert ev.mean_displacement_m == pytest.approx(shift, rel=1e-6)
        previous = ev.mean_distance_m


def test_branch_error_without_truth_uses_the_evaluated_transform(case):
    ref, tgt, T = case.scans[0], case.scans[1], case.T_ref_scan[1]
    c = ref.points.mean(axis=0)
    R = rotation_z(1.0)
    T_rot = make_transform(R, c - R @ c) @ T
    ev = evaluate_pair(ref, tgt, T_rot, evaluation=EvaluationParams())
    assert ev.ok and ev.rotation_error_deg is None and ev.mean_displacement_m is None
    assert ev.mean_distance_m > evaluate_pair(ref, tgt, T, evaluation=EvaluationParams()).mean_distance_m
    # Per-branch numbers as the paper's Figs. 13-14: layers at distinct heights, d per layer.
    for b in ev.branches:
        assert len(b.distances_m) == len(b.layer_z_m) <= EvaluationParams().layers
        assert np.allclose(b.ref_centres_m[:, 2], b.layer_z_m) and np.allclose(b.tgt_centres_m[:, 2], b.layer_z_m)
        assert b.mean_m == pytest.approx(b.distances_m.mean())


def test_branches_are_found_in_the_reference_only(case):
    fits = find_branches(case.scans[0], evaluation=EvaluationParams(max_branches=5))
    assert 1 <= len(fits) <= 5
    assert all(f.ok and abs(f.axis[2]) >= 0.3 for f in fits)


def test_no_branch_is_a_result_with_a_message(case):
    ref, tgt, T = case.scans[0], case.scans[1], case.T_ref_scan[1]
    ev = evaluate_pair(ref, tgt, T, evaluation=EvaluationParams(min_arc_deg=359.0))
    assert not ev.ok and "no branch could be evaluated" in ev.message
    assert np.isnan(ev.mean_distance_m)
