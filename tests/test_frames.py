"""Scans not in their scanner's frame: detected, and with the scanner position (given or from the
file's pose) registered as well as the originals, millimetres kept at UTM-sized coordinates."""

import warnings
from pathlib import Path

import numpy as np
import pytest

from treereg_cli.main import main
from treereg_core.demo import demo_case
from treereg_core.errors import ScanError
from treereg_core.geometry.rigid import apply_transform, invert, make_transform, rotation_z
from treereg_core.io.scans import ScanWarning, read_scan, write_scan
from treereg_core.io.transforms import read_transforms

#: Where each demo scanner stands in a (UTM-like) map frame.
UTM = [(512_345.678, 5_401_234.567, 312.4), (512_371.002, 5_401_250.111, 311.9), (512_330.515, 5_401_262.909, 313.0)]
#: Headings of the scanners in the map frame, for the copies that are also turned.
HEADINGS = [20.0, -75.0, 140.0]


def _georeferenced(case, d, headings):
    files, G = [], []
    for scan, pos, heading in zip(case.scans, UTM, headings):
        G.append(make_transform(rotation_z(heading), pos))
        # LAS keeps 0.1 mm at these coordinates (scaled integers with an offset), as a real export would.
        name = scan.name.replace(".ply", f"_utm{'_turned' if any(headings) else ''}.las")
        write_scan(d / name, apply_transform(G[-1], scan.points))
        files.append(str(d / name))
    return files, G


@pytest.fixture(scope="module")
def demo_files(tmp_path_factory):
    case = demo_case()
    d = tmp_path_factory.mktemp("demo")
    plain = []
    for scan in case.scans:
        write_scan(d / scan.name, scan.points)
        plain.append(str(d / scan.name))
    geo, G = _georeferenced(case, d, [0.0] * 3)
    turned, G_turned = _georeferenced(case, d, HEADINGS)
    return case, plain, geo, G, turned, G_turned


#: The demo's instrument steps, given to both runs: estimated from points rounded to LAS's 0.1 mm
#: they could differ in the last digits, and the comparison is about the frames, not the estimate.
STEP = ["--angular-step", "0.06", "0.06"]


def _register_georeferenced(files, out):
    args = ["register", *files, "--out", str(out), *STEP]
    for pos in UTM:
        args += ["--scanner-position", *map(str, pos)]
    assert main(args) == 0
    return read_transforms(out)


@pytest.mark.slow
def test_georeferenced_copies_register_to_the_same_transforms(demo_files, tmp_path):
    case, plain, geo, G, _, _ = demo_files
    assert main(["register", *plain, "--out", str(tmp_path / "plain.json"), *STEP]) == 0
    t_plain = read_transforms(tmp_path / "plain.json")
    t_geo = _register_georeferenced(geo, tmp_path / "geo.json")
    for k, scan in enumerate(case.scans[1:], start=1):
        T = t_plain.matrix(scan.name)
        # The georeferenced file's matrix maps UTM points of scan k onto UTM points of scan 1 ...
        T_geo = t_geo.matrix(Path(geo[k]).name)
        back = invert(G[0]) @ T_geo @ G[k]  # ... mapped back into the scanner frames: the same transform
        d = np.linalg.norm(apply_transform(back, scan.points) - apply_transform(T, scan.points), axis=1)
        assert d.mean() < 0.001, f"{scan.name}: georeferenced copy differs by {d.mean() * 1000:.2f} mm"
    assert "poses" in t_geo.extra


def test_turned_georeferenced_copies_register_in_the_map_frame(demo_files, tmp_path):
    case, _, _, _, turned, G = demo_files
    t_geo = _register_georeferenced(turned, tmp_path / "turned.json")
    for k, scan in enumerate(case.scans[1:], start=1):
        # The matrix moves scan k's map points onto scan 1's map points as the truth does.
        truth = G[0] @ case.truth[scan.name] @ invert(G[k])
        utm = apply_transform(G[k], scan.points)
        T_geo = t_geo.matrix(Path(turned[k]).name)
        assert np.linalg.norm(apply_transform(T_geo, utm) - apply_transform(truth, utm), axis=1).mean() < 0.01


def test_far_scan_without_position_is_refused_naming_the_flag(demo_files, tmp_path, capsys):
    geo = demo_files[2]
    with pytest.raises(ScanError, match=r"not in its scanner's frame.*--scanner-position X Y Z"):
        read_scan(geo[0])
    assert main(["register", *geo, "--out", str(tmp_path / "t.json")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--scanner-position" in err
    assert not (tmp_path / "t.json").exists()


def test_wrong_number_of_positions_is_one_line(demo_files, tmp_path, capsys):
    geo = demo_files[2]
    assert main(["register", *geo, "--out", str(tmp_path / "t.json"), "--scanner-position", "1", "2", "3"]) == 2
    assert "once per scan" in capsys.readouterr().err


def test_scan_shifted_off_its_scanner_warns_about_both_flags(tmp_path):
    scan = demo_case().scans[0]
    write_scan(tmp_path / "shifted.ply", scan.points + [25.0, 8.0, 0.0])  # a project frame, 25 m off
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        s = read_scan(tmp_path / "shifted.ply")
    assert s.step.low
    text = " ".join(str(x.message) for x in w if issubclass(x.category, ScanWarning))
    assert "--scanner-position" in text and "--angular-step" in text
    # With the position the grid is regular again and nothing is said.
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        s = read_scan(tmp_path / "shifted.ply", scanner_position=(25.0, 8.0, 0.0))
    assert not [x for x in w if issubclass(x.category, ScanWarning)]
    assert s.step.confidence > 0.7 and s.angular_step_deg == pytest.approx((0.06, 0.06), rel=0.02)
    assert np.allclose(apply_transform(s.pose, s.points), scan.points + [25.0, 8.0, 0.0])


def test_cli_prints_a_doubtful_step_as_one_warning_line(tmp_path, capsys):
    case = demo_case()
    files = []
    for scan in case.scans[:2]:
        write_scan(tmp_path / scan.name, scan.points + [25.0, 8.0, 0.0])
        files.append(str(tmp_path / scan.name))
    main(["register", *files, "--until", "coarse", "--out", str(tmp_path / "t.json")])
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("treereg: warning:")]
    assert len(lines) == 2 and all("--angular-step H V" in ln and "confidence" in ln for ln in lines)
