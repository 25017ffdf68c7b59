"""The simulator is the ground truth of every later test: check that its truth is true.

Scans must be reproducible, lie on one another's surfaces when moved by their truth matrices,
hide what is behind a trunk, agree with a brute-force ray caster, and round-trip through a case
folder written by `treereg simulate`.
"""

from __future__ import annotations

import shlex
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import REAL_TREES, needs
from scipy.spatial import cKDTree

from treereg_cli.main import main
from treereg_core.errors import ConfigError
from treereg_core.geometry.rigid import apply_transform, invert, make_transform
from treereg_core.scan import Scan
from treereg_core.demo import DEMO_DIR
from treereg_core.io.cases import read_case
from treereg_core.simulate.cases import CaseSpec, benchmark_cases, simulate_case
from treereg_core.simulate.scanner import (
    _intersect_cylinders,
    _intersect_disks,
    _intersect_spheres,
    scan_scene,
)
from treereg_core.simulate.tree import (
    LABEL_LEAF,
    LABEL_TRUNK,
    Cylinders,
    Disks,
    Scene,
    Spheres,
    TreeShape,
    make_tree,
)

ADTREE = REAL_TREES / "adtree_tree7.xyz"


# ---- helpers -------------------------------------------------------------------------------
def surface_distance(ref: Scan, q: np.ndarray, station: np.ndarray, max_edge_m: float = 0.1,
                     max_dist_m: float = 0.05, max_incidence_deg: float = 70.0) -> np.ndarray:
    """Distances of points `q` (in the reference frame) to the reference scan's surface, where both
    see it.

    The surface is the reference's range image, triangulated over its ray grid (triangles with
    edges up to `max_edge_m`: one surface, not a jump between two). A point counts where its ray
    from the reference scanner crosses such a triangle, the triangle faces both the reference
    scanner and the other scan's `station` (both at incidence below `max_incidence_deg`: a surface
    both scans see), and it lies within `max_dist_m` of the triangle's plane.
    """
    phi, vphi = ref.angular_step_deg
    p = ref.points
    a_c = np.round(np.degrees(np.arctan2(p[:, 1].mean(), p[:, 0].mean())) / phi) * phi

    def grid(az: np.ndarray, el: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return ((az - a_c + 180.0) % 360.0 - 180.0) / phi, el / vphi

    a, b = grid(ref.azimuth_deg, ref.elevation_deg)
    ia, ib = np.round(a).astype(int), np.round(b).astype(int)
    i0, j0 = ia.min(), ib.min()
    P = np.full((ia.max() - i0 + 2, ib.max() - j0 + 2, 3), np.nan)
    P[ia - i0, ib - j0] = p
    az = np.degrees(np.arctan2(q[:, 1], q[:, 0]))
    el = np.degrees(np.arctan2(q[:, 2], np.hypot(q[:, 0], q[:, 1])))
    a, b = grid(az, el)
    a, b = a - i0, b - j0
    fa, fb = np.floor(a).astype(int), np.floor(b).astype(int)
    inside = (fa >= 0) & (fb >= 0) & (fa < P.shape[0] - 1) & (fb < P.shape[1] - 1)
    a, b, fa, fb, q = a[inside], b[inside], fa[inside], fb[inside], q[inside]
    upper = (a - fa) + (b - fb) > 1.0
    v0 = np.where(upper[:, None], P[fa + 1, fb + 1], P[fa, fb])
    v1, v2 = P[fa + 1, fb], P[fa, fb + 1]
    edges = np.stack([np.linalg.norm(v1 - v0, axis=1), np.linalg.norm(v2 - v0, axis=1),
                      np.linalg.norm(v2 - v1, axis=1)], axis=1)
    ok = np.isfinite(edges).all(axis=1)
    ok[ok] = edges[ok].max(axis=1) <= max_edge_m
    v0, v1, v2, q = v0[ok], v1[ok], v2[ok], q[ok]
    n = np.cross(v1 - v0, v2 - v0)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n *= -np.sign(np.sum(n * v0, axis=1))[:, None]  # facing the reference scanner
    c_min = np.cos(np.radians(max_incidence_deg))
    to_s = station - v0
    faces = (np.sum(n * -v0, axis=1) / np.linalg.norm(v0, axis=1) >= c_min) & (
        np.sum(n * to_s, axis=1) / np.linalg.norm(to_s, axis=1) >= c_min)
    d = np.abs(np.sum((q - v0) * n, axis=1))[faces]
    return d[d < max_dist_m]


def small_spec(**kw) -> CaseSpec:
    base = dict(seed=3, angular_step_deg=(0.25, 0.25), height_m=6.0)
    base.update(kw)
    return CaseSpec(**base)


# ---- reproducibility -----------------------------------------------------------------------
def test_same_seed_gives_identical_points_and_truth():
    spec = small_spec(leaves=True, ground=True, tilt_deg=0.3, bent=True)
    a, b = spec.build(), spec.build()
    for sa, sb, Ta, Tb in zip(a.scans, b.scans, a.T_ref_scan, b.T_ref_scan):
        assert sa.name == sb.name
        assert np.array_equal(sa.points, sb.points)
        assert np.array_equal(Ta, Tb)
    c = small_spec(seed=4, leaves=True, ground=True, tilt_deg=0.3, bent=True).build()
    assert c.scans[0].n_points != a.scans[0].n_points or not np.array_equal(c.scans[0].points, a.scans[0].points)


def test_switching_leaves_keeps_the_tree_and_the_stations():
    bare, leafy = small_spec().build(), small_spec(leaves=True).build()
    for Ta, Tb in zip(bare.T_ref_scan, leafy.T_ref_scan):
        assert np.array_equal(Ta, Tb)
    assert np.array_equal(bare.trees[0].scene.cylinders.p0, leafy.trees[0].scene.cylinders.p0)
    assert len(leafy.trees[0].scene.disks) > 500 and len(bare.trees[0].scene.disks) == 0
    assert all((lab == LABEL_LEAF).sum() > 100 for lab in leafy.labels)


# ---- the truth -----------------------------------------------------------------------------
def test_truth_puts_every_scan_on_the_reference_surface():
    """The issue's truth check, on an awkward case (leaves, bent trunk, ground, tilted instruments):
    each scan moved by its truth matrix lies on scan 1's surface where both see it (median < 1 cm),
    and a truth 3 cm off would fail the same check."""
    case = simulate_case(seed=5, angular_step_deg=0.1, height_m=10.0, leaves=True, bent=True, ground=True,
                         tilt_deg=0.3, separation_deg=(90.0, 100.0))
    assert all(st.tilt_deg > 0.1 for st in case.stations)
    assert np.array_equal(case.T_ref_scan[0], np.eye(4))
    ref = case.scans[0]
    for k in (1, 2):
        T = case.T_ref_scan[k]
        d = surface_distance(ref, apply_transform(T, case.scans[k].points), T[:3, 3])
        assert d.size > 300, f"scan {k + 1}: only {d.size} points on surfaces both scans see"
        assert np.median(d) < 0.01, f"scan {k + 1}: median distance {np.median(d):.4f} m"
        # The same check catches a wrong truth: shift the scan 3 cm sideways in the world.
        T_world_ref = case.stations[0].T_world_scan
        shift = make_transform(np.eye(3), [0.03, 0.03, 0.0])
        T_bad = invert(T_world_ref) @ shift @ T_world_ref @ T
        d_bad = surface_distance(ref, apply_transform(T_bad, case.scans[k].points), T_bad[:3, 3])
        assert np.median(d_bad) > 0.01, f"scan {k + 1}: a 3 cm error went unnoticed ({np.median(d_bad):.4f} m)"


def test_points_lie_on_the_model_surfaces():
    """Without noise every returned trunk point lies on its tapered trunk (the world pose is right)."""
    case = small_spec(range_sigma_m=0.0, tilt_deg=0.3, angular_step_deg=(0.15, 0.15)).build()
    c = case.scene.cylinders
    trunk = c.label == LABEL_TRUNK
    p0, p1, r0, r1 = c.p0[trunk], c.p1[trunk], c.r0[trunk], c.r1[trunk]
    for k in range(len(case.scans)):
        w = case.world_points(k)[case.labels[k] == LABEL_TRUNK]
        assert len(w) > 200
        ax = p1 - p0
        t = np.clip(np.einsum("nsk,sk->ns", w[:, None] - p0, ax) / np.sum(ax * ax, axis=1), 0, 1)
        foot = p0 + t[..., None] * ax
        dist = np.linalg.norm(w[:, None] - foot, axis=2) - (r0 * (1 - t) + r1 * t)
        # joint spheres add up to a fraction of a millimetre on a tapering trunk
        assert np.percentile(np.min(np.abs(dist), axis=1), 99) < 5e-4


# ---- the scanner ---------------------------------------------------------------------------
def _empty_disks() -> Disks:
    return Disks(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int8))


def test_a_trunk_hides_what_is_behind_it():
    # A trunk (radius 0.3 m) 5 m in front of the scanner, a wall-like disk 8 m away behind it.
    scene = Scene(
        Cylinders(np.array([[5.0, 0.0, -2.0]]), np.array([[5.0, 0.0, 2.0]]), np.array([0.3]), np.array([0.3]),
                  np.array([LABEL_TRUNK], dtype=np.int8)),
        Spheres(np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int8)),
        Disks(np.array([[8.0, 0.0, 0.0]]), np.array([[-1.0, 0.0, 0.0]]), np.array([2.0]),
              np.array([LABEL_LEAF], dtype=np.int8)),
    )
    rs = scan_scene(scene, (0.2, 0.2), np.random.default_rng(0), range_sigma_m=0.0, dropout=0.0)
    az = np.degrees(np.arctan2(rs.points[:, 1], rs.points[:, 0]))
    el = np.degrees(np.arctan2(rs.points[:, 2], np.hypot(rs.points[:, 0], rs.points[:, 1])))
    shadow = np.degrees(np.arcsin(0.3 / 5.0))  # half-angle of the trunk's silhouette
    on_disk = rs.labels == LABEL_LEAF
    on_trunk = rs.labels == LABEL_TRUNK
    assert on_disk.sum() > 1000 and on_trunk.sum() > 100
    np.testing.assert_allclose(rs.points[on_disk, 0], 8.0, atol=1e-9)
    # nothing of the disk is returned from inside the trunk's shadow (where it is low enough)
    assert not np.any(on_disk & (np.abs(az) < shadow - 0.05) & (np.abs(el) < 19.0))
    # the trunk returns its front half only, on its surface
    trunk = rs.points[on_trunk]
    np.testing.assert_allclose(np.hypot(trunk[:, 0] - 5.0, trunk[:, 1]), 0.3, atol=1e-9)
    assert np.all(trunk[:, 0] < 5.0)
    # every ray inside the silhouette returned the trunk: no holes
    cols = np.arange(np.ceil(-(shadow - 0.3) / 0.2), np.floor((shadow - 0.3) / 0.2) + 1)
    rows = np.arange(np.ceil(-19.0 / 0.2), np.floor(19.0 / 0.2) + 1)
    got = set(map(tuple, rs.grid_ij[on_trunk]))
    assert all((int(i), int(j)) in got for i in cols for j in rows)


def test_bounding_boxes_lose_no_hit():
    """The pruned caster returns exactly what testing every ray against every primitive gives."""
    rng = np.random.default_rng(11)
    tree = make_tree(TreeShape(height_m=5.0, dbh_m=0.2, orders=2, leaves=True, bent=True), rng)
    T = make_transform(np.eye(3), [7.0, 2.0, 1.5])
    scene = tree.scene.transformed(invert(T))
    step = 0.25
    rs = scan_scene(scene, (step, step), np.random.default_rng(0), range_sigma_m=0.0, dropout=0.0)
    i0, i1, j0, j1 = rs.window_ij
    ii, jj = np.meshgrid(np.arange(i0, i1 + 1), np.arange(j0, j1 + 1), indexing="ij")
    ii, jj = ii.ravel(), jj.ravel()
    a, b = np.radians(ii * step), np.radians(jj * step)
    d = np.stack([np.cos(b) * np.cos(a), np.cos(b) * np.sin(a), np.sin(b)], axis=1)
    c, s, k = scene.cylinders, scene.spheres, scene.disks
    best = np.full(len(d), np.inf)
    # Brute force: every ray against every primitive, in blocks of rays.
    axis = c.p1 - c.p0
    L = np.linalg.norm(axis, axis=1)
    u = axis / L[:, None]
    kk = (c.r1 - c.r0) / L
    pa = np.sum(c.p0 * u, axis=1)
    m = c.r0 - kk * pa
    pre = {"ax": u[:, 0], "ay": u[:, 1], "az": u[:, 2], "L": L, "k": kk, "pa": pa, "m": m,
           "C": np.sum(c.p0 * c.p0, axis=1) - pa * pa - m * m}
    for r0 in range(0, len(d), 200):
        dd = d[r0:r0 + 200]
        R = np.repeat(np.arange(len(dd)), len(c))
        P = np.tile(np.arange(len(c)), len(dd))
        t = _intersect_cylinders(scene, P, dd[R, 0], dd[R, 1], dd[R, 2], pre).reshape(len(dd), -1).min(axis=1)
        R = np.repeat(np.arange(len(dd)), len(s))
        P = np.tile(np.arange(len(s)), len(dd))
        t = np.minimum(t, _intersect_spheres(s.centre[P], s.radius[P], dd[R, 0], dd[R, 1], dd[R, 2])
                       .reshape(len(dd), -1).min(axis=1))
        R = np.repeat(np.arange(len(dd)), len(k))
        P = np.tile(np.arange(len(k)), len(dd))
        t = np.minimum(t, _intersect_disks(k.centre[P], k.normal[P], k.radius[P], dd[R, 0], dd[R, 1], dd[R, 2])
                       .reshape(len(dd), -1).min(axis=1))
        best[r0:r0 + 200] = t
    hit = np.isfinite(best)
    assert hit.sum() == len(rs.points) > 800
    key = (ii - i0) * (j1 - j0 + 1) + (jj - j0)
    got = np.full(len(d), np.inf)
    got[(rs.grid_ij[:, 0] - i0) * (j1 - j0 + 1) + (rs.grid_ij[:, 1] - j0)] = np.linalg.norm(rs.points, axis=1)
    np.testing.assert_allclose(got[key[hit]], best[hit], rtol=0, atol=1e-9)


def test_stations_are_placed_as_specified():
    case = small_spec(tilt_deg=0.3, n_stations=3).build()
    az = [st.azimuth_deg for st in case.stations]
    for k in (1, 2):
        sep = abs((az[k] - az[0] + 180.0) % 360.0 - 180.0)
        assert 90.0 - 1e-9 <= sep <= 150.0 + 1e-9
    for st in case.stations:
        assert 8.0 <= st.distance_m <= 15.0
        assert 0.15 - 1e-9 <= st.tilt_deg <= 0.3 + 1e-9
        R = st.T_world_scan[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        # the instrument's z axis is tilted by exactly tilt_deg
        assert np.degrees(np.arccos(R[2, 2])) == pytest.approx(st.tilt_deg, abs=1e-6)
    level = small_spec().build()
    assert all(st.T_world_scan[2, 2] == pytest.approx(1.0, abs=1e-15) for st in level.stations)


def test_tree_has_the_asked_size_and_orders():
    rng = np.random.default_rng(2)
    tree = make_tree(TreeShape(height_m=12.0, dbh_m=0.4, orders=3), rng)
    c = tree.scene.cylinders
    trunk = c.label == LABEL_TRUNK
    top = max(c.p1[trunk, 2].max(), c.p0[trunk, 2].max())
    assert 11.5 < top <= 12.0 + 1e-9
    at_bh = trunk & (c.p0[:, 2] <= 1.3) & (c.p1[:, 2] >= 1.3)
    assert 2 * c.r0[at_bh][0] == pytest.approx(0.4, rel=0.05)
    assert set(np.unique(c.label)) == {1, 2, 3, 4}
    assert all(n > 0 for n in tree.n_branches) and len(tree.n_branches) == 3


# ---- stations from a point cloud -----------------------------------------------------------
@needs(ADTREE)
def test_stations_from_a_real_tree_keep_the_nearest_point_per_cell():
    case = simulate_case(seed=1, angular_step_deg=0.1, from_points=str(ADTREE), range_sigma_m=0.0, dropout=0.0)
    cloud = case.cloud
    assert cloud[:, 2].min() == pytest.approx(0.0)
    low = cloud[:, 2] < 0.5
    assert np.hypot(*np.median(cloud[low, :2], axis=0)) < 0.05  # the trunk base is at x = y = 0
    step = np.radians(0.1)
    for k, scan in enumerate(case.scans):
        assert 1000 < scan.n_points < len(cloud)  # occlusion and shared cells drop points
        assert 8.0 <= case.stations[k].distance_m <= 15.0
        w = case.world_points(k)
        d, _ = cKDTree(cloud).query(w)
        assert d.max() < 1e-9  # every returned point is a point of the cloud
        # ... and the nearest of its angular cell
        local = apply_transform(invert(case.stations[k].T_world_scan), cloud)
        r = np.linalg.norm(local, axis=1)
        a = np.arctan2(local[:, 1], local[:, 0])
        a_c = np.arctan2(np.sin(a).sum(), np.cos(a).sum())
        a = a_c + (a - a_c + np.pi) % (2 * np.pi) - np.pi
        cell = np.round(a / step).astype(np.int64) * 100000 + np.round(
            np.arctan2(local[:, 2], np.hypot(local[:, 0], local[:, 1])) / step).astype(np.int64)
        order = np.lexsort((r, cell))
        first = np.r_[True, cell[order][1:] != cell[order][:-1]]
        assert len(np.unique(cell)) == scan.n_points
        nearest = local[order[first]]
        np.testing.assert_allclose(np.sort(np.linalg.norm(nearest, axis=1)),
                                   np.sort(np.linalg.norm(scan.points, axis=1)), atol=1e-9)


@needs(ADTREE)
def test_stations_from_points_add_range_noise_along_the_ray():
    case = simulate_case(seed=1, angular_step_deg=0.1, from_points=str(ADTREE), range_sigma_m=0.003)
    d, _ = cKDTree(case.cloud).query(case.world_points(1))
    assert 0.0015 < np.median(d) < 0.003  # median |N(0, 3 mm)| = 2 mm
    assert d.max() < 0.02


# ---- the command line and case folders -----------------------------------------------------
def test_cli_writes_a_case_folder_that_reads_back(tmp_path, capsys):
    out = tmp_path / "case"
    rc = main(["simulate", "--seed", "4", "--angular-step", "0.3", "0.25", "--height", "6", "--ground",
               "--tilt", "--out", str(out)])
    assert rc == 0
    assert sorted(p.name for p in out.iterdir()) == ["scan1.ply", "scan2.ply", "scan3.ply", "truth.json"]
    case = read_case(out)
    scans, truth = case.scans, case.truth_file
    expected = simulate_case(seed=4, angular_step_deg=(0.3, 0.25), height_m=6.0, ground=True, tilt_deg=0.3)
    assert truth.reference == "scan1.ply"
    assert truth.extra["angular_step_deg"] == [0.3, 0.25]
    assert set(truth.extra["stations"]) == {"scan1.ply", "scan2.ply", "scan3.ply"}
    for got, want, T in zip(scans, expected.scans, expected.T_ref_scan):
        assert got.name == want.name and got.angular_step_deg == (0.3, 0.25) and not got.step_estimated
        assert np.array_equal(got.points, want.points)
        np.testing.assert_array_equal(truth.matrix(got.name), T)
    assert "wrote scan1.ply" in capsys.readouterr().out


@needs(ADTREE)
def test_cli_refuses_tree_options_with_a_point_cloud(tmp_path, capsys):
    rc = main(["simulate", "--from-points", str(ADTREE), "--leaves", "--out", str(tmp_path / "x")])
    assert rc == 2
    assert "leaves only apply to procedural trees" in capsys.readouterr().err


@pytest.mark.parametrize("kw, words", [
    (dict(angular_step_deg=0.0), "angular_step_deg"),
    (dict(orders=4), "orders"),
    (dict(station_distance_m=(15.0, 8.0)), "station_distance_m"),
    (dict(dropout=1.0), "dropout"),
])
def test_bad_options_are_config_errors(kw, words):
    with pytest.raises(ConfigError, match=words):
        CaseSpec(**kw)


# ---- the benchmark set ---------------------------------------------------------------------
def test_benchmark_set_is_a_third_awkward_and_reproducible():
    specs = benchmark_cases(24, seed=0)
    assert specs == benchmark_cases(24, seed=0)
    assert len({s.seed for s in specs}) == 24
    assert sum(s.awkward for s in specs) >= 8
    for feature in ("leaves", "bent", "ground"):
        assert sum(getattr(s, feature) for s in specs) >= 3
    assert sum(s.tilt_deg > 0 for s in specs) >= 3
    assert all(8.0 <= s.height_m <= 15.0 for s in specs)


@pytest.mark.timed
def test_small_benchmark_cases_are_quick_and_small():
    for spec in benchmark_cases(6, seed=1, small=True)[:3]:
        t0 = time.perf_counter()
        case = spec.build()
        assert time.perf_counter() - t0 < 2.0
        assert all(3_000 < s.n_points < 60_000 for s in case.scans), [s.n_points for s in case.scans]


# ---- the bundled demo ----------------------------------------------------------------------
ASSETS = Path(__file__).resolve().parents[1] / "assets"  # the demo's README (how it is made)


def test_the_demo_case_is_small_and_regenerates_from_its_readme_command(tmp_path):
    line = next(ln.strip() for ln in (ASSETS / "README.md").read_text().splitlines()
                if ln.strip().startswith("treereg simulate"))
    argv = shlex.split(line)[1:]
    argv[argv.index("--out") + 1] = str(tmp_path / "demo")
    assert main(argv) == 0
    demo, again = read_case(DEMO_DIR), read_case(tmp_path / "demo")
    truth, truth_again = demo.truth_file, again.truth_file
    assert len(demo.scans) == 3
    for a, b in zip(demo.scans, again.scans):
        assert (DEMO_DIR / a.name).stat().st_size <= 2_000_000
        assert a.n_points <= 60_000 and a.n_points == b.n_points
        np.testing.assert_allclose(a.points, b.points, rtol=0, atol=1e-9)
        np.testing.assert_allclose(truth.matrix(a.name), truth_again.matrix(a.name), rtol=0, atol=1e-12)
