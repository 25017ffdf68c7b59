"""ICP baseline: converges from a small perturbation; measured beside fine on a simulated pair."""

import numpy as np
import pytest

from treereg_core.evaluate.icp import align_icp
from treereg_core.geometry.normals import estimate_normals, voxel_downsample
from treereg_core.params import IcpParams
from treereg_core.geometry.rigid import apply_transform, invert, make_transform, mean_displacement, rotation_error_deg, rotation_z
from treereg_core.simulate.cases import benchmark_cases


@pytest.fixture(scope="module")
def case():
    return benchmark_cases(3, seed=0, small=True)[2].build()  # a plain leaf-off tree


def _offset(points, angle_deg, shift):
    c = points.mean(axis=0)
    R = rotation_z(angle_deg)
    return make_transform(R, c - R @ c + np.asarray(shift))


# Point-to-point pairs each point with a neighbour up to half a grid step away (the two samplings
# interleave), which biases it by millimetres; point-to-plane is free of that.
@pytest.mark.parametrize("method,tol_m,tol_deg", [("point_to_point", 0.015, 0.1), ("point_to_plane", 0.003, 0.05)])
def test_icp_recovers_a_small_offset_of_the_same_surface(case, method, tol_m, tol_deg):
    # The target samples the same surface as the reference (other points, own noise), moved by a
    # known small transform: ICP must undo it.
    rng = np.random.default_rng(1)
    ref = case.scans[1].points
    tgt_ref_frame = ref[1::2] + rng.normal(0, 0.002, ref[1::2].shape)
    T_err = _offset(ref, 0.4, [0.02, -0.015, 0.01])
    tgt = apply_transform(invert(T_err), tgt_ref_frame)  # so that T_err maps tgt back
    start = np.eye(4)
    res = align_icp(ref[::2], tgt, start, icp=IcpParams(method=method, voxel_m=0.01, max_distance_m=0.2, trim=0.8))
    assert res.ok
    assert rotation_error_deg(res.T_ref_target, T_err) < tol_deg
    assert mean_displacement(res.T_ref_target, T_err, tgt) < tol_m
    assert mean_displacement(res.T_ref_target, T_err, tgt) < mean_displacement(start, T_err, tgt) / 2


def test_icp_on_two_stations_runs_from_a_near_pose_and_reports(case):
    ref, tgt = case.scans[0], case.scans[1]
    T_true = case.T_ref_scan[1]
    start = _offset(apply_transform(T_true, tgt.points), 0.2, [0.01, 0.005, 0.0]) @ T_true
    res = align_icp(ref.points, tgt.points, start, icp=IcpParams())
    assert res.ok and res.iterations >= 1 and 0 < res.overlap <= 1 and np.isfinite(res.rmse_m)
    # Partial overlap (each station sees other sides of thin branches) biases ICP; from 1 cm it
    # stays within a few cm of the truth.
    assert mean_displacement(res.T_ref_target, T_true, tgt.points) < 0.03
    assert rotation_error_deg(res.T_ref_target, T_true) < 0.5


def test_icp_reports_failure_when_nothing_is_within_reach(case):
    ref, tgt = case.scans[0], case.scans[1]
    far = make_transform(np.eye(3), [50.0, 0, 0]) @ case.T_ref_scan[1]
    res = align_icp(ref.points, tgt.points, far, icp=IcpParams(max_distance_m=0.5))
    assert not res.ok and "max_distance" in res.message
    assert np.array_equal(res.T_ref_target, far)


def test_voxel_downsample_and_normals():
    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(0, 1, (5000, 2)), np.zeros(5000)]
    sub = voxel_downsample(plane, 0.1)
    assert 90 <= len(sub) <= 100
    n = estimate_normals(sub)
    assert np.all(np.abs(n[:, 2]) > 0.99)


def test_icp_says_whether_it_converged_and_measures_its_overlap(case):
    """Issue 32: "fitness 0.5" was the trim fraction (a setting), and "stopped after 50 iterations"
    hid that ICP had not converged."""
    ref, tgt = case.scans[0], case.scans[1]
    start = _offset(apply_transform(case.T_ref_scan[1], tgt.points), 0.2, [0.01, 0.005, 0.0]) @ case.T_ref_scan[1]
    said = {m.description: m.value for m in align_icp(ref.points, tgt.points, start, icp=IcpParams()).metrics}
    assert said["ICP converged"] == "yes"
    assert said["ICP overlap (target points within icp.max_distance_m)"] > IcpParams().trim
    capped = align_icp(ref.points, tgt.points, start, icp=IcpParams(max_iterations=2))
    assert not capped.converged
    assert dict((m.description, m.value) for m in capped.metrics)["ICP converged"] == "no (stopped at icp.max_iterations = 2)"
    # Nothing near: the overlap says so (no trimmed share of far points passes for a fit).
    near = align_icp(ref.points, tgt.points, start, icp=IcpParams(max_distance_m=0.002, max_iterations=1))
    assert near.overlap < 0.9
