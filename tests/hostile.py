"""What every hostile-input probe shares (tests/test_bad_input*.py): a sandbox of the demo scans and
awkward destinations, its fingerprint before and after, the command line run in this process, and the
one-line-message check."""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import stat
from pathlib import Path

import numpy as np
import pytest

from treereg_cli.main import main
from treereg_core.demo import DEMO_DIR
from treereg_core.io.scans import read_points, write_scan

REPO = Path(__file__).resolve().parent.parent


# ---- the sandbox and its fingerprint ----------------------------------------------------------------
def fingerprint(root: Path) -> dict[str, tuple]:
    """Every entry under `root` (links and FIFOs as themselves, never opened), with what identifies its content."""
    out: dict[str, tuple] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            st = os.lstat(p)
            if stat.S_ISLNK(st.st_mode):
                out[str(p.relative_to(root))] = ("link", os.readlink(p))
            elif stat.S_ISREG(st.st_mode):
                out[str(p.relative_to(root))] = ("file", stat.S_IMODE(st.st_mode), hashlib.sha1(p.read_bytes()).hexdigest())
            else:
                out[str(p.relative_to(root))] = ("dir" if stat.S_ISDIR(st.st_mode) else "special", stat.S_IFMT(st.st_mode))
    return out


def changed(before: dict, after: dict, allowed: tuple[str, ...] = ()) -> list[str]:
    """Entries added, removed or modified, outside the `allowed` prefixes (the output folder)."""
    keys = set(before) | set(after)
    return sorted(k for k in keys if before.get(k) != after.get(k) and not k.startswith(allowed))


@pytest.fixture()
def sandbox(tmp_path):
    """The demo scans, a few configs, and the awkward destinations a user might give."""
    box = tmp_path / "box"
    (box / "scans").mkdir(parents=True)
    for name in ("scan1.ply", "scan2.ply", "scan3.ply", "truth.json"):
        shutil.copy(DEMO_DIR / name, box / "scans" / name)
    pts = read_points(DEMO_DIR / "scan2.ply")
    write_scan(box / "scans" / "cm.ply", pts * 100.0)
    write_scan(box / "scans" / "mm.ply", pts * 1000.0)
    write_scan(box / "scans" / "utm.ply", pts + [512_345.0, 5_123_456.0, 250.0])
    holes = pts.copy()
    holes[::40] = np.nan
    np.savetxt(box / "scans" / "holes.xyz", holes, fmt="%.5f")
    (box / "target.json").write_text("the link's target\n")
    (box / "link.json").symlink_to(box / "target.json")
    os.mkfifo(box / "fifo.json")
    (box / "afile").write_text("a file, not a folder\n")
    (box / "folder").mkdir()
    (box / "readonly.json").write_text("keep me\n")
    os.chmod(box / "readonly.json", 0o444)
    (box / "loop1").symlink_to(box / "loop2")
    (box / "loop2").symlink_to(box / "loop1")
    (box / "deep.json").write_text("[" * 100_000 + "]" * 100_000)
    (box / "deep_obj.json").write_text('{"a":' * 100_000 + "1" + "}" * 100_000)
    (box / "tiny_step.json").write_text(json.dumps({"prepare": {"angular_step_deg": [1e-9, 1e-9]}}))
    (box / "huge_images.json").write_text(json.dumps({"prepare": {"angular_step_deg": [0.001, 0.001]},
                                                     "resolution": {"spacing_m": None},  # every point kept
                                                     "projection": {"max_image_px": None, "pixel_factor": 1}}))
    (box / "prev").mkdir()
    (box / "prev" / "transforms.json").write_text("a previous result\n")
    (box / "out").mkdir()
    return box


def cli(capsys, *args: str) -> tuple[int, str]:
    """`treereg ARGS` in this process: exit code and stderr (an exception escaping main fails the test)."""
    capsys.readouterr()
    rc = main([str(a) for a in args])
    return rc, capsys.readouterr().err


def one_line(err: str, pattern: str) -> None:
    """stderr's last line is treereg's message matching `pattern`; no traceback, no module path."""
    lines = [ln for ln in err.replace("\r", "\n").splitlines() if ln.strip() and not re.match(r"^\w+ \[[#-]+\]", ln)]
    assert lines, "nothing printed"
    assert "Traceback" not in err and not re.search(r"\.py:\d+", err), err
    assert re.search(pattern, lines[-1]), lines[-1]
    assert len(lines) == 1, lines



def ctrl_c_default() -> None:
    """`preexec_fn` of a process a test sends Ctrl-C: SIGINT at its default, as a terminal's foreground
    job has it. A test runner started in the background (`cmd &` from a script) has SIGINT ignored,
    its children inherit that, and Python then never raises KeyboardInterrupt."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _env() -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""), PYTHONUNBUFFERED="1")


def stop_register_midway(sandbox: Path, sig: int) -> tuple[int, str]:
    """`treereg register` of the demo scans over `prev/transforms.json` in a real process, sent `sig`
    once the registration has started: its exit code and stderr."""
    s = sandbox / "scans"
    proc = subprocess.Popen(
        [sys.executable, "-m", "treereg_cli", "register", s / "scan1.ply", s / "scan2.ply", s / "scan3.ply",
         "--exports", "--out", sandbox / "prev" / "transforms.json"],
        cwd=REPO, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, preexec_fn=ctrl_c_default)
    seen = b""
    while b"register [" not in seen:  # the registration has started: stop it mid-way
        chunk = proc.stderr.read1(256)
        assert chunk, f"ended before registering: {seen!r}"
        seen += chunk
    proc.send_signal(sig)
    _, rest = proc.communicate(timeout=60)
    return proc.returncode, (seen + rest).decode()


def view_started(proc: subprocess.Popen, timeout_s: float = 90.0) -> list[str]:
    """The lines `treereg view` (text stdout) printed up to and including its "treereg view: http://"
    line, or all it printed before it ended or `timeout_s` passed."""
    lines: list[str] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not any("treereg view: http://" in ln for ln in lines):
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line)
    return lines
