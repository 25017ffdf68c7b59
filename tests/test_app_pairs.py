"""Every pair the app offers, on every stage, without a browser (issue 29): with three scans the
pair between the two targets (scan3 → scan2), with four six pairs, one of them with a scan of
another tree. And an uploaded scan keeps what its file says: a posed PTX registers through the app
as `treereg register` registers it.
"""

from __future__ import annotations

import logging
import shutil

import numpy as np
import pytest
import viser

from treereg_cli.main import main
from treereg_core.demo import DEMO_DIR, demo_case
from treereg_core.fine.slicing import SliceResult
from treereg_core.geometry.rigid import make_transform, rotation_z
from treereg_core.io.ptx import write_ptx
from treereg_core.io.scans import read_scan
from treereg_core.io.transforms import read_transforms
from treereg_core.prepare.ground import PreparedScan
from treereg_core.simulate.cases import CaseSpec
from treereg_core.stages import STAGE_NAMES, stage
from treereg_viewer.app import TreeregApp
from treereg_viewer.controller import Controller
from treereg_viewer.export import transform_file
from treereg_viewer.stages.base import TargetControl, pair_labels


def other_tree():
    """A station of another tree (as tests/test_browser_reading.py uses): its pairs fail as
    "not the same tree", so the four-scan app also draws failed and skipped pairs."""
    scan = CaseSpec(seed=607, height_m=13.89, angular_step_deg=(0.0449, 0.0449)).build().scans[1]
    return scan.with_points(scan.points, name="other.ply")


def _idle(app: TreeregApp, timeout: float = 300.0) -> None:
    assert app.controller.wait_idle(timeout), "the pipeline did not finish"
    assert app.drawer.wait_idle(60.0), "drawing did not finish"


@pytest.fixture(scope="module", params=[3, 4], ids=["3 scans", "4 scans"])
def registered(request):
    """The app after a whole run on the demo's three stations (plus another tree's, for four)."""
    scans = list(demo_case().scans) + ([other_tree()] if request.param == 4 else [])
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = TreeregApp(server, Controller(scans), tabs="shared")
    _idle(app)
    yield request.param, app
    app.close()
    server.stop()


@pytest.mark.slow
def test_every_stage_draws_every_offered_pair(registered, caplog):
    n, app = registered
    snap = app.controller.snapshot
    assert all(snap.output(s) is not None for s in STAGE_NAMES), snap.message
    labels = pair_labels(snap)
    assert len(labels) == n * (n - 1) // 2  # three scans: every pair; four: the pipeline's choice, here all six
    assert f"{snap.scans[2].name} → {snap.scans[1].name}" in labels
    failures = {}
    with caplog.at_level(logging.ERROR):
        for name in STAGE_NAMES:
            app.select_stage(name)
            _idle(app)
            for k, label in enumerate(labels):
                try:
                    # As a person picks it: the stage's own "Pair" list where it has one.
                    target = next((c for c in app.stages.controls[name] if isinstance(c, TargetControl)), None)
                    if target is not None:
                        target.dropdown.value = label
                    else:
                        app.viewer.select_target(label)
                    _idle(app)
                except Exception as e:  # a control's callback that raised
                    failures[(name, label)] = f"{type(e).__name__}: {e}"
                    continue
                message, heading = app.controller.snapshot.message, app.panel.title.replace("\\", "")  # names escaped: '\.'
                if "Drawing failed" in message:
                    failures[(name, label)] = message
                elif app.view.target != k or (stage(name).per == "pair" and label not in heading):
                    failures[(name, label)] = f"pair {app.view.target} shown: {heading}"  # the heading names the pair drawn
                elif stage(name).per == "pair":
                    # Drawn in the pair's reference scan's frame, where that scan is shown.
                    layer, ref = app.drawer._groups[name], app.drawer._scan_frames[snap.pair(k).ref]
                    if not (np.allclose(layer.position, ref.position) and np.allclose(layer.wxyz, ref.wxyz)):
                        failures[(name, label)] = f"drawn at {layer.position}, its reference at {ref.position}"
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]  # on the drawer's and the worker's threads
    failures.update({("log", i): r.getMessage() + (f" ({r.exc_info[1]!r})" if r.exc_info else "")
                     for i, r in enumerate(errors)})
    assert not failures, failures


def test_a_pair_is_read_through_its_own_scans(registered):
    """`Snapshot.pair`: the pair between two targets joins its own scans, its items are its own."""
    n, app = registered
    snap = app.controller.snapshot
    k = next(k for k in range(snap.n_pairs) if snap.pair(k).ref != 0)
    pair = snap.pair(k)
    assert (pair.ref, pair.tgt) == (snap.pairs[k].ref, snap.pairs[k].tgt) and pair.ref_scan is snap.scans[pair.ref]
    assert pair.label == f"{snap.scans[pair.tgt].name} → {snap.scans[pair.ref].name}" == pair_labels(snap)[k]
    assert pair.item("slices", SliceResult) is snap.output("slices").items[k] or \
        not isinstance(snap.output("slices").items[k], SliceResult)
    ref, tgt = pair.scan_items("prepare", PreparedScan)
    assert ref is snap.output("prepare").items[pair.ref] and tgt is snap.output("prepare").items[pair.tgt]
    with pytest.raises(ValueError, match="per-scan"):
        pair.item("prepare", PreparedScan)
    with pytest.raises(IndexError):
        snap.pair(snap.n_pairs)


def _gridded(scan, step_deg: float) -> tuple[np.ndarray, int, int]:
    """The scan's points on its row/column grid (the demo's lie on a 0.06 deg grid), 0 0 0 where the
    scanner had no return: what a PTX holds."""
    col = np.rint((scan.azimuth_deg - scan.azimuth_deg.min()) / step_deg).astype(int)
    row = np.rint((scan.elevation_deg - scan.elevation_deg.min()) / step_deg).astype(int)
    rows, cols = row.max() + 1, col.max() + 1
    grid = np.zeros((rows, cols, 3))
    grid[row, col] = scan.points
    return grid, rows, cols


@pytest.mark.slow
def test_a_posed_ptx_uploaded_registers_as_register_does(tmp_path):
    """An uploaded PTX keeps its pose (and its steps read off the grid): the app's transforms.json
    says what `treereg register` says for the same files."""
    case = demo_case()
    for s in case.scans[:2]:
        shutil.copy(DEMO_DIR / s.name, tmp_path / s.name)
    pose = make_transform(rotation_z(30.0), [10.0, 5.0, 1.5])
    grid, rows, cols = _gridded(case.scans[2], 0.06)
    ptx = write_ptx(tmp_path / "scan3.ptx", [(grid, pose, rows, cols)])
    out = tmp_path / "cli.json"
    assert main(["register", str(tmp_path / "scan1.ply"), str(tmp_path / "scan2.ply"), str(ptx), "--out", str(out)]) == 0
    cli = read_transforms(out)

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = TreeregApp(server, Controller([read_scan(tmp_path / "scan1.ply"), read_scan(tmp_path / "scan2.ply")]),
                     autorun=False)
    try:
        app.uploads.receive(app.scans.upload, "scan3.ptx", ptx.read_bytes())  # what a browser's upload ends in
        _idle(app)
        uploaded = app.controller.snapshot.scans[-1]
        assert uploaded.name == "scan3.ptx" and uploaded.pose is not None and np.allclose(uploaded.pose, pose)
        assert uploaded.step is not None and uploaded.step.source == "grid"
        app.controller.request_run()
        _idle(app)
        tf, _ = transform_file(app.controller.snapshot)
    finally:
        app.close()
        server.stop()
    assert sorted(tf.transforms) == sorted(cli.transforms) == ["scan1.ply", "scan2.ply", "scan3.ptx"]
    for name in cli.transforms:
        assert np.allclose(tf.matrix(name), cli.matrix(name), atol=1e-9), name
    assert np.allclose(tf.extra["poses"]["scan3.ptx"], cli.extra["poses"]["scan3.ptx"])
    assert np.allclose(np.asarray(cli.extra["poses"]["scan3.ptx"])[:3, 3], [10.0, 5.0, 1.5])
