"""Misleading words, round 3 (issue 29): each refusal says what is actually wrong. A CSV with decimal
commas was "millimetres", a FIFO "empty", a link to the reference registered onto itself, a float32
PLY in UTM coordinates refused for its "angular step". Each is one line, exit 2, nothing changed."""

from __future__ import annotations

import os

import numpy as np
import pytest

from hostile import changed, cli, fingerprint, one_line, sandbox  # noqa: F401  (sandbox: a fixture)
from treereg_core.io.scans import read_points, write_scan

UTM = [512_345.0, 5_123_456.0, 250.0]


def _decimal_commas(path, points, sep):
    rows = (sep.join(f"{v:.3f}".replace(".", ",") for v in p) for p in points)
    path.write_text("x;y;z\n" * (sep == ";") + "\n".join(rows) + "\n")


def _register(capsys, sandbox, scan, reference=None):
    s = sandbox / "scans"
    before = fingerprint(sandbox)
    rc, err = cli(capsys, "register", reference or s / "scan1.ply", scan, "--out", sandbox / "out" / "t.json")
    assert rc == 2
    assert changed(before, fingerprint(sandbox)) == []
    return err


@pytest.mark.parametrize("name, sep, pattern", [
    ("semicolons.csv", ";", r"semicolons\.csv: the numbers are written with decimal commas \('-?\d+,\d{3};-?\d+,\d{3};-?\d+,\d{3}'\), "
                            r"and treereg reads a decimal point: export the scan with '\.' as the decimal separator "
                            r"\(or replace each ',' by '\.' in the file\) and read it again$"),
    ("spaces.xyz", " ", r"spaces\.xyz: the numbers are written with decimal commas .* \(or replace each ',' by '\.' in the file\)"),
    ("commas.csv", ",", r"commas\.csv: the numbers are written with decimal commas .*export the scan with '\.' as the decimal "
                        r"separator \(commas separate its columns too, so no line can be read as x y z\) and read it again$"),
])
def test_decimal_commas_are_named_not_taken_for_another_unit(sandbox, capsys, name, sep, pattern):
    _decimal_commas(sandbox / name, read_points(sandbox / "scans" / "scan2.ply"), sep)
    err = _register(capsys, sandbox, sandbox / name)
    one_line(err, r"^treereg: error: .*" + pattern)
    assert "metres" not in err and "scale" not in err


def test_a_csv_with_decimal_points_and_integer_columns_is_still_read(tmp_path):
    """What the decimal-comma test must not catch: commas between numbers with decimal points, or
    between whole numbers (millimetres with colours)."""
    pts = read_points(write_scan(tmp_path / "s.ply", np.random.default_rng(0).uniform(-5, 5, (500, 3))))
    (tmp_path / "points.csv").write_text("\n".join(f"{x:.3f}, {y:.3f}, {z:.3f}" for x, y, z in pts) + "\n")
    assert read_points(tmp_path / "points.csv").shape == (500, 3)
    mm = np.round(pts * 1000).astype(int)
    (tmp_path / "mm.csv").write_text("\n".join(f"{x},{y},{z},255,{k % 256},0" for k, (x, y, z) in enumerate(mm)) + "\n")
    with pytest.raises(Exception, match="looks like millimetres"):  # truly millimetres: that is what it says
        read_points(tmp_path / "mm.csv")


def test_a_fifo_is_not_a_regular_file_not_empty(sandbox, capsys):
    os.mkfifo(sandbox / "pipe.ply")
    err = _register(capsys, sandbox, sandbox / "pipe.ply")
    one_line(err, r"^treereg: error: .*pipe\.ply: is not a regular file \(a FIFO, device or socket\), so not a scan file; "
                  r"give the scan file itself$")
    assert "empty" not in err


def test_a_link_to_the_reference_is_the_same_scan_given_twice(sandbox, capsys):
    s = sandbox / "scans"
    (s / "copy_of_ref.ply").symlink_to(s / "scan1.ply")
    err = _register(capsys, sandbox, s / "copy_of_ref.ply")
    one_line(err, r"^treereg: error: .*scans/copy_of_ref\.ply: given twice \(also as .*scans/scan1\.ply: the same file\); "
                  r"give each scan once$")
    os.link(s / "scan1.ply", s / "hard.ply")  # a hard link is the same file too
    one_line(_register(capsys, sandbox, s / "hard.ply"), r"hard\.ply: given twice \(also as .*scan1\.ply: the same file\)")


def test_float32_coordinates_far_from_the_origin_say_they_lost_their_precision(sandbox, capsys):
    pts = read_points(sandbox / "scans" / "scan2.ply")
    write_scan(sandbox / "utm32.ply", pts + UTM, dtype="float32")
    err = _register(capsys, sandbox, sandbox / "utm32.ply")
    one_line(err, r"^treereg: error: .*utm32\.ply: the coordinates are single precision \(float32\) and lie some "
                  r"5,12\d,\d{3} m from the origin, where float32 holds a coordinate only to 0\.5 m: they lost their "
                  r"precision when the file was written\. Export the scan as float64 \(double\), or shifted near the "
                  r"origin \(e\.g\. minus the scanner's position\) as float32, and read it again$")
    assert "angular step" not in err
    # given the scanner's position (what the georeferenced message asks for), still the precision is named
    s = sandbox / "scans"
    rc, err = cli(capsys, "register", s / "scan1.ply", sandbox / "utm32.ply", "--scanner-position", "0", "0", "0",
                  "--scanner-position", *map(str, UTM), "--out", sandbox / "out" / "t.json")
    assert rc == 2
    one_line(err, r"utm32\.ply: the coordinates are single precision \(float32\)")
    # float32 near the origin (~1 um at 10 m) is read as it always was
    write_scan(sandbox / "near32.ply", pts, dtype="float32")
    assert read_points(sandbox / "near32.ply").shape == pts.shape
