"""E57 and PTX as they come from other tools: names, poses, grids, invalid cells, returns; a multi-scan
E57 registers with `treereg register stations.e57` and the E57 we write reopens registered."""

import gzip
import warnings

import laspy
import numpy as np
import pytest

from conftest import SHARED, needs
from treereg_cli.main import main
from treereg_core.demo import demo_case
from treereg_core.errors import ScanError
from treereg_core.geometry.rigid import apply_transform, make_transform, mean_displacement, rotation_error_deg, rotation_z
from treereg_core.io.e57 import pose_matrix, pose_quaternion, read_e57
from treereg_core.io.ptx import read_ptx, write_ptx
from treereg_core.io.scans import read_records, read_scan, read_scans
from treereg_core.io.transforms import read_transforms

E57_DIR = SHARED / "data" / "e57"


def _write_e57_like_another_tool(path, scans):
    """An E57 written with pye57 directly, as a scanner's software or CloudCompare would: one data3D
    entry per scan, points in the scan's own frame, an optional pose."""
    import pye57

    e = pye57.E57(str(path), mode="w")
    for name, pts, T in scans:
        kw = {} if T is None else dict(zip(("rotation", "translation"), pose_quaternion(T)))
        e.write_scan_raw({"cartesianX": pts[:, 0], "cartesianY": pts[:, 1], "cartesianZ": pts[:, 2]}, name=name, **kw)
    e.close()


@needs(E57_DIR / "pumpAVisualReferenceImage.e57")
def test_structured_e57_from_a_real_scanner_reads_name_grid_and_step():
    (scan,) = read_scans(E57_DIR / "pumpAVisualReferenceImage.e57")
    assert scan.name == "pumpA"
    assert scan.n_points == 155_201  # the grid's 1074 x 345 cells less the invalid ones
    assert scan.step.source == "grid"  # the exact step from rowIndex/columnIndex, not an estimate
    assert scan.angular_step_deg == pytest.approx((0.2504, 0.06754), rel=2e-3)
    assert np.allclose(scan.pose, np.eye(4))


@needs(E57_DIR / "translationWithoutRotation.e57")
def test_e57_pose_is_kept_and_points_stay_in_the_scan_frame():
    (rec,) = read_records(E57_DIR / "translationWithoutRotation.e57")
    assert rec.name == "Scan 0"
    assert np.allclose(rec.pose, make_transform(np.eye(3), [4, 5, 6]))
    assert np.allclose(rec.points, [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])  # not moved by the pose


def test_pose_quaternion_round_trip():
    T = make_transform(rotation_z(123.0) @ np.array([[1, 0, 0], [0, np.cos(0.01), -np.sin(0.01)], [0, np.sin(0.01), np.cos(0.01)]]),
                       [500_000.123, 5_000_000.456, 301.2])
    q, t = pose_quaternion(T)
    assert np.allclose(pose_matrix(q, t), T, atol=1e-12)


@pytest.mark.slow
def test_multi_scan_e57_from_another_tool_registers_and_our_e57_reopens_registered(tmp_path, capsys):
    case = demo_case()
    # Unnamed scans fall back to <stem>#k; the third scan carries a pose (georeferenced-sized).
    P3 = make_transform(rotation_z(30.0), [412_345.678, 5_123_456.789, 250.0])
    src = tmp_path / "stations.e57"
    _write_e57_like_another_tool(src, [("north", case.scans[0].points, None), ("", case.scans[1].points, None),
                                       ("south", case.scans[2].points, P3)])
    names = [r.name for r in read_e57(src)]
    assert names == ["north", "stations#2", "south"]

    out, reg = tmp_path / "t.json", tmp_path / "registered.e57"
    assert main(["register", str(src), "--out", str(out), "--e57", str(reg)]) == 0
    tf = read_transforms(out)
    assert tf.reference == "north"
    truth = case.truth
    # scan 2: no pose, the transform is the scanner-frame one
    T2 = tf.matrix("stations#2")
    # the demo reaches 0.04 deg and 1.6 mm for scan 2; held to about three times that
    assert rotation_error_deg(T2, truth["scan2.ply"]) < 0.12
    assert mean_displacement(T2, truth["scan2.ply"], case.scans[1].points) < 0.005
    # scan 3: its matrix maps the points as the file places them (pose applied) onto the reference
    T3 = tf.matrix("south")
    placed = apply_transform(P3, case.scans[2].points)
    expected = apply_transform(truth["scan3.ply"], case.scans[2].points)
    assert np.mean(np.linalg.norm(apply_transform(T3, placed) - expected, axis=1)) < 0.006  # 2.3 mm reached
    assert tf.extra["poses"]["south"][0][3] == pytest.approx(P3[0, 3])

    # Our E57: every scan in its own frame, posed where the registration puts it.
    back = {r.name: r for r in read_e57(reg)}
    assert set(back) == {"north", "stations#2", "south"}
    assert np.allclose(back["north"].pose, np.eye(4))
    for name, scan, P in (("stations#2", case.scans[1], np.eye(4)), ("south", case.scans[2], P3)):
        r = back[name]
        assert np.allclose(r.points, scan.points, atol=1e-4)  # stored in the scan's frame (32-bit floats)
        landed = apply_transform(r.pose, r.points)
        said = apply_transform(tf.matrix(name) @ P, scan.points)
        assert np.abs(landed - said).max() < 1e-3


def test_bad_e57_is_one_line(tmp_path):
    bad = tmp_path / "broken.e57"
    bad.write_bytes(b"ASTM-E57" + b"\0" * 2000)
    with pytest.raises(ScanError, match=r"broken\.e57: not a readable E57 file"):
        read_scans(bad)
    assert main(["register", str(bad), str(bad), "--out", str(tmp_path / "t.json")]) == 2
    assert not (tmp_path / "t.json").exists()


def _grid(rows, cols, step=(0.2, 0.1), r=6.0):
    az = np.radians(np.arange(cols) * step[0])
    el = np.radians(-10 + np.arange(rows) * step[1])
    A, E = np.meshgrid(az, el)
    R = r + 0.5 * np.sin(3 * A)
    return np.stack([R * np.cos(E) * np.cos(A), R * np.cos(E) * np.sin(A), R * np.sin(E)], axis=-1)


def test_ptx_scans_with_pose_grid_and_missing_cells(tmp_path):
    g = _grid(60, 90)
    g[20:35, 40:55] = 0.0  # no return there: written as 0 0 0
    T = make_transform(rotation_z(40.0), [1000.0, 2000.0, 5.0])
    path = write_ptx(tmp_path / "site.ptx", [(g, T, 60, 90), (_grid(60, 90, (0.3, 0.3)), np.eye(4), 60, 90)])
    recs = read_ptx(path)
    assert [r.name for r in recs] == ["site#1", "site#2"]
    assert len(recs[0].points) == 60 * 90 - 15 * 15
    assert np.allclose(recs[0].pose, T)
    scans = read_scans(path)
    assert scans[0].step.source == "grid"
    assert scans[0].angular_step_deg == pytest.approx((0.2, 0.1), rel=1e-6)
    assert scans[1].angular_step_deg == pytest.approx((0.3, 0.3), rel=1e-6)
    # one scan: named after the file
    single = write_ptx(tmp_path / "one.ptx", [(g, np.eye(4), 60, 90)])
    assert read_scan(single).name == "one.ptx"


def test_malformed_ptx_names_the_line(tmp_path):
    p = tmp_path / "bad.ptx"
    p.write_text("10\n5\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n1 0 0 0\n0 1 x 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(ScanError, match=r"bad\.ptx: line 8: expected 4 numbers"):
        read_ptx(p)
    short = tmp_path / "short.ptx"
    short.write_text("10\n5\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n1 2 3 0.5\n")
    with pytest.raises(ScanError, match=r"short\.ptx: scan 1: the file ends after 1 of its 10 x 5 = 50 points"):
        read_ptx(short)


def test_returns_first_or_all_from_las_and_from_a_text_header(tmp_path):
    case = demo_case()
    pts = case.scans[0].points
    ret = np.ones(len(pts), dtype=np.uint8)
    ret[::10] = 2  # every tenth point a second return
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales = np.full(3, 1e-4)
    header.offsets = np.floor(pts.min(axis=0))
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    las.return_number = ret
    las.number_of_returns = np.where(ret == 2, 2, 1).astype(np.uint8)
    las.write(tmp_path / "s.las")
    assert read_scan(tmp_path / "s.las").n_points == int((ret == 1).sum())
    assert read_scan(tmp_path / "s.las", returns="all").n_points == len(pts)

    # The real RIEGL station's text layout: a comment header naming target_count and target_index.
    txt = tmp_path / "s.xyz.gz"
    with gzip.open(txt, "wt") as fh:
        fh.write("# x y z target_count target_index\n")
        np.savetxt(fh, np.column_stack([pts, np.where(ret == 2, 2, 1), ret]), fmt="%.4f %.4f %.4f %d %d")
    assert read_scan(txt).n_points == int((ret == 1).sum())
    assert read_scan(txt, returns="all").n_points == len(pts)


def test_cli_returns_flag_reaches_the_reader(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(["params", "--preset", "robust"]) == 0  # the parser still builds with the new options
    from treereg_cli.main import build_parser

    args = build_parser().parse_args(["register", "a.e57", "--returns", "all", "--tree-at", "1", "2",
                                      "--scanner-position", "1", "2", "3"])
    assert args.returns == "all" and args.tree_at == [1.0, 2.0] and args.scanner_position == [[1.0, 2.0, 3.0]]


def _write_e57_with_returns(path, pts, ret):
    """An E57 whose points carry returnIndex/returnCount (as multi-return scanners write), via libE57."""
    import uuid

    import pye57
    from pye57 import libe57

    e = pye57.E57(str(path), mode="w")
    imf = e.image_file
    node = libe57.StructureNode(imf)
    node.set("guid", libe57.StringNode(imf, "{%s}" % uuid.uuid4()))
    node.set("name", libe57.StringNode(imf, "multi"))
    proto = libe57.StructureNode(imf)
    for f in ("cartesianX", "cartesianY", "cartesianZ"):
        proto.set(f, libe57.FloatNode(imf, 0.0, libe57.E57_DOUBLE, -1e6, 1e6))
    proto.set("returnIndex", libe57.IntegerNode(imf, 0, 0, 7))
    proto.set("returnCount", libe57.IntegerNode(imf, 1, 1, 8))
    cv = libe57.CompressedVectorNode(imf, proto, libe57.VectorNode(imf, True))
    node.set("points", cv)
    e.data3d.append(node)
    n = len(pts)
    arrays = {"cartesianX": np.ascontiguousarray(pts[:, 0]), "cartesianY": np.ascontiguousarray(pts[:, 1]),
              "cartesianZ": np.ascontiguousarray(pts[:, 2]), "returnIndex": ret.astype("q"),
              "returnCount": (ret + 1).astype("q")}
    bufs = libe57.VectorSourceDestBuffer()
    for k, v in arrays.items():
        bufs.append(libe57.SourceDestBuffer(imf, k, v, n, True, True))
    w = cv.writer(bufs)
    w.write(n)
    w.close()
    e.close()


def test_e57_return_numbers_select_first_or_all(tmp_path):
    pts = demo_case().scans[0].points
    ret = (np.arange(len(pts)) % 5 == 0).astype(int)  # every fifth point a second return
    _write_e57_with_returns(tmp_path / "returns.e57", pts, ret)
    assert read_scan(tmp_path / "returns.e57").n_points == int((ret == 0).sum())
    assert read_scan(tmp_path / "returns.e57", returns="all").n_points == len(pts)
