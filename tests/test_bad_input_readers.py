"""Hostile input, round 2 (issue 17), the readers: every reader checks what its header promises,
poses in file headers are refused when read if they are not rigid, raw library errors become
sentences, and what a file holds is diagnosed as what it is (no-data rows, stray rows, a header's
column names, a wrong-type PLY, kilometres) before any unit is guessed.

Each probe crafts the file in the sandbox, runs `treereg register <demo scan> <bad file>` and asserts
the one line a user sees (or, where a few rows are dropped, the one warning line and the run going
on), the exit code, and that nothing of the user's changed.
"""

from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np
import pytest

from hostile import changed, cli, fingerprint, one_line, sandbox  # noqa: F401  (sandbox: a fixture)
from treereg_core.io.ptx import write_ptx
from treereg_core.io.scans import read_points, write_scan


def _demo(box: Path) -> np.ndarray:
    return read_points(box / "scans" / "scan2.ply")


def _register(capsys, box: Path, bad: Path, *extra: str) -> tuple[int, str]:
    """`treereg register scan1.ply BAD`, with a check that nothing outside the output folder changed."""
    before = fingerprint(box)
    rc, err = cli(capsys, "register", box / "scans" / "scan1.ply", bad, *extra, "--out", box / "out" / "t.json")
    assert changed(before, fingerprint(box), ("out",)) == []
    return rc, err


def _refused(capsys, box: Path, bad: Path, pattern: str, *extra: str) -> None:
    rc, err = _register(capsys, box, bad, *extra)
    assert rc == 2, err
    one_line(err, r"^treereg: error: .*" + pattern)


def _warned_once(err: str, pattern: str) -> None:
    """One treereg warning line matching `pattern`, no other warning, no traceback, no module path."""
    warnings = [ln for ln in err.replace("\r", "\n").splitlines() if "warning" in ln.lower()]
    assert len(warnings) == 1 and re.fullmatch(r"treereg: warning: .*" + pattern, warnings[0]), warnings
    assert "Traceback" not in err and not re.search(r"\.py:\d+", err), err


def _ascii_ply(path: Path, pts: np.ndarray, count: int | None = None, kind: str = "float") -> Path:
    head = (f"ply\nformat ascii 1.0\nelement vertex {len(pts) if count is None else count}\n"
            f"property {kind} x\nproperty {kind} y\nproperty {kind} z\nend_header\n")
    with open(path, "w") as fh:
        fh.write(head)
        np.savetxt(fh, pts, fmt="%.5f" if kind == "float" else "%d")
    return path


# ---- every reader checks what its header promises ------------------------------------------------------
@pytest.mark.parametrize("case, pattern", [
    ("cut", r"cut\.ply: the PLY file is truncated: its header announces 25123 points, the file holds 1\d{4}$"),
    ("high", r"high\.ply: the PLY file is truncated: its header announces 25623 points, the file holds 25123$"),
    ("low", r"low\.ply: the PLY file holds more than its header announces: its header announces 12561 points, "
            r"the file holds 25123"),
])
def test_an_ascii_ply_that_disagrees_with_its_header_is_named_not_read_in_part(sandbox, capsys, case, pattern):
    pts = _demo(sandbox)
    bad = sandbox / f"{case}.ply"
    if case == "cut":  # cut mid-file, mid-line: was read and verified on 43% of its points
        whole = _ascii_ply(sandbox / "whole.ply", pts).read_bytes()
        (sandbox / "whole.ply").unlink()
        bad.write_bytes(whole[: int(len(whole) * 0.45)])
    else:
        _ascii_ply(bad, pts, count=len(pts) + 500 if case == "high" else len(pts) // 2)
    _refused(capsys, sandbox, bad, pattern)


@pytest.mark.parametrize("case, pattern", [
    ("cut", r"cut\.las: the LAS file is truncated: its header announces 25123 points, the file holds 12555$"),
    ("high", r"high\.las: the LAS file is truncated: its header announces 26123 points, the file holds 25123$"),
    ("low", r"low\.las: the LAS file holds more than its header announces: its header announces 12561 points, "
            r"the file holds 25123"),
])
def test_a_las_file_that_disagrees_with_its_header_is_named(sandbox, capsys, case, pattern):
    pts = _demo(sandbox)
    good = write_scan(sandbox / "good.las", pts).read_bytes()
    (sandbox / "good.las").unlink()
    bad = sandbox / f"{case}.las"
    if case == "cut":  # was "buffer size must be a multiple of element size"
        bad.write_bytes(good[: len(good) // 2 + 3])
    else:  # the LAS 1.2 point count (header offset 107), too high or too low: was read without a word
        raw = bytearray(good)
        struct.pack_into("<I", raw, 107, len(pts) + 1000 if case == "high" else len(pts) // 2)
        bad.write_bytes(bytes(raw))
    _refused(capsys, sandbox, bad, pattern)


def test_an_npz_with_several_arrays_is_refused_naming_them(sandbox, capsys):
    pts = _demo(sandbox)
    bad = sandbox / "two.npz"
    np.savez(bad, pts, pts[::-1])  # was: the first one taken without a word
    _refused(capsys, sandbox, bad, r"two\.npz: the \.npz archive holds 2 arrays \(arr_0, arr_1\) and none is named "
                                   r"'points': save the scan's N x 3 array alone, or under the name 'points'$")


# ---- a pose in a file header that is not rigid is refused when the file is read -------------------------
def _ptx(path: Path, pts: np.ndarray, pose: np.ndarray, rows: int = 100) -> Path:
    cols = len(pts) // rows
    return write_ptx(path, [(pts[: rows * cols].reshape(rows, cols, 3), pose, rows, cols)])


@pytest.mark.parametrize("case, pattern", [
    ("scaled", r"scaled\.ptx: lines 3-10: the pose in the scan's header is not rigid: its rotation part scales or "
               r"shears the scan \(\|R\^T R - I\| = 1\.2\); export the scan with a rigid pose"),
    ("sheared", r"sheared\.ptx: lines 3-10: the pose in the scan's header is not rigid: its rotation part scales or "
                r"shears the scan \(\|R\^T R - I\| = 0\.3\)"),
    ("mirrored", r"mirrored\.ptx: lines 3-10: the pose in the scan's header is a mirror \(determinant -1\), not a rotation"),
    ("nan", r"nan\.ptx: lines 3-10: the pose in the scan's header holds NaN or infinite numbers$"),
])
def test_a_ptx_header_pose_that_is_not_rigid_is_refused_when_read(sandbox, capsys, case, pattern):
    pose = np.eye(4)
    pose[:3, 3] = (1.0, 2.0, 0.0)
    if case == "scaled":
        pose[:3, :3] *= 1.5
    elif case == "sheared":
        pose[0, 1] = 0.3
    elif case == "mirrored":
        pose[2, 2] = -1.0
    else:
        pose[0, 3] = np.nan
    bad = _ptx(sandbox / f"{case}.ptx", _demo(sandbox), pose)
    # Refused at once (was: after the whole run, named transforms['...'], or read as if rigid).
    _refused(capsys, sandbox, bad, pattern)


def test_an_e57_pose_with_a_quaternion_that_scales_is_refused_when_read(sandbox, capsys):
    import pye57

    pts = _demo(sandbox)
    bad = sandbox / "scaled.e57"
    e57 = pye57.E57(str(bad), mode="w")
    e57.write_scan_raw({"cartesianX": pts[:, 0], "cartesianY": pts[:, 1], "cartesianZ": pts[:, 2]}, name="station",
                       rotation=np.array([2.0, 0.0, 0.0, 0.0]), translation=np.array([1.0, 2.0, 0.0]))
    e57.close()
    _refused(capsys, sandbox, bad, r"scaled\.e57: scan 1 \(station\): the pose in the scan's header is not rigid: its "
                                   r"rotation quaternion has length 2, not 1 \(a scale\)")


# ---- raw library errors become what a user can act on ------------------------------------------------------
def test_a_ply_without_end_header_is_named(sandbox, capsys):
    bad = sandbox / "noend.ply"  # was: "not a readable PLY file (IndexError: list index out of range)"
    bad.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                    b"property float z\n1 2 3\n4 5 6\n7 8 9\n")
    _refused(capsys, sandbox, bad, r"noend\.ply: the PLY header has no end_header line: the file is cut inside its "
                                   r"header, or not a PLY file$")


def test_a_ptx_row_count_too_low_is_named(sandbox, capsys):
    bad = _ptx(sandbox / "rows.ptx", _demo(sandbox), np.eye(4))
    lines = bad.read_text().splitlines(True)
    lines[1] = "50\n"  # half the rows: was "the grid size must be two positive integers, got 0 x 0" (or -10.9 x ...)
    bad.write_text("".join(lines))
    _refused(capsys, sandbox, bad, r"rows\.ptx: line 12561: a point line where the next scan's header should start: "
                                   r"scan 1 holds more points than its header's 251 x 50 grid; check the column and "
                                   r"row counts in its header$")


def test_identical_points_are_named_as_such(sandbox, capsys):
    bad = sandbox / "same.xyz"  # was: an angular-step message
    np.savetxt(bad, np.tile([[1.5, 2.0, 3.0]], (500, 1)))
    _refused(capsys, sandbox, bad, r"same\.xyz: all 500 points are the same point \(1\.5, 2, 3\), so the file holds no scan$")


@pytest.mark.parametrize("content", [bytes(range(256)) * 40, np.random.default_rng(1).bytes(5000)],
                         ids=["every_byte", "random_bytes"])
def test_a_binary_file_named_xyz_is_not_a_text_file_and_its_bytes_are_not_echoed(sandbox, capsys, content):
    bad = sandbox / "junk.xyz"
    bad.write_bytes(content)
    rc, err = _register(capsys, sandbox, bad)
    assert rc == 2
    one_line(err, r"^treereg: error: .*junk\.xyz: not a text file \(it holds binary data\): a \.xyz scan is text, "
                  r"x y z on each line")
    assert not re.search(r"[\x00-\x08\x0e-\x1f\ufffd]|\\x", err), err


# ---- diagnoses that fit --------------------------------------------------------------------------------------
@pytest.mark.parametrize("case, pattern", [
    # 3% of rows -9999: was "looks like centimetres ... scale the coordinates by 0.01"
    ("sentinel", r"sentinel\.xyz: dropped 838 of 25123 points at \(-9999, -9999, -9999\) \(a no-data value, not a measurement\)"),
    # one 1e30 row: was "use more image pairs" and a RuntimeWarning from ground.py
    ("outlier", r"outlier\.xyz: dropped 1 of 25123 points lying far outside the scan \(up to 1e\+30 units from its "
                r"median point, while half the points lie within [\d.]+ units of it\): corrupt or stray rows"),
])
def test_no_data_and_absurd_rows_are_dropped_with_one_warning_before_any_unit_guess(sandbox, capsys, case, pattern):
    pts = _demo(sandbox)
    if case == "sentinel":
        pts[::30] = -9999.0
    else:
        pts[123] = 1e30
    bad = sandbox / f"{case}.xyz"
    np.savetxt(bad, pts, fmt="%.6g")
    rc, err = _register(capsys, sandbox, bad, "--until", "coarse")
    assert rc == 1, err  # written; unverified (stopped before verification)
    _warned_once(err, pattern)
    assert "centimetres" not in err and "image pairs" not in err


@pytest.mark.parametrize("name, sep", [("ids.csv", ","), ("ids.xyz", " ")])
def test_a_header_naming_its_columns_says_where_x_y_z_are(sandbox, capsys, name, sep):
    pts = _demo(sandbox)
    bad = sandbox / name
    with open(bad, "w") as fh:  # was read as id, x, y and called millimetres, "scale by 0.001"
        fh.write(sep.join(("id", "x", "y", "z")) + "\n")
        np.savetxt(fh, np.column_stack([np.arange(len(pts)), pts]), fmt="%.5f", delimiter=sep)
    np.testing.assert_allclose(read_points(bad), pts, atol=1e-5)
    rc, err = _register(capsys, sandbox, bad, "--until", "coarse")
    assert rc == 1, err  # read and registered (unverified: stopped before verification)
    assert "error" not in err and "metres" not in err and "Traceback" not in err, err


@pytest.mark.parametrize("case, pattern", [
    ("uchar_ascii", r"uchar_ascii\.ply: the PLY file declares x as uchar \(whole numbers 0 to 255\), which cannot hold a "
                    r"scan's coordinates: export the scan with float or double x, y, z$"),
    ("int8_binary", r"int8_binary\.ply: the PLY file declares x as int8 \(whole numbers -128 to 127\), which cannot "
                    r"hold a scan's coordinates"),
    ("list", r"list\.ply: the PLY file declares x as a list property, not one number per point: export the scan with "
             r"float or double x, y, z$"),
])
def test_a_wrong_type_ply_is_named_as_such_not_as_a_unit(sandbox, capsys, case, pattern):
    pts = _demo(sandbox)
    bad = sandbox / f"{case}.ply"
    if case == "uchar_ascii":
        _ascii_ply(bad, np.clip(np.round(pts * 10) + 128, 0, 255), kind="uchar")
    elif case == "int8_binary":
        with open(bad, "wb") as fh:
            fh.write(f"ply\nformat binary_little_endian 1.0\nelement vertex {len(pts)}\nproperty int8 x\n"
                     "property int8 y\nproperty int8 z\nend_header\n".encode())
            fh.write(np.clip(np.round(pts * 10), -128, 127).astype("i1").tobytes())
    else:
        with open(bad, "w") as fh:
            fh.write(f"ply\nformat ascii 1.0\nelement vertex {len(pts)}\nproperty list uchar float x\n"
                     "property float y\nproperty float z\nend_header\n")
            np.savetxt(fh, np.column_stack([np.ones(len(pts)), pts]), fmt="%.5f")
    _refused(capsys, sandbox, bad, pattern)


def test_a_scan_in_kilometres_is_named_kilometres(sandbox, capsys):
    bad = write_scan(sandbox / "km.ply", _demo(sandbox) / 1000.0)  # was "angular steps 47.6 x 47.6 deg ..."
    _refused(capsys, sandbox, bad, r"km\.ply: coordinates span 0\.00\d+ units \(median distance from the scanner "
                                   r"0\.0\d+\); treereg expects metres and this looks like kilometres: convert the file to "
                                   r"metres \(scale the coordinates by 1000, which makes the scan span [\d.]+ m")


def test_a_nan_scanner_position_is_one_line_without_a_python_warning(sandbox, capsys):
    s = sandbox / "scans"  # was: two RuntimeWarnings with numpy's source paths, then an angular-step message
    _refused(capsys, sandbox, s / "scan2.ply",
             r"scan1\.ply: the scanner position given for it, \(nan, 0, 0\), is not a point: give --scanner-position "
             r"X Y Z as three finite numbers$",
             "--scanner-position", "nan", "0", "0", "--scanner-position", "0", "0", "0")


# ---- a binary PLY cut short, before or while it is read (issue 29) ---------------------------------------
def _binary_ply(path: Path, pts: np.ndarray, extra: bool) -> Path:
    """A binary PLY of x, y, z as float32, with an intensity after them when `extra` (another read path)."""
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")] + ([("intensity", "<u2")] if extra else [])
    rec = np.zeros(len(pts), dtype=fields)
    rec["x"], rec["y"], rec["z"] = pts.T
    props = "".join(f"property {'ushort' if t == '<u2' else 'float'} {n}\n" for n, t in fields)
    path.write_bytes(f"ply\nformat binary_little_endian 1.0\nelement vertex {len(pts)}\n{props}end_header\n".encode()
                     + rec.tobytes())
    return path


@pytest.mark.parametrize("extra", [False, True], ids=["xyz", "extra_property"])
def test_a_binary_ply_cut_short_is_named_truncated(sandbox, capsys, extra):
    pts = _demo(sandbox)
    bad = _binary_ply(sandbox / "cut.ply", pts, extra)
    bad.write_bytes(bad.read_bytes()[:-(len(pts) // 2) * (14 if extra else 12)])
    _refused(capsys, sandbox, bad, rf"cut\.ply: the PLY file is truncated: its header announces {len(pts)} points, "
                                   rf"the file holds {len(pts) - len(pts) // 2}$")


@pytest.mark.parametrize("extra", [False, True], ids=["xyz", "extra_property"])
def test_a_binary_ply_that_shrinks_while_read_is_named_truncated(tmp_path, sandbox, capsys, monkeypatch, extra):
    """The file is whole when its header is read and its size asked, then cut to a third (a copy being
    overwritten, a shared drive): was `ValueError: cannot reshape` (x y z) or a bus error (memory-mapped)."""
    import os
    import pathlib

    from treereg_core.io import scans

    pts = _demo(sandbox)
    bad = _binary_ply(tmp_path / "shrinks.ply", pts, extra)
    size = bad.stat().st_size
    armed = []
    real_header, real_fstat, real_stat = scans._ply_header, os.fstat, pathlib.Path.stat

    def header(path):
        h = real_header(path)
        if path == bad:  # the other scan is read alongside
            armed.append(h.offset)
        return h

    def cut_after(st):
        """The size a reader asked for, then the file cut under it (once, after the header was read)."""
        if armed and st.st_size == size:
            os.truncate(bad, armed.pop() + (len(pts) // 3) * (14 if extra else 12))
        return st

    monkeypatch.setattr(scans, "_ply_header", header)
    monkeypatch.setattr(os, "fstat", lambda fd: cut_after(real_fstat(fd)))
    monkeypatch.setattr(pathlib.Path, "stat", lambda self, **kw: cut_after(real_stat(self, **kw)))
    rc, err = cli(capsys, "register", sandbox / "scans" / "scan1.ply", bad, "--out", tmp_path / "t.json")
    assert rc == 2, err
    one_line(err, rf"^treereg: error: .*shrinks\.ply: the PLY file is truncated: its header announces {len(pts)} "
                  rf"points, the file holds {len(pts) // 3} \(it shrank while being read: read it again once it is complete\)$")


def test_a_scan_read_from_npy_does_not_change_or_crash_when_its_file_is_cut_afterwards(tmp_path):
    """A float64 .npy was memory-mapped and the map became the scan's points: the file cut (or
    overwritten) during a run changed them, or ended the process with a bus error. Run apart: a bus
    error would take pytest down."""
    import subprocess
    import sys

    from hostile import REPO, _env

    script = (
        "import os, sys, numpy as np\n"
        "from treereg_core.io.scans import read_points, read_scan\n"
        "pts = read_points(sys.argv[1])\n"
        "np.save(sys.argv[2], pts)\n"
        "scan = read_scan(sys.argv[2])\n"
        "os.truncate(sys.argv[2], 200)\n"
        "print(bool(np.array_equal(scan.points, pts)))\n"
    )
    proc = subprocess.run([sys.executable, "-c", script, str(REPO / "treereg_core" / "demo" / "scan2.ply"),
                           str(tmp_path / "scan.npy")], cwd=REPO, env=_env(), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and proc.stdout.strip() == "True", (proc.returncode, proc.stdout, proc.stderr[-2000:])


def test_a_truncated_npy_is_one_line(sandbox, capsys):
    bad = sandbox / "cut.npy"
    np.save(bad, _demo(sandbox))
    bad.write_bytes(bad.read_bytes()[:-1000])
    _refused(capsys, sandbox, bad, r"cut\.npy: the \.npy file is truncated: its header announces 25123 points, the file "
                                   r"holds 25081$")  # was "not a readable .npy array (mmap length is greater than file size)"
