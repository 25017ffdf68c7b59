"""Cross-sections and overlap residuals for inspection (treereg_core.evaluate.cross_section,
.residuals, geometry.picking), checked against the simulator's truth: registered by the true
transforms the scans' stem sections make one ring; moved by a coarse-like error, separate arcs."""

from dataclasses import replace

import numpy as np
import pytest

from treereg_core.evaluate.cross_section import branch_section, stem_section
from treereg_core.evaluate.residuals import overlap_residuals
from treereg_core.geometry.picking import nearest_to_ray
from treereg_core.geometry.rigid import apply_transform, make_transform
from treereg_core.params import Params
from treereg_core.prepare.ground import prepare_scan
from treereg_core.simulate.cases import benchmark_cases


@pytest.fixture(scope="module")
def case():
    """A small seeded tree of three stations (no leaves), prepared as the pipeline prepares it, with
    the true poses and the same poses each target moved 4 cm sideways."""
    spec = next(s for s in benchmark_cases(6, seed=0, small=True) if not s.leaves)
    built = spec.build()
    scans = [prepare_scan(s, prepare=Params().prepare).scan for s in built.scans]
    truth = list(built.T_ref_scan)
    shift = make_transform(np.eye(3), [0.04, 0.0, 0.0])
    off = [truth[0]] + [shift @ T for T in truth[1:]]
    return scans, {"truth": truth, "off": off}


def _stem_height(scans):
    z = scans[0].points[:, 2]
    return float(np.quantile(z, 0.001) + 0.5)


def test_registered_stem_is_one_ring_and_a_misregistered_one_separate_arcs(case):
    scans, poses = case
    p = Params()
    cs = stem_section(scans, poses, _stem_height(scans), thickness_m=0.1, below_m=0.3, arcs=p.arcs, sections=p.sections)
    assert cs.ok and cs.heights_m[1] - cs.heights_m[0] == pytest.approx(0.3)
    truth, off = cs.pose("truth"), cs.pose("off")
    # Every scan sees one side of the stem: its slab's largest arc is fitted, plausibly.
    for sc in truth.layers[1].scans:
        assert sc.n_arcs >= 1 and sc.sections[0].plausible, (sc.scan, sc.sections[:1])
        assert len(sc.uv) == len(sc.indices) == len(sc.labels) == len(sc.cells)
    # The targets' stem centres coincide with the reference's under the truth (a ring) and lie the
    # 4 cm shift away under the moved poses (separate arcs).
    assert set(truth.offsets_m[1]) == {s.name for s in scans[1:]}
    assert truth.spread_m(1) < 0.006
    assert all(0.03 < d < 0.05 for d in off.offsets_m[1].values()), off.offsets_m[1]
    # The points are the same slab, moved: the target's section-plane coordinates shift by 4 cm in x.
    a = next(sc for sc in truth.layers[1].scans if sc.index == 1)
    b = next(sc for sc in off.layers[1].scans if sc.index == 1)
    common = np.intersect1d(a.indices, b.indices)
    ua = a.uv[np.searchsorted(a.indices, common)]
    ub = b.uv[np.searchsorted(b.indices, common)]
    np.testing.assert_allclose(ub - ua, np.tile([0.04, 0.0], (len(common), 1)), atol=1e-9)


def test_unrolled_along_the_reference_circle_the_scans_lie_on_it_or_off_by_the_error(case):
    scans, poses = case
    p = Params()
    cs = stem_section(scans, poses, _stem_height(scans), thickness_m=0.1, below_m=0.3, arcs=p.arcs, sections=p.sections)
    truth, off = cs.ring("truth", 1), cs.ring("off", 1)
    assert truth.radius_m == off.radius_m  # the reference's circle: the same under every registration
    for s in scans:
        assert len(truth.offset_m[s.name]) > 20
        assert np.median(np.abs(truth.offset_m[s.name])) < 0.006
    # A target moved 4 cm in x: its arc lies up to 4 cm off the circle (the most where it faces +-x).
    worst = max(np.percentile(np.abs(off.offset_m[s.name]), 90) for s in scans[1:])
    assert 0.015 < worst < 0.05, worst
    assert cs.ring("nonsense", 1) is None


def test_the_taper_check_names_the_part_below_and_drops_a_wider_section(case):
    scans, poses = case
    p = Params()
    h = _stem_height(scans)
    cs = stem_section(scans, {"truth": poses["truth"]}, h, thickness_m=0.1, below_m=0.3, arcs=p.arcs, sections=p.sections)
    ref = cs.pose("truth").layers[1].scans[0]
    below = cs.pose("truth").layers[0].scans[0]
    assert ref.below[0] >= 0 and below.sections[ref.below[0]].plausible  # the stem's part below was found
    # A taper tolerance of -50 % makes any section at least as wide as half the part below "too wide".
    strict = replace(p.sections, taper_tolerance=-0.5)
    cs2 = stem_section(scans, {"truth": poses["truth"]}, h, thickness_m=0.1, below_m=0.3, arcs=p.arcs, sections=strict)
    s = cs2.pose("truth").layers[1].scans[0].sections[0]
    assert not s.plausible and "paper 4.2" in s.reason


def test_a_height_outside_the_tree_says_so(case):
    scans, poses = case
    p = Params()
    cs = stem_section(scans, poses, 500.0, thickness_m=0.1, below_m=0.3, arcs=p.arcs, sections=p.sections)
    assert not cs.ok and "pick a height inside the tree" in cs.message


def test_a_branch_section_keeps_the_points_near_its_axis(case):
    scans, poses = case
    p = Params()
    h = _stem_height(scans)
    centre = np.array([*np.median(scans[0].points[np.abs(scans[0].points[:, 2] - h) < 0.05, :2], axis=0), h])
    cs = branch_section(scans, {"truth": poses["truth"]}, point_m=centre, axis=np.array([0.0, 0.0, 1.0]),
                        radius_m=0.05, layer_z_m=[h - 0.1, h, h + 0.1], thickness_m=0.05, margin_m=0.02,
                        arcs=p.arcs, sections=p.sections)
    assert len(cs.heights_m) == 3
    for layer in cs.pose("truth").layers:
        for sc in layer.scans:
            assert np.all(np.linalg.norm(sc.uv, axis=1) <= 0.07 + 1e-9)


def test_overlap_residuals_are_small_when_registered_and_grow_with_the_error(case):
    scans, poses = case
    med = {}
    for name, Ts in poses.items():
        clouds = [apply_transform(T, s.points) for T, s in zip(Ts, scans)]
        res = overlap_residuals(clouds, [np.arange(0, len(c), 5) for c in clouds], reach_m=0.1)
        assert [len(r) for r in res] == [len(range(0, len(c), 5)) for c in clouds]
        med[name] = float(np.nanmedian(np.concatenate(res)))
    assert med["truth"] < 0.008 and med["off"] > 2.5 * med["truth"], med


def test_a_click_picks_the_point_in_front():
    pts = np.array([[0.0, 0.0, 10.0], [0.0, 0.05, 5.0], [0.0, 3.0, 5.0]])
    assert nearest_to_ray(pts, np.zeros(3), np.array([0.0, 0.0, 1.0])) == 1  # 0.6 deg off the ray, nearer
    assert nearest_to_ray(pts, np.zeros(3), np.array([0.0, 0.0, 1.0]), max_angle_deg=0.1) == 0
    assert nearest_to_ray(pts, np.zeros(3), np.array([0.0, 0.0, -1.0])) is None  # behind the camera
