"""Projection images (eq. 2-3), the pixel -> points index, the azimuth wrap, sequences, tie points."""

import numpy as np

from treereg_core.params import ProjectionParams
from treereg_core.coarse.projection import EMPTY, OCCUPIED, project, spherical_deg
from treereg_core.geometry.rigid import apply_transform, rotation_z
from treereg_core.scan import Scan
from treereg_core.coarse.sequences import build_sequence, sequence_angles_deg
from treereg_core.coarse.tiepoints import pixel_centroids


def _tree_like(rng: np.random.Generator, centre_xy=(10.0, 0.0), n: int = 5000) -> np.ndarray:
    """A 'trunk' (vertical cylinder surface) and a cloud of 'crown' points around `centre_xy`."""
    t = rng.uniform(0, 2 * np.pi, n // 2)
    trunk = np.column_stack([0.2 * np.cos(t), 0.2 * np.sin(t), rng.uniform(0, 4, n // 2)])
    crown = rng.normal([0, 0, 6], [1.5, 1.5, 1.0], size=(n - n // 2, 3))
    pts = np.vstack([trunk, crown])
    pts[:, :2] += centre_xy
    return pts


def test_pixels_give_back_exactly_their_points():
    rng = np.random.default_rng(0)
    pts = _tree_like(rng)
    alpha, beta = spherical_deg(pts[:, 0], pts[:, 1], pts[:, 2])
    proj = project(alpha, beta, (0.2, 0.2), (10, 10), azimuth_ref_deg=0.0)
    g = proj.geometry
    counts = proj.counts()
    # occupied <=> the pixel holds points, with the paper's values
    assert set(np.unique(proj.image)) == {OCCUPIED, EMPTY}
    assert np.array_equal(proj.image == OCCUPIED, counts > 0)
    assert counts.sum() == len(pts)
    order, offsets = proj.pixel_index()
    rows, cols = np.nonzero(counts)
    for r, c in zip(rows[::97], cols[::97]):
        idx = np.sort(proj.points_of_pixel(int(r), int(c)))
        f = r * proj.shape[1] + c
        assert np.array_equal(idx, np.sort(order[offsets[f]:offsets[f + 1]]))
        a_lo, a_hi = g.alpha_interval_deg(c)
        b_lo, b_hi = g.beta_interval_deg(r)
        # the pixel's points are exactly those whose angles fall into its intervals
        inside = (alpha >= a_lo - 1e-9) & (alpha < a_hi + 1e-9) & (beta >= b_lo - 1e-9) & (beta < b_hi + 1e-9)
        assert np.array_equal(idx, np.flatnonzero(inside))


def test_image_size_follows_eq2_with_borders():
    rng = np.random.default_rng(1)
    alpha = rng.uniform(-3.0, 5.0, 2000)
    beta = rng.uniform(10.0, 30.0, 2000)
    proj = project(alpha, beta, (0.2, 0.4), (7, 3))
    span_a, span_b = np.ptp(alpha), np.ptp(beta)
    assert proj.shape == (int(span_b / 0.4) + 1 + 2 * 3, int(span_a / 0.2) + 1 + 2 * 7)
    # the border rows and columns are empty, the first inner ones are not
    assert (proj.image[:3] == EMPTY).all() and (proj.image[:, :7] == EMPTY).all()
    assert (proj.image[3] == OCCUPIED).any() and (proj.image[:, 7] == OCCUPIED).any()


def test_tree_across_the_azimuth_wrap_stays_one_compact_image():
    rng = np.random.default_rng(2)
    pts = _tree_like(rng, centre_xy=(-10.0, 0.0))  # straddles alpha = +-180
    scan = Scan.from_points(pts, "wrap", angular_step_deg=(0.1, 0.1))
    rel = build_sequence(scan, projection=ProjectionParams(theta_deg=30.0, relative_azimuth=True, max_image_px=None), n_scans=3)
    ab = build_sequence(scan, projection=ProjectionParams(theta_deg=30.0, relative_azimuth=False, max_image_px=None), n_scans=3)
    k0 = rel.angles_deg.index(0.0)
    width_rel = rel.projections[k0].shape[1]
    width_abs = ab.projections[k0].shape[1]
    # the crown (a few metres at 10 m) spans some 40-60 deg: a few hundred px at 0.2 deg, not 360 deg
    assert width_rel < 600 and width_abs > 1700
    assert abs(abs(rel.azimuth_ref_deg) - 180.0) < 1.0
    # pixel intervals map back to absolute azimuths on both sides of the wrap
    proj = rel.projections[k0]
    alpha = scan.azimuth_deg
    for c in (proj.geometry.border_px[0], proj.shape[1] - proj.geometry.border_px[0] - 1):
        rows = np.nonzero(proj.image[:, c] == OCCUPIED)[0]
        idx = proj.points_of_pixel(int(rows[0]), int(c))
        lo, hi = proj.geometry.alpha_interval_deg(c)
        d = (alpha[idx] - lo + 180.0) % 360.0 - 180.0
        assert ((d >= -1e-4) & (d < hi - lo + 1e-4)).all()


def test_sequence_spans_plus_minus_360_over_n_and_keeps_the_scan_at_zero():
    assert np.allclose(sequence_angles_deg(10.0, 120.0), np.arange(-120, 121, 10))
    rng = np.random.default_rng(3)
    pts = _tree_like(rng, centre_xy=(6.0, 8.0))
    scan = Scan.from_points(pts, "s", angular_step_deg=(0.1, 0.1))
    p = ProjectionParams(theta_deg=10.0, max_image_px=None)
    seq = build_sequence(scan, projection=p, n_scans=3)
    assert len(seq) == 25 and seq.angles_deg[0] == -120.0 and seq.angles_deg[-1] == 120.0
    assert np.allclose(seq.centre_xy, pts[:, :2].mean(axis=0))
    # the image at rotation 0 is the scan's own projection
    alpha, beta = spherical_deg(pts[:, 0], pts[:, 1], pts[:, 2])
    direct = project(alpha, beta, seq.pixel_deg, p.border_px, azimuth_ref_deg=seq.azimuth_ref_deg)
    assert np.mean(direct.image != seq.projections[12].image) < 0.002
    # rotating the points about the centre by +90 deg changes the view: another image
    # (each image spans its own extent, eq. 2: compare the occupied (alpha, beta) cells of both)
    def cells(proj):
        rows, cols = np.nonzero(proj.image == OCCUPIED)
        a_lo, _ = proj.geometry.alpha_interval_deg(cols)
        b_lo, _ = proj.geometry.beta_interval_deg(rows)
        return set(zip(np.rint(a_lo / seq.pixel_deg[0]).astype(int), np.rint(b_lo / seq.pixel_deg[1]).astype(int)))

    c0, c90, again = cells(seq.projections[12]), cells(seq.projections[21]), cells(direct)
    assert len(c0 & c90) / len(c0 | c90) < 0.5  # another view of the tree
    assert len(c0 & again) / len(c0 | again) > 0.98  # the same view, cell for cell


def test_the_rotation_the_app_poses_an_image_by_gives_that_image():
    """`ImageSequence.rotation(k)` applied to the scan and projected again gives image k, cell for cell
    (the app draws the cloud rotated by it next to the image); another image's rotation does not."""
    rng = np.random.default_rng(3)
    pts = _tree_like(rng, centre_xy=(6.0, 8.0))
    scan = Scan.from_points(pts, "s", angular_step_deg=(0.1, 0.1))
    p = ProjectionParams(theta_deg=10.0, max_image_px=None)
    seq = build_sequence(scan, projection=p, n_scans=3)

    def cells(proj):
        rows, cols = np.nonzero(proj.image == OCCUPIED)
        a_lo, _ = proj.geometry.alpha_interval_deg(cols)
        b_lo, _ = proj.geometry.beta_interval_deg(rows)
        return set(zip(np.rint(a_lo / seq.pixel_deg[0]).astype(int), np.rint(b_lo / seq.pixel_deg[1]).astype(int)))

    def posed(k):
        q = apply_transform(seq.rotation(k), pts)
        alpha, beta = spherical_deg(q[:, 0], q[:, 1], q[:, 2])
        return cells(project(alpha, beta, seq.pixel_deg, p.border_px, azimuth_ref_deg=0.0))

    image = cells(seq.projections[21])
    assert len(image & posed(21)) / len(image | posed(21)) > 0.98
    assert len(image & posed(3)) / len(image | posed(3)) < 0.5


def test_image_size_cap_enlarges_pixels_uniformly():
    rng = np.random.default_rng(4)
    scan = Scan.from_points(_tree_like(rng), "s", angular_step_deg=(0.01, 0.01))
    seq = build_sequence(scan, projection=ProjectionParams(theta_deg=60.0, max_image_px=300), n_scans=3)
    assert max(max(p.shape) for p in seq.projections) <= 300 + 2 * 10 + 2
    assert np.isclose(seq.pixel_deg[0] / seq.pixel_deg[1], 1.0)


def test_tie_points_are_pixel_centroids_in_the_scans_own_frame():
    rng = np.random.default_rng(5)
    pts = _tree_like(rng, centre_xy=(8.0, -3.0))
    scan = Scan.from_points(pts, "s", angular_step_deg=(0.1, 0.1))
    seq = build_sequence(scan, projection=ProjectionParams(theta_deg=40.0, max_image_px=None), n_scans=3)
    k = 0  # rotated by -120 deg
    proj = seq.projections[k]
    rows, cols = np.nonzero(proj.image == OCCUPIED)
    rc = np.column_stack([rows[::50], cols[::50]])
    xyz, cnt = pixel_centroids(proj, scan.points, rc)
    assert (cnt > 0).all()
    for (r, c), x in zip(rc[:20], xyz[:20]):
        idx = proj.points_of_pixel(int(r), int(c))
        assert np.allclose(x, pts[idx].mean(axis=0))
    # the rotated centroid projects into its pixel: rotating it by the sequence angle about the centre
    R = rotation_z(seq.angles_deg[k])
    cxy = np.array(seq.centre_xy)
    rot = xyz.copy()
    rot[:, :2] = (xyz[:, :2] - cxy) @ R[:2, :2].T + cxy
    a, b = spherical_deg(rot[:, 0], rot[:, 1], rot[:, 2])
    a = (a - seq.azimuth_ref_deg + 180.0) % 360.0 - 180.0
    g = proj.geometry
    col = np.floor((a - g.alpha_min_deg) / g.pixel_deg[0]).astype(int) + g.border_px[0]
    row = np.floor((b - g.beta_min_deg) / g.pixel_deg[1]).astype(int) + g.border_px[1]
    # a centroid of points inside a cell lies inside it (up to a pixel for curved cells)
    assert np.all(np.abs(col - rc[:, 1]) <= 1) and np.all(np.abs(row - rc[:, 0]) <= 1)
    # an empty pixel gives no tie point
    empty = np.argwhere(proj.image == EMPTY)[:1]
    e_xyz, e_cnt = pixel_centroids(proj, scan.points, empty)
    assert e_cnt[0] == 0 and np.isnan(e_xyz).all()


def test_sequence_span_never_leaves_relative_headings_uncovered():
    rng = np.random.default_rng(6)
    scan = Scan.from_points(_tree_like(rng), "s", angular_step_deg=(0.2, 0.2))
    paper = build_sequence(scan, projection=ProjectionParams(theta_deg=12.0, min_span_deg=0.0, max_image_px=None), n_scans=5)
    robust = build_sequence(scan, projection=ProjectionParams(theta_deg=12.0), n_scans=5)
    assert (paper.angles_deg[0], paper.angles_deg[-1]) == (-72.0, 72.0)  # 360 / n, n = 5
    assert robust.angles_deg[0] <= -84.0 and robust.angles_deg[-1] >= 84.0  # two sequences cover +-180
