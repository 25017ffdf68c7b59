"""Reading and writing scan files: every format round-trips, every bad input names file and problem."""

from __future__ import annotations

import gzip
import warnings
from pathlib import Path

import laspy
from conftest import REAL_TREES, needs
import numpy as np
import pytest

from treereg_core.io import scans as tio
from treereg_core.errors import OutputError, ScanError
from treereg_core.io.scans import ScanWarning, read_points, read_scan, write_scan
from treereg_core.simulate.cases import simulate_case

REAL_SCAN = REAL_TREES / "rtls_single_scan_scanner_at_origin.xyz.gz"


@pytest.fixture(scope="module")
def sim_scan():
    """A small simulated scan with known steps (0.25 x 0.2 deg)."""
    return simulate_case(seed=7, n_stations=1, angular_step_deg=(0.25, 0.2), height_m=6.0).scans[0]


@pytest.fixture()
def pts():
    rng = np.random.default_rng(0)
    return rng.uniform([-3, 5, -1.5], [3, 9, 10], size=(500, 3))


def _write_text(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _xyz_lines(p: np.ndarray, sep: str = " ") -> str:
    return "".join(sep.join(repr(float(v)) for v in row) + "\n" for row in p)


# ---- round trips -------------------------------------------------------------------------------
def test_ply_binary_float64_round_trip_is_exact(tmp_path, pts):
    out = write_scan(tmp_path / "a.ply", pts)
    assert out == tmp_path / "a.ply"
    assert out.read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\n")
    np.testing.assert_array_equal(read_points(out), pts)


def test_ply_float32_halves_the_size_and_keeps_micrometres(tmp_path, pts):
    a = write_scan(tmp_path / "a.ply", pts)
    b = write_scan(tmp_path / "b.ply", pts, dtype="float32")
    assert b.stat().st_size < 0.6 * a.stat().st_size
    np.testing.assert_allclose(read_points(b), pts, atol=2e-6)


def test_ascii_ply_is_read(tmp_path, pts):
    header = f"ply\nformat ascii 1.0\nelement vertex {len(pts)}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    p = _write_text(tmp_path / "ascii.ply", header + _xyz_lines(pts))
    np.testing.assert_allclose(read_points(p), pts, atol=1e-5)


@pytest.mark.parametrize("ext", [".las", ".laz"])
def test_las_laz_round_trip_to_a_tenth_of_a_millimetre(tmp_path, pts, ext):
    far = pts + [512_345.0, 5_123_456.0, 250.0]  # georeferenced: offsets must be applied
    p = write_scan(tmp_path / f"a{ext}", far)
    back = read_points(p)
    np.testing.assert_allclose(back, far, atol=0.6 * tio.LAS_SCALE_M, rtol=0)
    las = laspy.read(p)
    np.testing.assert_allclose(las.header.scales, tio.LAS_SCALE_M)
    with laspy.open(p) as reader:
        assert reader.header.are_points_compressed == (ext == ".laz")


def test_scan_object_is_written_and_read_back_with_name_and_steps(tmp_path, sim_scan):
    p = write_scan(tmp_path / "scan2.ply", sim_scan)
    scan = read_scan(p)
    assert scan.name == "scan2.ply" and scan.source == p
    np.testing.assert_array_equal(scan.points, sim_scan.points)
    assert scan.step_estimated
    np.testing.assert_allclose(scan.angular_step_deg, (0.25, 0.2), rtol=0.10)
    given = read_scan(p, angular_step_deg=(0.3, 0.3), name="other")
    assert given.angular_step_deg == (0.3, 0.3) and given.name == "other" and not given.step_estimated


@pytest.mark.parametrize(
    "name, text_of",
    [
        ("spaces.xyz", lambda p: _xyz_lines(p)),
        ("tabs.txt", lambda p: _xyz_lines(p, "\t")),
        ("header.csv", lambda p: "X,Y,Z,intensity\n" + "".join(f"{a!r},{b!r},{c!r},17\n" for a, b, c in p.tolist())),
        ("spaced.csv", lambda p: "".join(f"{a!r}, {b!r}, {c!r}\n" for a, b, c in p.tolist())),
        ("extra.txt", lambda p: "x y z r g b label\n" + "".join(f"{a!r} {b!r} {c!r} 1 2 3 leaf\n" for a, b, c in p.tolist())),
        ("comments.xyz", lambda p: "# exported by X\n// X Y Z\n\n" + _xyz_lines(p)),
        ("windows.csv", lambda p: "\ufeffx,y,z\r\n" + _xyz_lines(p, ",").replace("\n", "\r\n")),
    ],
)
def test_text_formats(tmp_path, pts, name, text_of):
    p = _write_text(tmp_path / name, text_of(pts))
    np.testing.assert_array_equal(read_points(p), pts)


def test_gzipped_text_with_hash_header(tmp_path, pts):
    p = tmp_path / "scan.xyz.gz"
    with gzip.open(p, "wt") as fh:
        fh.write("# x y z target_count target_index\n" + "".join(f"{a!r} {b!r} {c!r} 1 1\n" for a, b, c in pts.tolist()))
    np.testing.assert_array_equal(read_points(p), pts)


@needs(REAL_SCAN)
def test_real_gzipped_riegl_scan():
    p = read_points(REAL_SCAN)
    assert p.shape == (1_046_843, 3)
    np.testing.assert_array_equal(p[0], [-3.392, 12.330, -1.200])


def test_npy_and_npz(tmp_path, pts):
    np.save(tmp_path / "a.npy", pts.astype(np.float32))
    np.testing.assert_allclose(read_points(tmp_path / "a.npy"), pts, atol=1e-5)
    np.savez(tmp_path / "only.npz", pts)
    np.testing.assert_array_equal(read_points(tmp_path / "only.npz"), pts)
    np.savez(tmp_path / "first.npz", pts, np.zeros(3))  # which array is the scan is not guessed
    with pytest.raises(ScanError, match=r"holds 2 arrays \(arr_0, arr_1\) and none is named 'points'"):
        read_points(tmp_path / "first.npz")
    np.savez(tmp_path / "keyed.npz", colours=np.zeros((4, 3)), points=pts)
    np.testing.assert_array_equal(read_points(tmp_path / "keyed.npz"), pts)


# ---- bad input ---------------------------------------------------------------------------------
def test_missing_file(tmp_path):
    p = tmp_path / "nope.ply"
    with pytest.raises(ScanError, match=rf"^{p}: no such file$"):
        read_points(p)


@pytest.mark.parametrize("name", ["empty.xyz", "empty.ply", "empty.las", "empty.npy"])
def test_empty_file(tmp_path, name):
    p = _write_text(tmp_path / name, "")
    with pytest.raises(ScanError, match=rf"^{p}: the file is empty$"):
        read_points(p)


def test_only_header_or_comments(tmp_path):
    p = _write_text(tmp_path / "h.csv", "x,y,z\n")
    with pytest.raises(ScanError, match=r"h\.csv: the file holds no points \(only a header\)"):
        read_points(p)
    p = _write_text(tmp_path / "c.xyz", "# nothing\n\n")
    with pytest.raises(ScanError, match=r"c\.xyz: the file holds no points"):
        read_points(p)


def test_fewer_than_min_points(tmp_path, pts):
    p = _write_text(tmp_path / "few.xyz", _xyz_lines(pts[:12]))
    with pytest.raises(ScanError, match=r"few\.xyz: only 12 points; at least 100 are needed"):
        read_scan(p)
    with pytest.raises(ScanError, match=r"at least 50 are needed"):
        read_scan(p, min_points=50)


def test_non_numeric_text_names_the_line(tmp_path, pts):
    lines = _xyz_lines(pts[:20]).splitlines(keepends=True)
    lines[6] = "1.0 abc 3.0\n"
    p = _write_text(tmp_path / "bad.xyz", "# comment\n" + "".join(lines))
    with pytest.raises(ScanError, match=r"bad\.xyz: line 8, column 2: 'abc' is not a number"):
        read_points(p)


def test_too_few_columns_names_the_line(tmp_path, pts):
    lines = _xyz_lines(pts[:20]).splitlines(keepends=True)
    lines[3] = "1.0,2.0\n"
    p = _write_text(tmp_path / "short.csv", "".join(l.replace(" ", ",") for l in lines))
    with pytest.raises(ScanError, match=r"short\.csv: line 4 has 2 column\(s\).*x y z are needed.*commas"):
        read_points(p)


def test_unknown_extension_lists_supported(tmp_path):
    p = _write_text(tmp_path / "scan.pcd", "whatever")
    with pytest.raises(ScanError, match=r"scan\.pcd: unknown file type '\.pcd'; supported: \.ply, \.las, \.laz, .*\.npz.*\.e57, \.ptx"):
        read_points(p)
    with pytest.raises(ScanError, match=r"cannot write '\.xyz' files; supported: \.ply, \.las, \.laz"):
        write_scan(tmp_path / "out.xyz", np.zeros((5, 3)))


def test_nan_rows_are_dropped_with_a_warning_giving_the_count(tmp_path, pts):
    text = _xyz_lines(pts[:200]).splitlines(keepends=True)
    text[5] = "nan 1 2\n"
    text[9] = "1 inf 2\n"
    text[10] = "1 2 -inf\n"
    p = _write_text(tmp_path / "holes.xyz", "".join(text))
    with pytest.warns(ScanWarning, match=r"holes\.xyz: dropped 3 of 200 points with NaN or infinite"):
        out = read_points(p)
    assert out.shape == (197, 3) and np.isfinite(out).all()


def test_all_nan_is_an_error(tmp_path):
    np.save(tmp_path / "nan.npy", np.full((50, 3), np.nan))
    with pytest.raises(ScanError, match=r"nan\.npy: all 50 points have NaN or infinite coordinates; nothing is left"):
        read_points(tmp_path / "nan.npy")


def test_millimetre_coordinates_are_refused(tmp_path, sim_scan):
    p = write_scan(tmp_path / "mm.ply", sim_scan.points * 1000.0)  # a tree of thousands of units
    with pytest.raises(ScanError, match=r"mm\.ply: coordinates span .* units .*looks like millimetres.*scale the coordinates by 0\.001"):
        read_scan(p)
    assert read_points(p, check_units=False).shape == sim_scan.points.shape


def test_georeferenced_metres_are_not_mistaken_for_millimetres(tmp_path, pts):
    p = write_scan(tmp_path / "utm.las", pts + [512_345.0, 5_123_456.0, 250.0])
    assert read_points(p).shape == pts.shape  # a cloud (e.g. --from-points) may be georeferenced
    # A scan may not: its angles from the origin would mean nothing. Said plainly, not as millimetres.
    with pytest.raises(ScanError, match=r"utm\.las: the points lie 5,1\d\d,\d\d\d m or more from the origin, so the scan is "
                                        r"not in its scanner's frame \(georeferenced.*--scanner-position X Y Z"):
        read_scan(p)


@pytest.mark.parametrize("shape", [(100,), (100, 2), (100, 4), (2, 100, 3)])
def test_wrong_array_shape(tmp_path, shape):
    np.save(tmp_path / "bad.npy", np.zeros(shape))
    with pytest.raises(ScanError, match=rf"bad\.npy: the array has shape \({shape[0]},.*expected N x 3"):
        read_points(tmp_path / "bad.npy")


def test_non_numeric_array_and_corrupt_binary_files(tmp_path):
    np.save(tmp_path / "s.npy", np.array([["a", "b", "c"]] * 5))
    with pytest.raises(ScanError, match=r"s\.npy: the array holds <U1 values, not numbers"):
        read_points(tmp_path / "s.npy")
    p = _write_text(tmp_path / "junk.ply", "this is not a ply file at all\n")
    with pytest.raises(ScanError, match=r"junk\.ply: not a readable PLY file"):
        read_points(p)
    p = _write_text(tmp_path / "junk.laz", "LASF but broken")
    with pytest.raises(ScanError, match=r"junk\.laz: not a readable LAS/LAZ file"):
        read_points(p)
    p = tmp_path / "junk.xyz.gz"
    p.write_bytes(b"not gzip")
    with pytest.raises(ScanError, match=r"junk\.xyz\.gz: cannot read the file"):
        read_points(p)


# ---- atomic writes -----------------------------------------------------------------------------
def test_failed_write_leaves_no_file_and_keeps_the_old_one(tmp_path, pts, monkeypatch):
    target = write_scan(tmp_path / "keep.ply", pts)
    before = target.read_bytes()

    def broken(path, p, dtype):
        path.write_bytes(b"ply\nhalf")  # a partial file...
        raise OSError("disk full")  # ...then the failure

    monkeypatch.setattr(tio, "_write_ply", broken)
    with pytest.raises(OutputError, match=r"keep\.ply: could not be written \(disk full\); nothing was replaced"):
        write_scan(target, pts * 2)
    with pytest.raises(OutputError):
        write_scan(tmp_path / "new.ply", pts)
    assert target.read_bytes() == before
    assert sorted(f.name for f in tmp_path.iterdir()) == ["keep.ply"]


def test_write_rejects_bad_points(tmp_path):
    bad = np.zeros((10, 3))
    bad[2, 2] = np.nan
    with pytest.raises(ScanError, match=r"out\.ply: points to write contain NaN"):
        write_scan(tmp_path / "out.ply", bad)
    with pytest.raises(ScanError, match=r"out\.las: points to write have shape \(10, 2\)"):
        write_scan(tmp_path / "out.las", np.zeros((10, 2)))
    assert not any(tmp_path.iterdir())


def test_reading_a_directory_or_a_good_file_warns_nothing(tmp_path, pts):
    d = tmp_path / "dir.ply"
    d.mkdir()
    with pytest.raises(ScanError, match=r"dir\.ply: is a directory"):
        read_points(d)
    p = write_scan(tmp_path / "ok.ply", pts)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_points(p)


def test_extension_handles_case_and_gzip():
    assert tio.extension("A.PLY") == ".ply"
    assert tio.extension("x/scan.v2.XYZ.gz") == ".xyz.gz"
    assert tio.extension("noext") == ""


def test_merged_cloud_carries_each_points_scan_number(tmp_path):
    """PLY: a `scan_id` vertex property; LAS: `point_source_id`; unregistered scans left out."""
    import laspy

    from treereg_core.io.merged import merged_cloud, write_merged
    from treereg_core.scan import Scan

    rng = np.random.default_rng(3)
    scans = [Scan.from_points(rng.normal(size=(n, 3)) + [5, 0, 2], name=f"s{k + 1}.ply", angular_step_deg=(0.1, 0.1))
             for k, n in enumerate((400, 300, 200))]
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    transforms = {"s1.ply": np.eye(4), "s3.ply": T}  # s2 did not register
    pts, ids = merged_cloud(scans, transforms)
    assert len(pts) == 600 and set(np.unique(ids)) == {1, 3}
    np.testing.assert_allclose(pts[ids == 3], scans[2].points + [1.0, 2.0, 3.0])
    las = laspy.read(write_merged(tmp_path / "m.las", scans, transforms))
    np.testing.assert_array_equal(np.asarray(las.point_source_id), ids)
    np.testing.assert_allclose(np.c_[las.x, las.y, las.z], pts, atol=1e-4)
    ply = write_merged(tmp_path / "m.ply", scans, transforms)
    head, body = ply.read_bytes().split(b"end_header\n", 1)
    assert b"property ushort scan_id" in head
    rec = np.frombuffer(body, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("scan_id", "<u2")])
    np.testing.assert_array_equal(rec["scan_id"], ids)
    np.testing.assert_allclose(np.c_[rec["x"], rec["y"], rec["z"]], pts, atol=1e-5)
    np.testing.assert_allclose(read_points(ply), pts, atol=1e-5)  # our reader still reads it
