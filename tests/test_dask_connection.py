"""`batch --dask` at something that is not a Dask scheduler (issue 29): an HTTP port that waits for a
request hung forever; a server answering at once ("HTTP/1.1 400 ...", read as an 8-byte length: 3 EiB)
died allocating it inside distributed's handshake. Each is one line, exit 2, within the connect timeout."""

from __future__ import annotations

import re
import shutil
import socket
import threading
import time

import pytest

from treereg_cli.main import main
from treereg_core.batch import runner
from treereg_core.demo import DEMO_DIR

pytest.importorskip("distributed")


def _serve(answer):
    """A TCP server on 127.0.0.1 (port 0) that hands each connection to `answer`; its address."""
    server = socket.create_server(("127.0.0.1", 0))

    def loop():
        while True:
            try:
                conn, _ = server.accept()
            except OSError:
                return
            threading.Thread(target=answer, args=(conn,), daemon=True).start()

    threading.Thread(target=loop, daemon=True).start()
    return server, f"tcp://127.0.0.1:{server.getsockname()[1]}"


def _http_waiting(conn):  # an HTTP server: nothing until a request ends with an empty line
    with conn:
        data = b""
        while b"\r\n\r\n" not in data and (chunk := conn.recv(4096)):
            data += chunk
        conn.sendall(b"HTTP/1.1 400 Bad Request\r\n\r\n")


def _http_eager(conn):  # answers anything at once
    with conn:
        conn.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n")
        time.sleep(5)


def _hangs_up(conn):
    conn.close()


@pytest.fixture()
def campaign(tmp_path):
    for k in (1, 2):
        (tmp_path / "trees" / "tree1").mkdir(parents=True, exist_ok=True)
        shutil.copy(DEMO_DIR / f"scan{k}.ply", tmp_path / "trees" / "tree1" / f"scan{k}.ply")
    return tmp_path


@pytest.mark.parametrize("answer, pattern", [
    (_http_waiting, r"nothing answered as a Dask scheduler within 1 s \(another service's port, e\.g\. the dashboard's "
                    r"or an HTTP server\?\); give the scheduler's own address, which it prints when it starts"),
    (_http_eager, r"the peer answered, but not in Dask's protocol \(another service's port\?\)"),
    (_hangs_up, r"the peer closed the connection without answering as a Dask scheduler"),
], ids=["http waiting", "http answering at once", "hangs up"])
def test_a_peer_that_is_no_scheduler_is_one_line_within_the_timeout(campaign, capsys, monkeypatch, answer, pattern):
    monkeypatch.setattr(runner, "DASK_CONNECT_TIMEOUT", "1s")
    server, address = _serve(answer)
    result = {}

    def run():  # in a thread: without the bound this hangs, and the test must fail, not hang
        result["rc"] = main(["batch", str(campaign / "trees"), "--out", str(campaign / "out"), "--dask", address])

    start = time.monotonic()
    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(timeout=8)
    server.close()
    assert not t.is_alive(), "still connecting after 8 s"
    assert time.monotonic() - start < 5
    assert result["rc"] == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and not re.search(r"\.py:\d+", err), err
    lines = err.strip().splitlines()  # batch first says what it will run, then the one error line
    assert re.search(rf"^treereg: error: --dask {address}: {pattern}", lines[-1]) and len(lines) == 2, lines
    assert not (campaign / "out" / "tree1").exists()


def test_a_real_scheduler_passes_the_probe():
    from distributed import LocalCluster

    with LocalCluster(n_workers=0, processes=False, protocol="tcp://", host="127.0.0.1", dashboard_address=None) as c:
        host, port = c.scheduler_address.removeprefix("tcp://").rsplit(":", 1)
        runner._probe_scheduler(c.scheduler_address, (host, int(port)), 5.0)  # raises if refused
