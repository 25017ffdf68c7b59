"""Hostile input, round 3 (issue 29), uploads to the app: bounded by what they unpack to, not only by
their bytes (a 190 kB LAZ held 20 M points and took the server from 208 MB to 1.48 GB); a name no
file can have (a NUL character) refused with a message and the button freed (was a server traceback
and the tab's *Add a scan file* disabled for good); the upload limits' flags checked.

The app is driven without a browser: `UploadReceiver.receive` sends what a browser sends.
"""

from __future__ import annotations

import gzip
import re

import numpy as np
import pytest
import viser
from viser import _messages as M

from hostile import cli, one_line
from treereg_core.demo import DEMO_DIR, demo_case
from treereg_core.io.e57 import write_e57
from treereg_core.io.scans import read_points, write_scan
from treereg_viewer.app import TreeregApp
from treereg_viewer.controller import Controller, parse_scan_upload

#: The most points an upload may hold in these tests (the demo's scans hold 25,123).
LIMIT = 1000


@pytest.fixture(scope="module")
def app():
    """The app on the demo, nothing run, uploads limited to `LIMIT` points; `app.parsed` lists the
    uploads the worker read (a refused one must never be)."""
    demo = demo_case()
    parsed: list[str] = []

    def parse(filename, path):
        parsed.append(filename)
        return parse_scan_upload(filename, path)

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    a = TreeregApp(server, Controller(list(demo.scans), truth=demo.truth, parse_upload=parse), autorun=False,
                   max_upload_points=LIMIT)
    a.parsed = parsed
    yield a
    a.close()
    server.stop()


def _message(app) -> str:
    assert app.controller.wait_idle(60), "the worker did not finish"
    return app.controller.snapshot.message


def _files(tmp_path, pts: np.ndarray) -> dict[str, bytes]:
    """The demo scan as each format whose size says little of its points."""
    write_scan(tmp_path / "s.laz", pts)
    write_scan(tmp_path / "s.las", pts)
    write_scan(tmp_path / "s.ply", pts)
    np.savez_compressed(tmp_path / "s.npz", points=pts)
    write_e57(tmp_path / "s.e57", [("s", pts, np.eye(4))])
    text = "\n".join(f"{x:.4f} {y:.4f} {z:.4f}" for x, y, z in pts).encode()
    return {"big.laz": (tmp_path / "s.laz").read_bytes(), "big.las": (tmp_path / "s.las").read_bytes(),
            "big.ply": (tmp_path / "s.ply").read_bytes(), "big.npz": (tmp_path / "s.npz").read_bytes(),
            "big.e57": (tmp_path / "s.e57").read_bytes(), "big.xyz.gz": gzip.compress(text)}


@pytest.mark.parametrize("name", ["big.laz", "big.las", "big.ply", "big.npz", "big.e57", "big.xyz.gz"])
def test_an_upload_announcing_more_points_than_the_limit_is_refused_before_it_is_read(app, tmp_path, name):
    data = _files(tmp_path, read_points(DEMO_DIR / "scan2.ply"))[name]
    scans = app.controller.snapshot.scans
    app.uploads.receive(app.scans.upload, name, data)
    holds = ("it holds more than 1,000 lines of points" if name.endswith(".gz")
             else "its header announces 25,123 points")
    assert re.fullmatch(rf"Upload rejected — {re.escape(name)}: {holds}, more than the 1,000 an uploaded scan may "
                        r"have here \(treereg view --max-upload-points\); nothing was added\.", _message(app)), _message(app)
    assert name not in app.parsed  # refused from its header: no point was read
    assert app.controller.snapshot.scans == scans and not any(app.uploads.tmp_root.rglob("*"))


def test_an_upload_within_the_point_limit_is_read(app, tmp_path):
    pts = read_points(DEMO_DIR / "scan2.ply")[:LIMIT]
    write_scan(tmp_path / "small.laz", pts)
    app.uploads.receive(app.scans.upload, "small.laz", (tmp_path / "small.laz").read_bytes())
    _message(app)
    assert "small.laz" in app.parsed and "max-upload-points" not in _message(app)
    assert not any(app.uploads.tmp_root.rglob("*"))
    if "small.laz" in app.controller.snapshot.scan_names:
        app.controller.remove_scan("small.laz")
        _message(app)


def test_an_upload_named_with_a_nul_is_refused_and_its_button_freed(app, monkeypatch):
    """Was: ValueError (embedded null byte) in viser's handler, no acknowledgement, so the tab's
    *Add a scan file* stayed disabled for good."""
    sent = []

    class Tab:
        class _websock_connection:
            queue_message = staticmethod(sent.append)

    monkeypatch.setattr(app.server, "get_clients", lambda: {7: Tab})
    scans = app.controller.snapshot.scans
    data = (DEMO_DIR / "scan2.ply").read_bytes()
    app.uploads.receive(app.scans.upload, "scan\x00.ply", data, client_id=7)
    assert re.fullmatch(r"Upload rejected — scan\x00\.ply: its name holds a NUL character, which no file name can "
                        r"hold; rename the file; nothing was added\.", _message(app)), _message(app)
    # The tab was told the transfer is over (all its bytes acknowledged): its button is enabled again.
    acks = [m for m in sent if isinstance(m, M.FileTransferPartAck)]
    assert acks and acks[-1].transferred_bytes == acks[-1].total_bytes == len(data)
    assert app.controller.snapshot.scans == scans and not any(app.uploads.tmp_root.rglob("*"))


@pytest.mark.parametrize("flag, value, pattern", [
    ("--max-upload-mb", "inf", r"--max-upload-mb: inf must be a positive, finite size in MB$"),  # was OverflowError
    ("--max-upload-mb", "nan", r"--max-upload-mb: nan must be a positive, finite size in MB$"),
    ("--max-upload-points", "0", r"--max-upload-points: 0 must be a positive number of points$"),
])
def test_an_upload_limit_that_is_no_limit_is_one_line_exit_2(capsys, flag, value, pattern):
    rc, err = cli(capsys, "view", "--port", "0", flag, value)
    assert rc == 2, err
    one_line(err, r"^treereg: error: " + pattern)
