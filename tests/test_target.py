"""Whole stations of a plot: stems found, stem maps matched, the target tree chosen (by default the
stem the stations surround, or `tree_at`), each station cut to it, and the plot registered."""

import numpy as np
import pytest

from conftest import read
from treereg_core.demo import demo_case
from treereg_core.geometry.rigid import invert, mean_displacement, rotation_error_deg
from treereg_core.params import Params, TargetParams
from treereg_core.pipeline import register
from treereg_core.prepare.ground import find_ground, prepare_scans
from treereg_core.prepare.target import find_stems, match_stem_maps
from treereg_core.simulate.plots import PlotSpec, target_in_scan


@pytest.fixture(scope="module")
def plot():
    return PlotSpec(seed=3, angular_step_deg=(0.25, 0.25), plot_radius_m=15.0, real_like=True).build()


def _trunks_in_scan(case, k):
    """(x, y, DBH/2) of every tree (not shrub) in scan k's frame."""
    T = invert(case.stations[k].T_world_scan)
    out = []
    for t in case.trees:
        if t.shape.height_m > 3.0:  # shrubs are lower
            x, y = (T @ np.r_[t.base_m, 1.0])[:2]
            out.append((x, y, t.shape.dbh_m / 2))
    return np.array(out)


def _stems(scan):
    plane, _ = find_ground(scan.points, Params().prepare)  # cells of 1 m, band 0.3 m
    return find_stems(scan.points, scan.points @ plane[:3] + plane[3])


def test_stems_at_breast_height_are_the_trunks(plot):
    for k, scan in enumerate(plot.scans):
        stems = _stems(scan)
        trunks = _trunks_in_scan(plot, k)
        d = np.hypot(*(stems.xy[:, None, :] - trunks[None, :, :2]).transpose(2, 0, 1))
        found = d.min(axis=0) < 0.1
        # The target and most neighbours are found (a trunk hidden behind another may not be).
        assert found[0], f"{scan.name}: the target's stem was not found"
        assert found.mean() >= 0.6, f"{scan.name}: only {found.sum()} of {len(found)} trunks found"


def test_stem_maps_place_the_stations(plot):
    ref = _stems(plot.scans[0])
    for k in (1, 2):
        T, pairs = match_stem_maps(ref, _stems(plot.scans[k]))
        assert T is not None and len(pairs) >= 3
        T_true = plot.T_ref_scan[k]
        assert np.hypot(*(T[:2, 3] - T_true[:2, 3])) < 0.05
        yaw = np.degrees(np.arctan2(T[1, 0], T[0, 0]) - np.arctan2(T_true[1, 0], T_true[0, 0]))
        assert abs((yaw + 180) % 360 - 180) < 0.5


def test_default_target_is_the_stem_the_stations_surround(plot):
    p = Params()
    prepared = prepare_scans(list(plot.scans), prepare=p.prepare, target=p.target)
    for k, ps in enumerate(prepared):
        assert ps.ok
        assert np.hypot(*(np.asarray(ps.stem_xy) - target_in_scan(plot, k))) < 0.1
        assert "surround" in ps.target
        # cut to the target's disc: nothing farther than the radius, far fewer points than the station
        d = np.hypot(ps.scan.points[:, 0] - ps.stem_xy[0], ps.scan.points[:, 1] - ps.stem_xy[1])
        assert d.max() <= p.target.radius_m + 1e-9 and ps.scan.n_points < 0.5 * plot.scans[k].n_points


def test_tree_at_picks_another_tree(plot):
    trunks = [_trunks_in_scan(plot, k) for k in range(3)]
    at = tuple(trunks[0][1, :2] + 0.3)  # near neighbour 1, in scan 1's frame
    prepared = prepare_scans(list(plot.scans), prepare=Params().prepare, target=TargetParams(tree_at=at))
    for k, ps in enumerate(prepared):
        assert np.hypot(*(np.asarray(ps.stem_xy) - trunks[k][1, :2])) < 0.1, ps.target
    assert "--tree-at" in prepared[0].target


def test_a_scan_cut_to_one_tree_is_left_as_it_is():
    case = demo_case()
    p = Params()
    prepared = prepare_scans(list(case.scans), prepare=p.prepare, target=p.target)
    for ps in prepared:
        assert ps.stem_xy is None and "all points kept" in ps.target


@pytest.mark.slow
def test_plot_registers_and_is_verified_with_the_default_target(plot):
    reg = register(list(plot.scans), Params())
    assert reg.ok
    prepared = reg.pipeline.output("prepare").items
    verdicts = reg.pipeline.verdicts()
    for k, scan in enumerate(plot.scans[1:], start=1):
        T, T_true = reg.transforms[scan.name], plot.T_ref_scan[k]
        # this plot is registered to 0.05 deg and 5 mm; held to about three times that
        assert rotation_error_deg(T, T_true) < 0.15
        assert mean_displacement(T, T_true, prepared[k].scan.points) < 0.015
        assert verdicts[scan.name][0] == "verified", verdicts[scan.name]
    # On a sloping plot the densest low cell of a cut station can be a neighbour's stem: the stem
    # profile (the stems' lean and offset the verifier checks) must trace the target the prepare
    # stage chose in both stations, or a right pose reads as stems metres apart and is refused.
    for pair, item in zip(reg.pipeline.pairs, reg.pipeline.output("fine").items):
        assert item.profile is not None and item.profile.model is not None
        assert np.hypot(*(item.profile.base_xy_m - np.asarray(prepared[pair.ref].stem_xy))) < 0.3
        assert np.hypot(*item.profile.model.shift_m) < 0.02


def test_the_app_marks_the_target_and_takes_another_tree(plot):
    import viser

    from treereg_viewer.app import TreeregApp
    from treereg_viewer.controller import Controller

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = TreeregApp(server, Controller(list(plot.scans)), autorun=False)
    try:
        app.select_stage("prepare")
        app.controller.request_run("prepare")
        assert app.controller.wait_idle(120) and app.drawer.wait_idle(30)
        nodes = set(server.scene._handle_from_node_name)
        assert {"/prepare/s0/target", "/prepare/s1/target", "/prepare/s2/target", "/prepare/s0/stems"} <= nodes
        text = read(app.panel._text.content)
        assert "Target tree:" in text and "surround" in text
        x, y = target_in_scan(plot, 0)
        assert f"{x:.2f}, {y:.2f}" in app.panel.table  # the table names the target's stem
        # Another tree: its stem's x, y typed into "tree at", then Run.
        other = _trunks_in_scan(plot, 0)[1, :2]
        assert app.on_param_change("target", "tree_at", f"{other[0]:.2f}, {other[1]:.2f}") is None
        app.controller.request_run("prepare")
        assert app.controller.wait_idle(120) and app.drawer.wait_idle(30)
        got = app.controller.snapshot.output("prepare").items[0].stem_xy
        assert np.hypot(*(np.asarray(got) - other)) < 0.1
        assert "--tree-at" in read(app.panel._text.content)
    finally:
        app.close()
        server.stop()
