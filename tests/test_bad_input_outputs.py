"""Outputs that would destroy an input, export names, odd file names, stale temporaries (issue 17:
items 1, 2, part of 6 and 7, and `--e57 x.ply` of item 8).

Each probe asserts the one line a user sees, the exit code, and that nothing of the user's changed.
The refusals come before anything is read or computed, so most probes take a fraction of a second.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from hostile import REPO, _env, changed, cli, fingerprint, one_line, sandbox  # noqa: F401  (sandbox: a fixture)
from conftest import read
from treereg_core.errors import OutputError
from treereg_core.io import atomic
from treereg_core.io.e57 import read_e57, write_e57
from treereg_core.io.scans import read_points
from treereg_core.io.transforms import read_transforms

NOT_AN_INPUT = r"treereg never replaces an input"


def _e57(path: Path, *scans: Path) -> Path:
    """A multi-scan E57 of the sandbox's scans (an input of the user's)."""
    return write_e57(path, [(p.name, read_points(p), np.eye(4)) for p in scans])


# ---- item 1: no output is an input, no two outputs one file ----------------------------------------
def _probe_args(box: Path, probe: str) -> tuple[list, str]:
    s = box / "scans"
    a, b = s / "scan1.ply", s / "scan2.ply"
    if probe == "out is scan b":
        return [a, b, "--out", b], rf"scan2\.ply: --out is the input .*scan2\.ply; {NOT_AN_INPUT}"
    if probe == "merged is the reference":
        return [a, b, "--merged", a], rf"scan1\.ply: --merged is the input .*scan1\.ply; {NOT_AN_INPUT}"
    if probe == "e57 is the input e57":
        three = _e57(box / "three.e57", a, b, s / "scan3.ply")
        return [three, "--e57", three], rf"three\.e57: --e57 is the input .*three\.e57; {NOT_AN_INPUT}"
    if probe == "out and merged one file":
        return [a, b, "--out", box / "x.ply", "--merged", box / "x.ply"], \
            r"x\.ply: --out and --merged are the same file; each output needs its own name"
    if probe == "out through a symbolic link to a scan":
        (box / "to_scan2.json").symlink_to(b)
        return [a, b, "--out", box / "to_scan2.json"], r"to_scan2\.json: --out is the input .*scan2\.ply \(the same file\)"
    if probe == "out a hard link of a scan":
        os.link(b, box / "hard.json")
        return [a, b, "--out", box / "hard.json"], r"hard\.json: --out is the input .*scan2\.ply \(the same file\)"
    if probe == "out is the config":
        (box / "p.json").write_text("{}\n")
        return [a, b, "--config", box / "p.json", "--out", box / "p.json"], r"p\.json: --out is the input .*p\.json"
    if probe == "exports e57 is an input":
        e57 = _e57(box / "out" / "t.registered.e57", s / "scan3.ply")
        return [a, b, e57, "--out", box / "out" / "t.json", "--exports"], \
            rf"t\.registered\.e57: the --exports E57 \(named after --out\) is the input .*t\.registered\.e57; {NOT_AN_INPUT}"
    if probe == "e57 is out":
        return [a, b, "--out", box / "t.e57", "--e57", box / "t.e57"], r"t\.e57: --out and --e57 are the same file"
    if probe == "exports matrix is an input":  # a text scan named as scan1's matrix file would be
        np.savetxt(box / "out" / "t.scan1.cloudcompare.txt", read_points(s / "scan3.ply"), fmt="%.5f")
        return [a, b, box / "out" / "t.scan1.cloudcompare.txt", "--out", box / "out" / "t.json", "--exports"], \
            rf"t\.scan1\.cloudcompare\.txt: an --exports matrix file \(named after --out\) is the input .*; {NOT_AN_INPUT}"
    if probe == "exports matrix is out, through a link":
        (box / "out" / "t.scan2.pdal.txt").symlink_to("t.json")
        return [a, b, "--out", box / "out" / "t.json", "--exports"], \
            r"t\.scan2\.pdal\.txt: --out and an --exports matrix file \(named after --out\) are the same file"
    raise AssertionError(probe)


@pytest.mark.parametrize("probe", [
    "out is scan b", "merged is the reference", "e57 is the input e57", "out and merged one file",
    "out through a symbolic link to a scan", "out a hard link of a scan", "out is the config",
    "exports e57 is an input", "e57 is out", "exports matrix is an input", "exports matrix is out, through a link",
])
def test_an_output_that_is_an_input_or_another_output_is_refused_before_computing(sandbox, capsys, probe):
    args, pattern = _probe_args(sandbox, probe)
    before = fingerprint(sandbox)
    t0 = time.perf_counter()
    rc, err = cli(capsys, "register", *args)
    assert rc == 2, err
    one_line(err, "^treereg: error: .*" + pattern)
    assert time.perf_counter() - t0 < 10  # refused before the registration, not after it
    assert changed(before, fingerprint(sandbox)) == []


def test_simulate_never_writes_over_the_cloud_it_simulates_from(sandbox, capsys):
    before = fingerprint(sandbox)
    s = sandbox / "scans"
    rc, err = cli(capsys, "simulate", "--from-points", s / "scan1.ply", "--out", s)
    assert rc == 2
    one_line(err, rf"^treereg: error: .*scan1\.ply: the case's scan1\.ply is the input .*scan1\.ply; {NOT_AN_INPUT}: "
                  "choose another --out")
    assert changed(before, fingerprint(sandbox)) == []


# ---- item 8: an E57 under another format's name ---------------------------------------------------
def test_e57_with_another_extension_is_refused_up_front(sandbox, capsys):
    s = sandbox / "scans"
    before = fingerprint(sandbox)
    rc, err = cli(capsys, "register", s / "scan1.ply", s / "scan2.ply", "--out", sandbox / "out" / "t.json",
                  "--e57", sandbox / "out" / "x.ply")
    assert rc == 2
    one_line(err, r"^treereg: error: .*x\.ply: --e57 writes an E57 file; give it the extension \.e57, not '\.ply'$")
    assert changed(before, fingerprint(sandbox)) == []


# ---- item 2: export names derived from --out ------------------------------------------------------
def test_exports_e57_is_named_after_out_and_never_replaces_a_users_file(sandbox, capsys):
    s, out = sandbox / "scans", sandbox / "out"
    (out / "registered.e57").write_text("the user's own file\n")
    before = fingerprint(sandbox)
    for case, scan in (("a", "scan2.ply"), ("b", "scan3.ply")):  # two cases into one folder
        rc, err = cli(capsys, "register", s / "scan1.ply", s / scan, "--out", out / f"{case}.json", "--exports")
        assert rc == 0, err
    assert changed(before, fingerprint(sandbox), allowed=("out/a.", "out/b.")) == []  # registered.e57 as it was
    assert [r.name for r in read_e57(out / "a.registered.e57")] == ["scan1.ply", "scan2.ply"]
    assert [r.name for r in read_e57(out / "b.registered.e57")] == ["scan1.ply", "scan3.ply"]  # each case keeps its own


# ---- item 6: a file name that is not UTF-8 ----------------------------------------------------------
def test_a_scan_name_that_is_not_utf8_is_exported_without_a_traceback(sandbox):
    s = sandbox / "scans"
    odd = Path(os.fsdecode(bytes(s) + b"/sc\xffan2.ply"))
    os.rename(s / "scan2.ply", odd)
    before = fingerprint(sandbox)
    # A UTF-8 desktop locale: stdout is strict (the C locale would hide the problem).
    env = dict(_env(), PYTHONIOENCODING="utf-8:strict")
    p = subprocess.run([sys.executable, "-m", "treereg_cli", "register", str(s / "scan1.ply"), os.fsencode(odd),
                        "--out", str(sandbox / "out" / "t.json"), "--exports"],
                       cwd=REPO, env=env, capture_output=True, timeout=300)
    err = p.stderr.decode("utf-8", "replace")
    assert p.returncode == 0, err
    assert "Traceback" not in err
    # The name as shown (`text.shown`: the undecodable byte as \\udcff) everywhere: printed, the key of
    # transforms.json, the E57's scan name; the files named after it made safe.
    assert re.search(rb"^  sc\\udcffan2\.ply +verified$", p.stdout, re.M), p.stdout
    assert b"t.sc_udcffan2.cloudcompare.txt" in p.stdout
    assert "sc\\udcffan2.ply" in read_transforms(sandbox / "out" / "t.json").transforms
    assert (sandbox / "out" / "t.sc_udcffan2.pdal.txt").is_file()
    assert [r.name for r in read_e57(sandbox / "out" / "t.registered.e57")] == ["scan1.ply", "sc\\udcffan2.ply"]
    assert changed(before, fingerprint(sandbox), allowed=("out/",)) == []


# ---- item 1 in the app: an export never replaces a loaded scan --------------------------------------------
def test_view_refuses_an_out_folder_where_an_export_would_replace_a_scan(sandbox):
    s, out = sandbox / "scans", sandbox / "out"
    os.rename(s / "scan3.ply", out / "merged.ply")  # e.g. a merged cloud of an earlier run, opened as a scan
    before = fingerprint(sandbox)
    p = subprocess.run([sys.executable, "-m", "treereg_cli", "view", str(s / "scan1.ply"), str(out / "merged.ply"),
                        "--out", str(out), "--port", "0"], cwd=REPO, env=_env(), capture_output=True, text=True,
                       timeout=60)
    assert p.returncode == 2, p.stderr
    one_line(p.stderr, rf"^treereg: error: .*out/merged\.ply: the export merged\.ply is the input .*merged\.ply; "
                       rf"{NOT_AN_INPUT}: start treereg view with another --out folder$")
    assert changed(before, fingerprint(sandbox)) == []


def test_app_export_never_replaces_a_loaded_scan_and_still_downloads(sandbox):
    import viser

    from treereg_core.io.scans import read_scan
    from treereg_viewer.app import TreeregApp
    from treereg_viewer.controller import Controller

    s, out = sandbox / "scans", sandbox / "out"
    os.rename(s / "scan2.ply", out / "merged.ply")  # a loaded scan named as the app's merged cloud
    scans = [read_scan(s / "scan1.ply"), read_scan(out / "merged.ply")]
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = TreeregApp(server, Controller(scans), out_dir=out)
    sent: list[str] = []
    app.send_file = lambda client, name, data: sent.append(name)
    try:
        assert app.controller.wait_idle(240) and app.drawer.wait_idle(30)
        before = fingerprint(sandbox)
        app.files.download_cloud.value = True  # the click
        assert app.controller.wait_idle(60) and app.drawer.wait_idle(30)  # the message drawn, not only published
        assert sent == ["merged.ply"]  # the download, as asked
        assert changed(before, fingerprint(sandbox)) == []  # the scan kept, nothing half written beside it
        md = read(app.files.export_md.content)
        assert re.search(rf"Not written to .*out: .*merged\.ply: the export merged\.ply is the input .*merged\.ply; "
                         rf"{NOT_AN_INPUT}: start treereg view with another --out folder; the download has every file", md), md
        assert "Not written to" in read(app.stages.message_md.content)
    finally:
        app.close()
        server.stop()


def test_app_export_bundle_is_refused_over_an_input(tmp_path):
    from treereg_viewer.export import ExportBundle, input_clash, write_bundle

    loaded = tmp_path / "merged.ply"
    loaded.write_bytes(b"the user's scan\n")
    bundle = ExportBundle("fine", {}, {"transforms.json": b"{}\n", "merged.ply": b"the export\n"})
    why = input_clash(bundle, tmp_path, [loaded])
    assert why and "the export merged.ply is the input" in why and "another --out folder" in why
    with pytest.raises(OutputError, match=NOT_AN_INPUT):
        write_bundle(bundle, tmp_path, [loaded])
    assert loaded.read_bytes() == b"the user's scan\n" and not (tmp_path / "transforms.json").exists()


# ---- item 7: stale temporaries of ours are removed by the next write into their folder -----------------
def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_a_killed_write_leaves_a_temporary_the_next_write_removes(sandbox, capsys):
    out = sandbox / "out"
    # A real writer killed mid-write (SIGKILL: no handler runs), its temporary left behind.
    code = textwrap.dedent(f"""
        import time
        from treereg_core.io.atomic import write_atomic
        def slow(tmp):
            tmp.write_text("half")
            print("writing", flush=True)
            time.sleep(60)
        write_atomic({str(out / 't.json')!r}, slow)
    """)
    p = subprocess.Popen([sys.executable, "-c", code], cwd=REPO, env=_env(), stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "writing"
    p.send_signal(signal.SIGKILL)
    p.wait()
    p.stdout.close()
    left = [f for f in os.listdir(out) if f.endswith(".tmp")]
    assert len(left) == 1 and left[0].startswith(".t.json.treereg"), left
    old = time.time() - 2 * atomic.STALE_AFTER_S
    os.utime(out / left[0], (old, old))
    # What must stay: a live writer's temporary (ours), a fresh one, files not named as ours.
    alive = out / f".u.json.treereg{os.getpid()}.abcdefgh.tmp"
    fresh = out / f".v.json.treereg{_dead_pid()}.abcdefgh.tmp"
    users = [out / ".notes.tmp", out / ".w.json.abcdefgh.tmp", out / f".x.json.treereg{_dead_pid()}.tmp"]
    for f in (alive, fresh, *users):
        f.write_text("keep\n")
    for f in (alive, *users):
        os.utime(f, (old, old))
    before = fingerprint(sandbox)
    rc, err = cli(capsys, "params", "--out", out / "params.json")  # any write into that folder
    assert rc == 0, err
    assert changed(before, fingerprint(sandbox)) == ["out/" + left[0], "out/params.json"]
    assert not (out / left[0]).exists() and (out / "params.json").is_file()
