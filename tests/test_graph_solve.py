"""The joint placement of all stations (`verify.graph.solve_pose_graph`, `place_scans`): the sparse
solve against the truth, a wrong edge dropped and named, scans not connected, the smallest graphs."""

from __future__ import annotations

import numpy as np
import pytest

from treereg_core.geometry.rigid import invert, make_transform, mean_displacement, rotation_error_deg, rotation_from_vector
from treereg_core.params import GraphParams
from treereg_core.verify.evidence import FAILED, UNVERIFIED, VERIFIED
from treereg_core.verify.graph import Edge, _Problem, place_scans, solve_pose_graph


def _grid(rows: int, cols: int, seed: int, noise: bool = True) -> tuple[list[np.ndarray], dict[int, np.ndarray], list[Edge]]:
    """Stations 10 m apart on a grid, random headings; edges to grid neighbours and diagonals, measured
    from the truth with 1 mm / 0.005 deg noise (or exactly)."""
    rng = np.random.default_rng(seed)
    world = [make_transform(rotation_from_vector(np.r_[np.radians(rng.normal(0, 0.3, 2)), rng.uniform(-np.pi, np.pi)]),
                            [c * 10.0, r * 10.0, rng.normal(0, 0.3)]) for r in range(rows) for c in range(cols)]
    truth = [invert(world[0]) @ T for T in world]
    samples = {k: np.c_[rng.uniform(-10, 10, (200, 2)), rng.uniform(0, 15, 200)] for k in range(len(truth))}
    pairs = [(r * cols + c, rr * cols + cc) for r in range(rows) for c in range(cols)
             for rr, cc in ((r, c + 1), (r + 1, c), (r + 1, c + 1)) if rr < rows and cc < cols]
    edges = []
    for i, j in pairs:
        e = make_transform(rotation_from_vector(np.radians(rng.normal(0, 0.005, 3))), rng.normal(0, 0.001, 3)) if noise else np.eye(4)
        edges.append(Edge(i=i, j=j, T=invert(truth[i]) @ truth[j] @ e, verdict=VERIFIED, weight=float(rng.uniform(0.5, 2))))
    return truth, samples, edges


def test_the_analytic_jacobian_is_the_residuals_derivative():
    truth, samples, edges = _grid(2, 3, seed=1)
    rng = np.random.default_rng(2)
    poses = {k: make_transform(rotation_from_vector(rng.normal(0, 0.3, 3)), rng.normal(0, 2, 3)) @ T for k, T in enumerate(truth)}
    poses[0] = np.eye(4)
    pb = _Problem(poses, edges, samples)
    x = rng.normal(0, 0.3, pb.shape[1])  # far from zero: the rotation vectors' Jacobians matter
    numeric = np.stack([(pb.residuals(x + 1e-6 * d) - pb.residuals(x - 1e-6 * d)) / 2e-6 for d in np.eye(len(x))], axis=1)
    J = pb.jacobian(x)
    assert J.nnz <= 12 * J.shape[0]
    assert np.abs(J.toarray() - numeric).max() < 1e-6 * np.abs(numeric).max()


def test_exact_edges_give_the_truth_and_noisy_ones_a_placement_within_their_noise():
    truth, samples, edges = _grid(3, 3, seed=3, noise=False)
    sol = solve_pose_graph(9, edges, samples, graph=GraphParams(), max_loop_m=0.01)
    assert sorted(sol.poses) == list(range(9)) and not sol.dropped
    assert max(mean_displacement(sol.poses[k], truth[k], samples[k]) for k in range(9)) < 1e-8
    truth, samples, edges = _grid(4, 4, seed=4)
    sol = solve_pose_graph(16, edges, samples, graph=GraphParams(), max_loop_m=0.01)
    disp = [mean_displacement(sol.poses[k], truth[k], samples[k]) for k in range(16)]
    assert max(disp) < 0.006 and np.median(disp) < 0.003  # each edge is 1-2 mm off (0.005 deg at 10 m)
    assert max(rotation_error_deg(sol.poses[k], truth[k]) for k in range(16)) < 0.02
    assert all(e.used and e.loop_error_m < 0.005 for e in sol.edges)


def test_the_compact_residuals_weigh_an_edge_as_all_its_sample_points_do():
    """Six sigma points per edge: the sum of squares over all of scan j's samples, exactly."""
    truth, samples, edges = _grid(2, 2, seed=5)
    rng = np.random.default_rng(6)
    poses = {k: make_transform(rotation_from_vector(rng.normal(0, 0.01, 3)), rng.normal(0, 0.02, 3)) @ T for k, T in enumerate(truth)}
    poses[0] = np.eye(4)
    pb = _Problem(poses, edges, samples)
    f = pb.residuals(np.zeros(pb.shape[1]))
    compact = float(np.sum(pb.count * f ** 2))
    w = np.sqrt(np.array([e.weight for e in edges]) / np.mean([e.weight for e in edges]))
    full = sum(wk ** 2 * float(np.sum(((invert(poses[e.i]) @ poses[e.j] - e.T)[:3, :3] @ samples[e.j].T
                                       + (invert(poses[e.i]) @ poses[e.j] - e.T)[:3, 3:]) ** 2))
               for wk, e in zip(w, edges))
    assert compact == pytest.approx(full, rel=1e-9)


def test_a_wrong_edge_is_dropped_named_with_its_residual_and_the_rest_placed_through_the_others():
    truth, samples, edges = _grid(3, 3, seed=7)
    k = next(n for n, e in enumerate(edges) if (e.i, e.j) == (4, 5))
    edges[k] = Edge(i=4, j=5, T=make_transform(rotation_from_vector(np.radians([0, 0, 0.2])), [0.03, -0.02, 0.0]) @ edges[k].T,
                    verdict=VERIFIED)
    sol = solve_pose_graph(9, edges, samples, graph=GraphParams(), max_loop_m=0.01)
    assert [(e.i, e.j) for e, _ in sol.dropped] == [(4, 5)] and sol.dropped[0][1] > 0.01
    assert max(mean_displacement(sol.poses[n], truth[n], samples[n]) for n in range(9)) < 0.004
    placed = place_scans(9, edges, samples, graph=GraphParams(), max_loop_m=0.01)
    assert all(pl.verdict == VERIFIED for pl in placed)
    unused = [e for e in placed[0].edges if not e.used]
    assert [(e.i, e.j) for e in unused] == [(4, 5)] and unused[0].loop_error_m == sol.dropped[0][1]
    assert 5 not in placed[4].via and 4 not in placed[5].via
    assert any(m.description == "pairs dropped by loop closure" and m.value == 1 for m in placed[5].metrics)


def test_two_wrong_edges_apart_both_dropped_and_no_right_one():
    truth, samples, edges = _grid(4, 4, seed=8)
    for pair in ((5, 6), (10, 14)):
        k = next(n for n, e in enumerate(edges) if (e.i, e.j) == pair)
        edges[k] = Edge(i=pair[0], j=pair[1], T=make_transform(np.eye(3), [0.0, 0.04, 0.01]) @ edges[k].T, verdict=VERIFIED)
    sol = solve_pose_graph(16, edges, samples, graph=GraphParams(), max_loop_m=0.01)
    assert sorted((e.i, e.j) for e, _ in sol.dropped) == [(5, 6), (10, 14)]
    assert max(mean_displacement(sol.poses[n], truth[n], samples[n]) for n in range(16)) < 0.006


def test_a_station_without_a_verified_edge_is_unverified_through_a_pair_or_failed_without_one():
    truth, samples, edges = _grid(2, 2, seed=9)
    samples = {**samples, 4: samples[0], 5: samples[1]}
    edges = [e for e in edges if 3 not in (e.i, e.j)]
    edges.append(Edge(i=2, j=3, T=invert(truth[2]) @ truth[3], verdict=UNVERIFIED, reasons=("the heading is ambiguous",)))
    edges.append(Edge(i=0, j=4, T=np.eye(4), verdict=FAILED, reasons=("coarse: only 2 tie points",)))
    placed = place_scans(6, edges, samples, graph=GraphParams(), max_loop_m=0.01)
    assert [pl.verdict for pl in placed] == [VERIFIED] * 3 + [UNVERIFIED, FAILED, FAILED]
    assert mean_displacement(placed[3].T_ref_scan, truth[3], samples[3]) < 0.005  # its best guess, through scan 3
    assert "the heading is ambiguous" in placed[3].reasons
    assert placed[4].T_ref_scan is None and "coarse: only 2 tie points" in placed[4].reasons[0]
    assert placed[5].reasons == ("no registered pair links it to the reference",)
    assert sorted(solve_pose_graph(6, edges, samples, graph=GraphParams(), max_loop_m=0.01).poses) == [0, 1, 2]


def test_one_station_and_two_stations():
    samples = {0: np.random.default_rng(0).uniform(-5, 5, (50, 3))}
    sol = solve_pose_graph(1, [], samples, graph=GraphParams(), max_loop_m=0.01)
    assert list(sol.poses) == [0] and np.array_equal(sol.poses[0], np.eye(4)) and sol.edges == ()
    (pl,) = place_scans(1, [], samples, graph=GraphParams(), max_loop_m=0.01)
    assert pl.verdict == VERIFIED and np.array_equal(pl.T_ref_scan, np.eye(4))
    T = make_transform(rotation_from_vector(np.radians([0.5, -0.3, 40.0])), [4.0, -2.0, 0.1])
    samples[1] = samples[0] + 1.0
    placed = place_scans(2, [Edge(i=0, j=1, T=T, verdict=VERIFIED)], samples, graph=GraphParams(), max_loop_m=0.01)
    assert [pl.verdict for pl in placed] == [VERIFIED, VERIFIED]
    assert np.allclose(placed[1].T_ref_scan, T, atol=1e-12) and placed[1].via == (0,)
    assert placed[0].edges[0].used and placed[0].edges[0].loop_error_m < 1e-9
    # Its one pair failed: no placement.
    placed = place_scans(2, [Edge(i=0, j=1, T=np.eye(4), verdict=FAILED, reasons=("no tie points",))], samples,
                         graph=GraphParams(), max_loop_m=0.01)
    assert placed[1].verdict == FAILED and placed[1].T_ref_scan is None
