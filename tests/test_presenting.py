"""Presenting and projector mode without a browser (issue 32 items 2 and 3): two viewers of one app,
their callbacks fired as a browser would fire them — and as a browser could fire them against a
greyed-out control (the server refuses what the page only greys out).
"""

from __future__ import annotations

from dataclasses import replace

import pytest
import viser

from conftest import read
from treereg_core.demo import demo_case
from treereg_viewer.app import TreeregApp
from treereg_viewer.controller import Controller
from treereg_viewer.viewer import PROJECTOR_SCALE, Viewer


@pytest.fixture(scope="module")
def demo():
    return demo_case()


@pytest.fixture()
def two_tabs(demo):
    """An app that runs nothing by itself, with a second viewer ("tab 2") beside its own (its GUI and
    scene those of a second server: a tab's own)."""
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    other = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = TreeregApp(server, Controller(list(demo.scans), truth=demo.truth), autorun=False)
    second = Viewer(app, other.gui, other.scene, None, other.atomic, name="tab 2")
    app._viewers[2] = second
    yield app, app.viewer, second
    app.close()
    server.stop()
    other.stop()


def test_a_follower_cannot_change_parameters_run_or_take_the_lead(two_tabs, monkeypatch, tmp_path):
    app, teacher, pupil = two_tabs
    teacher.present_box.value = True  # "Others follow me"
    assert app.presenter is teacher and pupil.following and pupil.read_only
    assert pupil.stages.sections["arcs"].handles["min_points"].disabled
    assert pupil.stages.run_button.disabled and pupil.present_box.disabled
    # What a page could still send: refused, nothing changes.
    before = app.controller.params
    assert pupil.on_param_change("arcs", "min_points", 20) is not None
    pupil.load_params(replace(before, arcs=replace(before.arcs, min_points=20)), "x.json")
    assert app.controller.params == before
    runs = []
    monkeypatch.setattr(app.controller, "request_run", lambda *a, **k: runs.append(a))
    pupil.run_current()
    assert not runs
    pupil.present_box.value = True
    assert app.presenter is teacher and not pupil.present_box.value
    assert not app.hand_over(pupil, "this tab") and app.presenter is teacher
    pupil.key_step(1)
    assert pupil.view.stage == teacher.view.stage  # a follower's keys do not step it
    assert pupil.scans.upload.disabled and pupil.align.locked
    sent = tmp_path / "scan4.ply"
    sent.write_bytes(b"ply")
    pupil.scans._add_file("scan4.ply", sent)  # a scan file sent anyway: dropped, not added
    assert not sent.exists() and len(app.controller.snapshot.scans) == 3


def test_a_change_in_another_tab_is_named_and_undone(two_tabs):
    app, teacher, pupil = two_tabs
    teacher.present_box.value = True
    pupil.follow_box.value = False  # on its own: it may change the shared parameters
    assert not pupil.read_only and not pupil.stages.sections["arcs"].handles["min_points"].disabled
    old = app.controller.params.arcs.min_points
    assert pupil.on_param_change("arcs", "min_points", old + 5) is None
    assert teacher.changed_md.visible and teacher.undo_button.visible
    assert f"Changed by tab 2: arcs.min_points {old} → {old + 5}." in read(teacher.changed_md.content)
    teacher.undo_button.value = True  # Undo
    assert app.controller.params.arcs.min_points == old
    assert pupil.changed_md.visible and "Changed by this tab: undid tab 2's change" in read(pupil.changed_md.content)  # the undo is told to tab 2


def test_only_the_presenter_hands_the_lead_over(two_tabs):
    app, teacher, pupil = two_tabs
    teacher.present_box.value = True
    assert teacher.hand_to.visible and tuple(teacher.hand_to.options) == ("tab 2",)
    assert app.hand_over(teacher, "tab 2")
    assert app.presenter is pupil and pupil.present_box.value and not pupil.read_only
    assert teacher.following and teacher.read_only and teacher.present_box.disabled
    pupil.present_box.value = False  # the presenter stops: nobody leads, nobody is read-only
    assert app.presenter is None and not teacher.read_only and not teacher.present_box.disabled


def test_projector_mode_scales_labels_lines_points_and_binds_the_arrows(two_tabs):
    app, teacher, _ = two_tabs
    assert teacher.drawer.wait_idle(30)

    def sizes():
        labels = [h.font_screen_scale for h in teacher.drawer._handles["scans"] if isinstance(h, viser.LabelHandle)]
        points = [h.point_size for h in teacher.drawer._handles["scans"] if isinstance(h, viser.PointCloudHandle)]
        return labels, points

    labels, points = sizes()
    assert labels and points and teacher.keys.commands["arrowright"].disabled
    teacher.projector_box.value = True
    assert teacher.drawer.wait_idle(30)
    big_labels, big_points = sizes()
    assert big_labels == pytest.approx([PROJECTOR_SCALE * s for s in labels])
    assert big_points == pytest.approx([PROJECTOR_SCALE * s for s in points])
    assert teacher.projector_css.visible and not teacher.keys.commands["arrowright"].disabled
    teacher.key_step(1)
    assert teacher.view.stage == "projection"


def test_a_hypothesis_picked_in_another_tab_is_named_and_undone(two_tabs, monkeypatch):
    app, teacher, pupil = two_tabs
    picked = []
    monkeypatch.setattr(app.controller, "choose", lambda pair, candidate: picked.append((pair, candidate)))
    pupil.choose_hypothesis("scan2 -> scan1", "half turn")
    assert picked == [("scan2 -> scan1", "half turn")]
    assert "Changed by tab 2: the hypothesis of scan2 -> scan1 automatic → half turn." in read(teacher.changed_md.content)
    teacher.undo_button.value = True
    assert picked[-1] == ("scan2 -> scan1", None)  # automatic again
    teacher.present_box.value = True  # a follower cannot pick one
    pupil.choose_hypothesis("scan2 -> scan1", "half turn")
    assert len(picked) == 2
