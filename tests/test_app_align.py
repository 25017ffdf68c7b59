"""Align by hand in the app (issue 33 item 2), without a browser: a scan the coarse stage lost (forced
with coarse.max_tilt_deg = 0 on the demo) rescued with three point pairs clicked in 3-D, refined from
there by the pipeline, verified, and its start exported (starts.json, which `register --initial`
reads back, and transforms.json's started_from).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial import cKDTree
import viser

from conftest import read
from treereg_core.demo import demo_case
from treereg_core.geometry.point_pairs import as_file_frames, fit_point_pairs
from treereg_core.geometry.rigid import apply_transform, invert, make_transform, rotation_error_deg, rotation_z
from treereg_core.io.start import read_start
from treereg_core import params as P
from treereg_core.params import Params
from treereg_core.prepare.ground import PreparedScan
from treereg_viewer.align import candidates
from treereg_viewer.app import TreeregApp
from treereg_viewer.controller import Controller
from treereg_viewer.export import PARAMS_NAME, STARTS_NAME, export_bundle


def _idle(app: TreeregApp, timeout: float = 120.0) -> None:
    assert app.controller.wait_idle(timeout), "the pipeline did not finish"
    assert app.drawer.wait_idle(30.0), "drawing did not finish"


def test_fit_point_pairs_and_file_frames():
    rng = np.random.default_rng(1)
    tgt = rng.normal(size=(5, 3))
    T = make_transform(rotation_z(30.0), np.array([1.0, -2.0, 0.5]))
    fit = fit_point_pairs(apply_transform(T, tgt), tgt)
    assert fit.ok and fit.rms_m < 1e-9 and np.allclose(fit.T_ref_tgt, T)
    assert not fit_point_pairs(tgt[:2], tgt[:2]).ok
    line = np.outer(np.arange(4.0), [1.0, 0.0, 0.0])
    assert "one line" in fit_point_pairs(line, line).message
    # The inverse of the coarse stage's to_stage_frames: P_ref^-1 U P_tgt, levelled, gives T back.
    P_ref, P_tgt = make_transform(rotation_z(10.0), np.array([5.0, 0, 0])), make_transform(rotation_z(-40.0), np.ones(3))
    L = make_transform(rotation_z(3.0), np.zeros(3))
    U = as_file_frames(T, ref_pose=P_ref, tgt_pose=P_tgt, ref_level=None, tgt_level=L)
    assert np.allclose(invert(P_ref) @ U @ P_tgt @ invert(L), T)


@pytest.fixture(scope="module")
def refused():
    """The app on the demo whose coarse stage refuses every pose (max_tilt_deg = 0): scans 2 and 3 fail."""
    case = demo_case()
    params = Params().with_value("coarse", "max_tilt_deg", 0.0)
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = TreeregApp(server, Controller(list(case.scans), params, case.truth), tabs="shared")
    _idle(app)
    yield app, case
    app.close()
    server.stop()


def _ray_at(point: np.ndarray, away: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A click's ray from 2 m off `point` (towards `away`, from the tree) straight at it."""
    d = np.asarray(away, float)
    d = d / np.linalg.norm(d)
    return point + 2.0 * d, -d


def test_a_refused_scan_rescued_with_three_point_pairs(refused):
    app, case = refused
    snap = app.controller.snapshot
    name = snap.scans[1].name
    assert snap.verdicts[name][0] == "failed"
    assert name in candidates(snap)
    align = app.viewer.align
    assert name in align.scan_choice.options
    align.scan_choice.value = name
    align.start_button.value = True  # "Align this scan by hand"
    assert app.view.align_scan == name and align.state.scan == name
    _idle(app)
    assert not app.drawer._scans_root.visible  # the scan layer makes way for the two trees

    ref_prep = snap.scan_item("prepare", 0, PreparedScan)
    tgt_prep = snap.scan_item("prepare", 1, PreparedScan)
    T_true = invert(case.truth[snap.scans[0].name]) @ case.truth[name]  # no levelling in the demo
    assert ref_prep.T_level is None and tgt_prep.T_level is None
    # Three points both stations saw (a person picks what both show), spread over the tree: low on the
    # stem, the crown's top, a branch to the side.
    tgt = tgt_prep.scan.points
    near, _ = cKDTree(ref_prep.scan.points).query(apply_transform(T_true, tgt))
    tgt = tgt[near < 0.02]
    centre = np.median(tgt, axis=0)
    chosen = [tgt[np.argmin(tgt[:, 2])], tgt[np.argmax(tgt[:, 2])],
              tgt[np.argmax(np.hypot(*(tgt[:, :2] - centre[:2]).T))]]
    for p in chosen:
        shown = align._D[:3, :3] @ p + align._D[:3, 3]
        away = np.append(shown[:2] - (align._D[:3, :3] @ centre + align._D[:3, 3])[:2], 0.5)
        app.viewer.pick(*_ray_at(shown, away))  # a click on the scan
        picked = np.asarray(align.state.tgt_pick)
        assert np.linalg.norm(picked - p) < 0.3
        q = apply_transform(T_true, picked[None])[0]  # the same point on the reference
        app.viewer.pick(*_ray_at(q, np.append(q[:2] - np.median(ref_prep.scan.points[:, :2], axis=0), 0.5)))
    assert len(align.state.pairs) == 3 and align.state.tgt_pick is None
    fit = align.state.fit()
    assert fit.ok and fit.rms_m < 0.15, fit.message
    assert "RMS residual" in align.status_md.content and "| 3 |" in align.pairs_md.content
    assert not align.refine_button.disabled

    # A pair can be removed (the fit then asks for another) and picked again.
    last = align.state.pairs[-1]
    align.pair_choice.value = "Pair 3"
    align.remove_button.value = True
    assert len(align.state.pairs) == 2 and align.refine_button.disabled
    align.add_pick(ref=last.ref_xyz)
    align.add_pick(tgt=last.tgt_xyz)
    assert len(align.state.pairs) == 3

    start = align.start_pose()
    assert rotation_error_deg(start.T_ref_scan, snap.scans[0].pose @ T_true @ invert(snap.scans[1].pose)) < 5.0
    align.refine_button.value = True  # "Refine from here"
    assert app.view.align_scan is None
    _idle(app)
    snap = app.controller.snapshot
    assert name in snap.starts
    assert snap.verdicts[name][0] == "verified", snap.verdicts[name]
    T = snap.transforms[name]
    truth_user = snap.scans[0].pose @ T_true @ invert(snap.scans[1].pose)
    assert rotation_error_deg(T, truth_user) < 0.5
    assert np.linalg.norm(T[:3, 3] - truth_user[:3, 3]) < 0.05
    assert "verified" in align.verdict_md.content and "Started from" in align.verdict_md.content

    bundle = export_bundle(snap)
    doc = json.loads(bundle.files["transforms.json"])
    assert name in doc["transforms"]
    assert "the app" in json.dumps(doc["quality"]["scans"][name])
    starts = json.loads(bundle.files[STARTS_NAME])
    assert starts["reference"] == snap.scans[0].name and name in starts["transforms"]


def test_starts_json_reads_back_as_a_start_file(refused, tmp_path):
    app, _ = refused
    snap = app.controller.snapshot
    if not snap.starts:
        pytest.skip("needs the rescue above")
    path = tmp_path / STARTS_NAME
    path.write_bytes(export_bundle(snap).files[STARTS_NAME])
    name = next(iter(snap.starts))
    pose = read_start(path, name)
    assert np.allclose(pose.T_ref_scan, snap.starts[name].T_ref_scan)
    assert pose.reference == snap.scans[0].name


def test_a_refused_scan_rescued_by_moving_it_with_the_gizmo(refused):
    """The second way: the scan moved with the transform controls (as their updates set it) to 5 deg
    and 0.3 m from where it belongs, then Refine from here."""
    app, case = refused
    snap = app.controller.snapshot
    name = snap.scans[2].name
    assert snap.verdicts[name][0] == "failed"
    align = app.viewer.align
    align.scan_choice.value = name
    align.start_button.value = True
    align.gizmo_box.value = True
    assert align._gizmo is not None and not align.refine_button.disabled
    T_true = invert(case.truth[snap.scans[0].name]) @ case.truth[name]
    off = make_transform(rotation_z(5.0), np.array([0.3, -0.1, 0.0]))
    C = np.eye(4)
    C[:3, 3] = align._centre()
    align.move_to(off @ T_true @ C)  # the gizmo dragged there: the scan drawn at off @ T_true
    assert np.allclose(align._D, off @ T_true)
    assert "the scan moved by hand" in align.start_pose().source
    align.refine_button.value = True
    _idle(app)
    snap = app.controller.snapshot
    assert snap.verdicts[name][0] == "verified", snap.verdicts[name]
    truth_user = snap.scans[0].pose @ T_true @ invert(snap.scans[2].pose)
    assert rotation_error_deg(snap.transforms[name], truth_user) < 0.5
    assert np.linalg.norm(snap.transforms[name][:3, 3] - truth_user[:3, 3]) < 0.05



def test_start_poses_forgotten_then_loaded_back_from_their_file(refused, tmp_path):
    """Forget the start pose: the scan fails again; the starts.json downloaded before brings it back
    (its source the file's name, not the upload's temporary path); a bad file is one message."""
    app, _ = refused
    snap = app.controller.snapshot
    name = snap.scans[1].name
    if name not in snap.starts:
        pytest.skip("needs the rescue above")
    saved = export_bundle(snap).files[STARTS_NAME]
    align = app.viewer.align
    align.scan_choice.value = name
    assert align.forget_button.visible
    align.forget_button.value = True
    _idle(app)
    snap = app.controller.snapshot
    assert name not in snap.starts and snap.verdicts[name][0] == "failed"
    bad = tmp_path / "a" / "upload"  # each upload in a folder of its own, which discard removes
    bad.parent.mkdir()
    bad.write_text("1 0 0\n")
    align.load_start_file("mine.txt", bad)
    _idle(app)
    assert app.controller.snapshot.error and "mine.txt" in app.controller.snapshot.message
    assert str(bad) not in app.controller.snapshot.message and not bad.exists()
    good = tmp_path / "b" / "upload"
    good.parent.mkdir()
    good.write_bytes(saved)
    align.load_start_file(STARTS_NAME, good)
    _idle(app)
    snap = app.controller.snapshot
    assert snap.starts[name].source == STARTS_NAME
    assert snap.verdicts[name][0] == "verified", snap.verdicts[name]


def test_the_parameters_file_carries_the_start_poses_and_loading_it_restores_them(refused, tmp_path, monkeypatch):
    """params.json (the Files tab's download and the exports) holds the start poses in force beside the
    parameters ("starts", as starts.json has them); it still loads as parameters anywhere
    (`params.from_dict`), `register --initial SCAN=params.json` reads a start from it, and loading it in
    the app gives the starts back to their scans (run when Run is pressed, as the parameters are)."""
    app, _ = refused
    snap = app.controller.snapshot
    name = snap.scans[1].name
    if name not in snap.starts:
        pytest.skip("needs the rescue above")
    sent = {}
    monkeypatch.setattr(app.viewer, "send_file", lambda client, filename, data: sent.update({filename: data}))
    app.viewer.files._download_params(None)
    doc = json.loads(sent[PARAMS_NAME])
    assert json.loads(export_bundle(snap).files[PARAMS_NAME]) == doc  # the exports' params.json: the same
    assert doc["starts"]["reference"] == snap.scans[0].name
    assert set(doc["starts"]["transforms"]) == set(snap.starts)
    assert doc["starts"]["sources"][name] == snap.starts[name].source
    assert P.from_dict(doc) == snap.params
    saved = tmp_path / PARAMS_NAME
    saved.write_bytes(sent[PARAMS_NAME])
    assert np.allclose(read_start(saved, name).T_ref_scan, snap.starts[name].T_ref_scan)
    assert P.load(saved) == snap.params  # `--config params.json` as before

    for n in list(snap.starts):  # every start forgotten (not run: the file gives them back before Run)
        app.controller.start(n, None, run=False)
    _idle(app)
    assert not app.controller.snapshot.starts
    upload = tmp_path / "c" / "upload"
    upload.parent.mkdir()
    upload.write_bytes(sent[PARAMS_NAME])
    app.viewer.files._load_params(PARAMS_NAME, upload)
    _idle(app)
    after = app.controller.snapshot
    assert not upload.exists()
    assert set(after.starts) == set(snap.starts) and "Start poses restored for" in after.message, after.message
    for n in snap.starts:
        assert np.allclose(after.starts[n].T_ref_scan, snap.starts[n].T_ref_scan)
        assert after.starts[n].source == snap.starts[n].source  # where the pose came from, as saved
    assert after.verdicts.get(name, ("",))[0] != "verified"  # not run yet: the parameters wait for Run too
    app.controller.request_run()
    _idle(app)
    after = app.controller.snapshot
    assert after.verdicts[name][0] == "verified", after.verdicts[name]


def test_the_align_tab_escapes_a_hostile_scan_name():
    """A scan named as markup reads as its characters in every markdown of the Align tab."""
    case = demo_case()
    hostile = "<img src=x onerror=alert(1)>*scan2*.ply"
    scans = list(case.scans)
    scans[1] = scans[1].with_points(scans[1].points, name=hostile)
    truth = {hostile if k == case.scans[1].name else k: v for k, v in case.truth.items()}
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = TreeregApp(server, Controller(scans, Params().with_value("coarse", "max_tilt_deg", 0.0), truth), tabs="shared")
    try:
        _idle(app)
        align = app.viewer.align
        assert hostile in align.scan_choice.options  # a dropdown shows text, not markup
        align.scan_choice.value = hostile
        align.start_button.value = True
        assert align.state.scan == hostile
        for t in (align.status_md.content, align.verdict_md.content):
            assert hostile in read(t), t  # rendered as viser renders markdown: the name as given, no tag
        align.stop_button.value = True
        assert app.view.align_scan is None
    finally:
        app.close()
        server.stop()
