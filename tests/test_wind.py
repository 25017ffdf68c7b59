"""Wind between the stations and mixed pixels: simulated, modelled, verified, reported.

Small seeded cases (two stations of an 8 m tree); the full families are in
`benchmarks/bench_verify.py --families wind mixed wind+mixed "wind negatives"`.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import read
from treereg_core.fine.bend import Bend, cantilever
from treereg_core.fine.stem import stem_profile
from treereg_core.geometry.rigid import apply_transform, mean_displacement, rotation_error_deg
from treereg_core.params import PRESETS, Params
from treereg_core.pipeline import Pipeline
from treereg_core.prepare.ground import stem_position
from treereg_core.prepare.mixed import find_mixed, remove_mixed
from treereg_core.scan import Scan
from treereg_core.simulate.cases import CaseSpec
from treereg_core.simulate.tree import LABEL_TRUNK
from treereg_core.verify.evidence import VERIFIED, _motion_needed


def _case(**options):
    opts = dict(seed=101, height_m=8.5, angular_step_deg=(0.05, 0.05), n_stations=2)
    opts.update(options)
    return CaseSpec(**opts).build()


def _pair(case, params=None):
    pipe = Pipeline(list(case.scans), params or Params(), case.truth())
    pipe.run("graph")
    v = pipe.output("verify").items[0]
    T_true = case.T_ref_scan[1]
    return pipe, v, rotation_error_deg(v.T_ref_target, T_true), mean_displacement(v.T_ref_target, T_true,
                                                                                    case.scans[1].points)


def test_cantilever_holds_the_base_and_moves_the_top():
    s = np.array([0.0, 1 / 3, 1.0])
    f = cantilever(s)
    assert f[0] == 0.0 and f[2] == 1.0
    assert 0.1 < f[1] < 0.2  # the lowest third moves about a sixth of the top's sway
    assert cantilever(np.array([-0.5]))[0] == 0.0  # below the base nothing moves


def test_wind_bends_the_stem_not_its_base_and_truth_records_it(tmp_path):
    from treereg_core.simulate.cases import write_case

    still, windy = _case(), _case(wind_m=0.3)
    assert windy.stations[1].sway is not None and abs(windy.stations[1].sway.magnitude_m - 0.3) < 1e-9
    # The same rays hit the stem's base in both; the top of the stem is displaced by the sway.
    for case in (still, windy):
        assert case.scans[1].n_points > 5000
    trunk_w = windy.world_points(1)[windy.labels[1] == LABEL_TRUNK]
    trunk_s = still.world_points(1)[still.labels[1] == LABEL_TRUNK]
    low_w, low_s = (p[p[:, 2] < 0.5, :2].mean(axis=0) for p in (trunk_w, trunk_s))
    assert np.hypot(*(low_w - low_s)) < 0.01
    high_w, high_s = (p[p[:, 2] > 5.0, :2].mean(axis=0) for p in (trunk_w, trunk_s))
    assert np.hypot(*(high_w - high_s)) > 0.05
    truth = json.loads(write_case(windy, tmp_path).read_text())
    wind = truth["stations"]["scan2.ply"]["wind"]
    assert wind["top_sway_m"] == pytest.approx(0.3) and "direction_deg" in wind
    assert truth["simulation"]["wind_m"] == 0.3


def test_mixed_pixels_are_simulated_and_the_filter_finds_them():
    case = _case(mixed_pixels=0.4)
    s, truth = case.scans[0], case.mixed[0]
    assert 0.02 < truth.mean() < 0.3  # a few to tens of per cent of the points
    found = find_mixed(s.points, s.azimuth_deg, s.elevation_deg, s.angular_step_deg, 0.02, 4.0)
    # most are found, tails strung out side by side behind one edge too ...
    assert (found & truth).sum() >= 0.85 * truth.sum()
    assert (found & ~truth).sum() <= 0.01 * s.n_points  # ... and few real returns are taken
    clean = _case().scans[0]
    assert remove_mixed(clean, enabled=True, tolerance_m=0.02, slope=4.0).n_removed <= 0.01 * clean.n_points
    assert remove_mixed(clean, enabled=False, tolerance_m=0.02, slope=4.0).n_removed == 0


def test_the_mixed_pixel_filter_stays_off_without_a_regular_grid():
    # A cloud whose steps are only guessed (a merged cloud, a scan not in its scanner frame): its
    # neighbours on the guessed grid are not the beam's, so nothing is taken and the table says why.
    s = _case(mixed_pixels=0.4).scans[0]
    resampled = s.points + np.random.default_rng(0).normal(0.0, 0.02, s.points.shape)  # off the beam's grid
    guessed = Scan.from_points(resampled, name="merged.ply")
    assert guessed.step.low
    out = remove_mixed(guessed, enabled=True, tolerance_m=0.02, slope=4.0)
    assert out.n_removed == 0 and "no regular angular grid" in str(out.metrics[0].value)
    assert out.not_filtered == out.metrics[0].value  # what the Scans panel says, kept in the result


def test_the_mixed_pixel_filter_does_not_take_a_surface_rougher_than_the_grid():
    # Stations simulated from a real leafy crown sparser than their angular grid: most returns lie
    # behind a range jump and nothing continues them; they are the tree, not tails.
    from pathlib import Path
    from treereg_core.simulate.cases import simulate_case
    cloud = Path(__file__).resolve().parents[2] / "shared" / "data" / "real_trees" / "rtls_pc_tree.xyz"
    if not cloud.exists():
        pytest.skip("../shared/data/real_trees/rtls_pc_tree.xyz is not beside the project")
    s = simulate_case(seed=0, from_points=str(cloud), angular_step_deg=(0.05, 0.05)).scans[0]
    assert find_mixed(s.points, s.azimuth_deg, s.elevation_deg, s.angular_step_deg, 0.02, 4.0).mean() > 0.4
    out = remove_mixed(s, enabled=True, tolerance_m=0.02, slope=4.0)
    assert out.n_removed == 0 and "too many to be tails" in str(out.metrics[0].value)


def test_bend_unbend_is_its_own_inverse():
    b = Bend(-1.5, 8.0, (0.1, -0.2))
    p = np.array([[0.0, 0.0, -1.5], [1.0, 2.0, 6.5], [0.5, 0.0, 2.0]])
    assert np.allclose(b.bend(b.unbend(p)), p)
    assert np.allclose(b.unbend(p)[0], p[0])  # the base stays
    assert np.allclose(b.unbend(p)[1, :2] - p[1, :2], [0.1, -0.2])  # the top takes the whole shift
    assert b.sway_m == pytest.approx(np.hypot(0.1, 0.2))


def test_the_stem_profile_measures_the_sway_and_is_flat_in_still_air():
    for wind in (0.0, 0.3):
        case = _case(wind_m=wind)
        ref, tgt = case.scans
        T = case.T_ref_scan[1]
        z = ref.points[:, 2]
        lo, hi = float(np.quantile(z, 0.001)), float(np.quantile(z, 0.999))
        pts = apply_transform(T, tgt.points)
        prof = stem_profile(ref.points, pts, stem_position(ref.points, z - lo),
                            stem_position(pts, pts[:, 2] - lo), (lo, hi))
        true = float(np.linalg.norm(case.relative_sway_m(1)))
        assert prof.model is not None and prof.n >= 8
        if wind:
            assert abs(prof.sway_m - true) <= max(0.3 * true, 0.02)
            assert prof.stable_height_m(0.005) < 3.0
        else:
            assert prof.sway_m < 0.03 and np.abs(prof.offsets_m).max() < 0.01


def test_motion_needed_is_the_allowance_that_makes_the_views_agree():
    d = np.array([0.01, 0.02, 0.05, 0.2])
    assert _motion_needed(d, 1000, 0.95) == 0.0  # 996 agree of 1000: no allowance needed
    assert _motion_needed(d, 60, 0.95) == pytest.approx(0.02)  # 56 agree: 2 may stay beyond, the 2 nearest moved
    assert _motion_needed(d, 24, 0.95) == pytest.approx(0.05)  # 20 agree: 1 may stay beyond
    assert _motion_needed(d, 14, 0.95) == pytest.approx(0.2)  # 10 agree: every one must have moved


@pytest.mark.slow
@pytest.mark.parametrize("wind", [0.15])
def test_a_swayed_pair_is_verified_and_right_and_says_how_far_the_crown_moved(wind):
    case = _case(wind_m=wind)
    pipe, v, rot, disp = _pair(case)
    assert v.verdict == VERIFIED, v.reasons
    assert rot < 0.2 and disp < 0.01  # the wind criteria are 0.5 deg and 1.5 cm; the model does better
    true = float(np.linalg.norm(case.relative_sway_m(1)))
    assert v.evidence.sway_m > 0 and abs(v.evidence.sway_m - true) <= max(0.3 * true, 0.02)
    assert any("crown moved between the stations" in m.description for m in v.metrics)
    # With wind not modelled, the same pair ends centimetres off (the fit tilts the scan to line the
    # crowns up): the reason the model exists.
    _, _, rot_rigid, disp_rigid = _pair(case, Params().with_value("wind", "enabled", False))
    assert disp_rigid > 3 * disp and disp_rigid > 0.01


@pytest.mark.slow
def test_a_pair_with_mixed_pixels_is_verified_and_right():
    case = _case(mixed_pixels=0.4)
    _, v, rot, disp = _pair(case)
    assert v.verdict == VERIFIED, v.reasons
    assert rot < 0.2 and disp < 0.005
    # Without the filter the tails smear the projection images and lie in the reference's free space:
    # the same pair is refused (it comes out 100 deg off).
    _, v_off, _, _ = _pair(case, Params().with_value("prepare", "mixed_pixels", False))
    assert v_off.verdict != VERIFIED


def test_a_swayed_pair_of_two_different_trees_is_refused():
    a = CaseSpec(seed=510, height_m=9.0, angular_step_deg=(0.05, 0.05), n_stations=2, wind_m=0.2).build()
    b = CaseSpec(seed=610, height_m=9.4, angular_step_deg=(0.05, 0.05), n_stations=2, wind_m=0.2).build()
    pipe = Pipeline([a.scans[0], b.scans[1]], Params())
    pipe.run("graph")
    assert pipe.verdicts()["scan2.ply"][0] != VERIFIED


def test_the_paper_preset_models_no_wind_and_filters_no_mixed_pixels():
    p = PRESETS["paper"]
    assert not p.wind.enabled and not p.prepare.mixed_pixels
    assert Params().wind.enabled and Params().prepare.mixed_pixels


def test_the_crown_motion_reaches_transforms_json_and_the_command_line(tmp_path, capsys):
    from treereg_cli.main import main
    from treereg_core.simulate.cases import write_case

    case = _case(wind_m=0.15)
    write_case(case, tmp_path)
    out = tmp_path / "t.json"
    assert main(["register", str(tmp_path / "scan1.ply"), str(tmp_path / "scan2.ply"), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "wind: scan2.ply: the crown moved" in printed
    q = json.loads(out.read_text())["quality"]
    m = q["scans"]["scan2.ply"]["crown_motion"]
    true = float(np.linalg.norm(case.relative_sway_m(1)))
    assert m["relative_to"] == "scan1.ply" and abs(m["top_sway_m"] - true) <= max(0.3 * true, 0.02)
    assert m["stems_agree_up_to_m"] is not None and m["stems_agree_up_to_m"] >= 0
    assert q["edges"][0]["sway_m"] == pytest.approx(m["top_sway_m"])


def test_the_scans_table_says_why_a_scan_was_not_filtered():
    import viser

    from treereg_viewer.controller import Snapshot
    from treereg_viewer.stages.prepare import render
    from treereg_viewer.view_state import ViewState

    s = _case(mixed_pixels=0.4).scans[0]
    resampled = Scan.from_points(s.points + np.random.default_rng(0).normal(0.0, 0.02, s.points.shape), name="merged.ply")
    pipe = Pipeline([s, resampled], Params())
    pipe.run(until="prepare")
    snap = Snapshot(version=1, scans=(s, resampled), truth=None, params=Params(),
                    outputs={"prepare": pipe.output("prepare")}, transforms={}, pair_metrics={})
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        _, panel = render(server.scene, "/t", snap, ViewState())
    finally:
        server.stop()
    assert "not filtered" in panel.table and "merged.ply: mixed pixels off: no regular angular grid" in read(panel.text)
