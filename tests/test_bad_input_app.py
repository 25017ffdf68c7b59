"""Hostile input, round 2 (issue 17): the app's threads and tabs, signals, warnings, `--tree-at`.

- viser is called only from the app's own threads (the drawing thread, viser's callbacks), never
  from the pipeline's worker: a call from there once ended a run with "deque mutated during iteration".
- Two tabs changing a parameter at once (one presses Run while the other's keystroke is on its
  way in): each tab's inputs show the parameters in force.
- SIGTERM is handled as Ctrl-C: `register` prints one line and exits 143 with every file as it was;
  `view` stops and removes its upload folder.
- A warning that still reaches the command line is one "treereg: warning:" line, no source path.
- `--tree-at X Y` where no stem is: named, exit 2, before any registration; the app says the same.
"""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import threading
import time
import warnings

import pytest
import viser
from viser.infra._infra import WebsockMessageHandler

from hostile import REPO, _env, changed, cli, fingerprint, one_line, sandbox, view_started  # noqa: F401  (sandbox: a fixture)
from conftest import read
from treereg_viewer.app import TreeregApp
from treereg_viewer.controller import Controller
from treereg_viewer.viewer import Viewer

TREE_AT_OFF = (r"--tree-at 50 50: no stem within 2 m of that point in .*scan1\.ply; the stems found at breast height "
               r"are at -11\.43 3\.69 \(r 12 cm\) \(x y in m\); give one of those, or leave --tree-at out")
#: Seconds `treereg view` may take to stop on SIGTERM while its run computes (measured 0.3-0.6 s;
#: an item, the longest a pair's fine stage, is the run's grain).
STOP_S = 3.0


# ---- the app: threads and tabs --------------------------------------------------------------------------
@pytest.fixture(scope="module")
def app():
    """The app on the demo with a second tab (a viewer of its own), every viser message recorded
    with the thread that sent it; nothing run yet."""
    from treereg_core.demo import demo_case

    threads: list[str] = []
    sent: list = []
    original = WebsockMessageHandler.queue_message

    def recording(self, message):
        threads.append(threading.current_thread().name)
        sent.append(message)
        return original(self, message)

    WebsockMessageHandler.queue_message = recording
    demo = demo_case()
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    a = TreeregApp(server, Controller(list(demo.scans), truth=demo.truth), autorun=False)
    # A second tab: a GUI and scene of its own (another server's, as a client's would be).
    other = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    with a._lock:
        a._viewers[1] = Viewer(a, other.gui, other.scene, None, other.atomic)
    a.sent_from, a.sent = threads, sent
    try:
        yield a
    finally:
        WebsockMessageHandler.queue_message = original
        a.close()
        server.stop()
        other.stop()


def _idle(a: TreeregApp, timeout: float = 120.0) -> None:
    assert a.controller.wait_idle(timeout), "the pipeline did not finish"
    for v in a.viewers:
        assert v.drawer.wait_idle(30.0), "drawing did not finish"


def test_app_no_viser_call_from_the_pipeline_thread(app):
    ctl = app.controller
    _idle(app)
    app.sent_from.clear()
    ctl.request_run("projection")  # stages with progress, a snapshot after each
    _idle(app)
    assert ctl.snapshot.output("projection") is not None and ctl.snapshot.output("projection").ok
    assert app.sent_from, "nothing was sent to the browser"
    assert "treereg-worker" not in app.sent_from, sorted(set(app.sent_from))
    assert "Ran " in read(app.stages.message_md.content)  # and the news still reached the tab


def _type(viewer: Viewer, section: str, name: str, text: str) -> None:
    """As a person typing into a tab's input: the value arrives, and waits to settle."""
    w = viewer.stages.sections[section]
    w._syncing.on = True  # the keystroke itself (a browser's update carries its client)
    try:
        w.handles[name].value = text
    finally:
        w._syncing.on = False
    w._changed(name, typed=True)


def test_app_a_keystroke_crossing_the_other_tabs_change_leaves_no_tab_showing_a_value_not_in_force(app):
    """Tab B presses Run with 30 while tab A's keystroke "20" is on its way in: A's browser gets B's 30,
    then the server gets A's 20 (already sent, so the server's copy of A's input says 20), and 20
    is applied. A's browser must then be told 20: it shows what the last message for its input said."""
    from viser._messages import GuiUpdateMessage

    ctl = app.controller
    a, b = app.viewers
    field_a = a.stages.sections["matching"].handles["n_pairs"]

    def shown_in_a() -> str:
        return next(m.updates["value"] for m in reversed(app.sent) if isinstance(m, GuiUpdateMessage)
                    and m.uuid == field_a._impl.uuid and "value" in m.updates)

    _type(b, "matching", "n_pairs", "30")
    b.flush_edits()  # B's Run
    _idle(app)
    assert ctl.params.matching.n_pairs == 30 and shown_in_a() == "30"  # A's browser was told
    field_a._impl.value = "20"  # A's keystroke, sent before that arrived, reaches the server now
    a.stages.sections["matching"]._changed("n_pairs", typed=True)
    time.sleep(1.5)  # it settles and is applied
    _idle(app)
    assert ctl.params.matching.n_pairs == 20
    assert shown_in_a() == "20", "tab A shows 30, 20 is in force"
    assert b.stages.sections["matching"].handles["n_pairs"].value == "20"
    assert app.on_param_change("matching", "n_pairs", 15) is None
    _idle(app)


def test_app_tree_at_off_the_tree_says_so(app):
    ctl = app.controller
    _idle(app)
    assert app.on_param_change("target", "tree_at", "50, 50") is None
    ctl.request_run("prepare")
    _idle(app)
    assert re.search(r"⚠ 1 Scans failed: " + TREE_AT_OFF, read(app.stages.message_md.content)), read(app.stages.message_md.content)
    assert app.on_param_change("target", "tree_at", None) is None
    _idle(app)


# ---- the command line ----------------------------------------------------------------------------------
def test_tree_at_off_the_tree_is_named_exit_2(sandbox, capsys):
    s = sandbox / "scans"
    before = fingerprint(sandbox)
    rc, err = cli(capsys, "register", s / "scan1.ply", s / "scan2.ply", s / "scan3.ply", "--tree-at", "50", "50",
                  "--out", sandbox / "out" / "t.json")
    assert rc == 2, err
    one_line(err, "^treereg: error: " + TREE_AT_OFF)
    assert changed(before, fingerprint(sandbox)) == []


@pytest.mark.timed
def test_sigterm_in_view_stops_it_and_removes_its_upload_folder(tmp_path):
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    proc = subprocess.Popen([sys.executable, "-m", "treereg_cli", "view", "--port", "0"], cwd=REPO,
                            env=dict(_env(), TMPDIR=str(tmp)), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines = view_started(proc)
    assert any("treereg view: http://" in ln for ln in lines), lines
    assert [p.name for p in tmp.iterdir() if p.name.startswith("treereg-uploads-")], "no upload folder made"
    # The demo's first run is under way: the app stops at its next item, not at the run's end
    # (it took 8-11 s, the rest of the run, before).
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert time.monotonic() - t0 < STOP_S, f"view took {time.monotonic() - t0:.1f} s to stop"
    assert proc.returncode == 0, err
    assert "treereg view: stopped (SIGTERM)" in out, out
    assert "Traceback" not in err and not re.search(r"\.py:\d+", err), err
    assert not [p for p in tmp.iterdir() if p.name.startswith("treereg-uploads-")]


def test_a_warning_is_one_line_without_its_source_or_dropped_when_it_is_library_noise(capsys):
    from treereg_cli.main import warning_line

    assert warning_line(RuntimeWarning("overflow encountered\n  in multiply"), RuntimeWarning) == \
        "warning: overflow encountered in multiply"
    assert warning_line(DeprecationWarning("np.foo is deprecated"), DeprecationWarning) is None
    assert warning_line(FutureWarning("will change"), FutureWarning) is None
    # Through the command line's handler: a warning raised while a command runs, twice, prints once.
    from treereg_cli import main as cli_main

    def warns(args) -> int:
        for _ in range(2):
            warnings.warn_explicit("invalid value encountered in divide", RuntimeWarning, "/x/numpy/core.py", 7)
        warnings.warn("a library's API will change", DeprecationWarning)
        return 0

    parser = cli_main.build_parser
    try:
        cli_main.build_parser = lambda *argv: _Parser(warns)
        rc, err = cli(capsys, "anything")
    finally:
        cli_main.build_parser = parser
    assert rc == 0
    one_line(err, r"^treereg: warning: invalid value encountered in divide$")


class _Parser:
    """A parser whose one command is `func` (to run the command line's handlers around it)."""

    def __init__(self, func) -> None:
        self.func = func

    def parse_args(self, argv):
        import argparse

        return argparse.Namespace(func=self.func)
