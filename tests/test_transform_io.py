"""transforms.json, CloudCompare and PDAL matrices: exact round trips and validated reads."""

from __future__ import annotations

import json

import numpy as np
import pytest

from treereg_core._version import __version__
from treereg_core.errors import ConfigError
from treereg_core.params import PRESETS, to_dict
from treereg_core.results import Metric
from treereg_core.geometry.rigid import apply_transform, make_transform, rotation_z
from treereg_core.io.transforms import (
    TransformFile,
    cloudcompare_matrix_text,
    parse_cloudcompare_matrix,
    parse_pdal_matrix,
    pdal_matrix_string,
    read_transforms,
    transforms_json_text,
    write_exports,
    write_transforms,
)


def random_rigid(seed: int) -> np.ndarray:
    """A general rigid 4x4: rotation from a random quaternion, translation of metres."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    R = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])
    return make_transform(R, rng.uniform(-20, 20, 3))


@pytest.fixture()
def tf() -> TransformFile:
    return TransformFile(
        reference="scan1.ply",
        transforms={"scan2.ply": random_rigid(1), "scan3.ply": make_transform(rotation_z(123.4), [1.5, -2.0, 0.1])},
        params=to_dict(PRESETS["paper"]),
        extra={
            "angular_step_deg": [0.1, 0.1],
            "metrics": {"scan2.ply": [Metric("rotation error", "deg", np.float64(0.0123))]},
            "rmse_m": float("nan"),
            "counts": np.array([3, 4]),
        },
    )


def test_json_layout_is_exactly_the_documented_one(tmp_path, tf):
    path = write_transforms(tmp_path / "transforms.json", tf)
    data = json.loads(path.read_text())
    assert list(data)[:4] == ["reference", "transforms", "params", "software"]
    assert data["reference"] == "scan1.ply"
    assert data["software"] == f"treereg {__version__}" == "treereg 0.1.0"
    assert data["transforms"]["scan2.ply"] == tf.transforms["scan2.ply"].tolist()  # 4x4, row-major
    assert data["params"] == to_dict(PRESETS["paper"])
    assert data["angular_step_deg"] == [0.1, 0.1]
    assert data["metrics"]["scan2.ply"][0] == {"description": "rotation error", "unit": "deg", "value": 0.0123}
    assert data["rmse_m"] is None and data["counts"] == [3, 4]
    assert "  [0.0, 0.0, 0.0, 1.0]" in path.read_text()  # one matrix row per line


def test_round_trip_is_bit_exact(tmp_path, tf):
    back = read_transforms(write_transforms(tmp_path / "t.json", tf))
    assert back.reference == tf.reference and back.software == tf.software and back.params == tf.params
    assert list(back.transforms) == ["scan2.ply", "scan3.ply"]
    for name, T in tf.transforms.items():
        np.testing.assert_array_equal(back.transforms[name], T)
    assert back.extra["angular_step_deg"] == [0.1, 0.1]
    assert transforms_json_text(back) == (tmp_path / "t.json").read_text()  # re-writing changes nothing


def test_matrix_maps_scan_into_reference_and_reference_is_identity(tf):
    np.testing.assert_array_equal(tf.matrix("scan1.ply"), np.eye(4))
    assert tf.names == ["scan1.ply", "scan2.ply", "scan3.ply"]
    p = np.array([[1.0, 2.0, 3.0]])
    np.testing.assert_allclose(apply_transform(tf.matrix("scan3.ply"), p),
                               p @ rotation_z(123.4).T + [1.5, -2.0, 0.1])
    with pytest.raises(KeyError, match="scan9.ply"):
        tf.matrix("scan9.ply")
    with pytest.raises(ValueError):
        tf.transforms["scan2.ply"][0, 0] = 2.0  # read-only


def _doc(T) -> dict:
    return {"reference": "scan1.ply", "transforms": {"scan2.ply": T}, "params": {}, "software": "treereg 0.1.0"}


def _write(tmp_path, doc, raw: str | None = None):
    p = tmp_path / "transforms.json"
    p.write_text(raw if raw is not None else json.dumps(doc))
    return p


@pytest.mark.parametrize(
    "T, problem",
    [
        ([[1, 0, 0], [0, 1, 0], [0, 0, 1]], r"expected a 4x4 matrix .*shape \(3, 3\)"),
        ("identity", r"not a 4x4 matrix of numbers"),
        ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, "a"], [0, 0, 0, 1]], r"not a 4x4 matrix of numbers"),
        ((np.eye(4) * [1.01, 1, 1, 1]).tolist(), r"rotation part is not orthonormal"),
        ((np.eye(4) * [-1, 1, 1, 1]).tolist(), r"reflection"),
        ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0.5, 1]], r"last row must be 0 0 0 1"),
    ],
)
def test_bad_matrices_are_named_by_file_and_key(tmp_path, T, problem):
    p = _write(tmp_path, _doc(T))
    with pytest.raises(ConfigError, match=rf"^{p}: transforms\['scan2\.ply'\]: .*{problem}"):
        read_transforms(p)


def test_nan_in_matrix(tmp_path):
    p = _write(tmp_path, None, raw='{"reference": "a.ply", "transforms": {"b.ply": '
               '[[NaN, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}}')
    with pytest.raises(ConfigError, match=r"transforms\['b\.ply'\]: the matrix contains NaN"):
        read_transforms(p)


def test_bad_files(tmp_path):
    with pytest.raises(ConfigError, match=r"missing\.json: no such transform file"):
        read_transforms(tmp_path / "missing.json")
    p = _write(tmp_path, None, raw="{not json")
    with pytest.raises(ConfigError, match=rf"^{p}: not valid JSON"):
        read_transforms(p)
    p = _write(tmp_path, {"transforms": {}})
    with pytest.raises(ConfigError, match=rf"^{p}: missing key 'reference'"):
        read_transforms(p)
    p = _write(tmp_path, {"reference": "a.ply", "transforms": [1, 2]})
    with pytest.raises(ConfigError, match=rf"^{p}: 'transforms' must be an object"):
        read_transforms(p)
    p = _write(tmp_path, {"reference": "", "transforms": {}})
    with pytest.raises(ConfigError, match=rf"^{p}: 'reference' must be a scan file name"):
        read_transforms(p)


def test_nearly_orthonormal_matrices_pass(tmp_path):
    T = random_rigid(3)
    T[:3, :3] += 1e-8  # e.g. printed with limited precision by another tool
    back = read_transforms(_write(tmp_path, _doc(T.tolist())))
    np.testing.assert_array_equal(back.transforms["scan2.ply"], T)


def test_cloudcompare_text_round_trip():
    T = random_rigid(5)
    text = cloudcompare_matrix_text(T)
    lines = text.strip().splitlines()
    assert len(lines) == 4 and all(len(line.split()) == 4 for line in lines)
    assert lines[3].split() == ["0.0", "0.0", "0.0", "1.0"]
    np.testing.assert_array_equal(parse_cloudcompare_matrix(text), T)
    # CloudCompare's console adds a title and a timestamp around the four rows
    wrapped = "Transformation matrix\n" + text + "Timestamp: 2024-01-01 10:00\n"
    np.testing.assert_array_equal(parse_cloudcompare_matrix(wrapped), T)
    with pytest.raises(ConfigError, match="expected 4 lines of 4 numbers, found 3"):
        parse_cloudcompare_matrix("\n".join(lines[:3]))


def test_pdal_string_round_trip():
    T = random_rigid(6)
    s = pdal_matrix_string(T)
    values = [float(v) for v in s.split(" ")]
    assert len(values) == 16 and values[3] == T[0, 3] and values[12:] == [0.0, 0.0, 0.0, 1.0]  # row-major
    np.testing.assert_array_equal(parse_pdal_matrix(s), T)
    with pytest.raises(ConfigError, match="expected 16 numbers, found 15"):
        parse_pdal_matrix(" ".join(s.split()[:15]))


def test_exports_write_every_scan(tmp_path, tf):
    written = write_exports(tmp_path / "out", tf)
    names = [p.name for p in written]
    assert names == ["transforms.json",
                     "transforms.scan1.cloudcompare.txt", "transforms.scan1.pdal.txt",
                     "transforms.scan2.cloudcompare.txt", "transforms.scan2.pdal.txt",
                     "transforms.scan3.cloudcompare.txt", "transforms.scan3.pdal.txt"]
    out = tmp_path / "out"
    np.testing.assert_array_equal(parse_cloudcompare_matrix((out / "transforms.scan1.cloudcompare.txt").read_text()),
                                  np.eye(4))
    for name in ("scan2", "scan3"):
        T = tf.transforms[f"{name}.ply"]
        np.testing.assert_array_equal(parse_cloudcompare_matrix((out / f"transforms.{name}.cloudcompare.txt").read_text()), T)
        np.testing.assert_array_equal(parse_pdal_matrix((out / f"transforms.{name}.pdal.txt").read_text()), T)
    assert not [p for p in out.iterdir() if p.name.endswith(".tmp")]


def test_two_cases_in_one_folder_keep_their_matrices(tmp_path, tf):
    """Each case's matrices are named after its transform file: a second case overwrites nothing."""
    other = TransformFile(reference="scan1.ply", transforms={"scan2.ply": random_rigid(11)})
    write_exports(tmp_path, tf, name="caseA.json")
    write_exports(tmp_path, other, name="caseB.json")
    a = parse_cloudcompare_matrix((tmp_path / "caseA.scan2.cloudcompare.txt").read_text())
    b = parse_cloudcompare_matrix((tmp_path / "caseB.scan2.cloudcompare.txt").read_text())
    np.testing.assert_array_equal(a, tf.transforms["scan2.ply"])
    np.testing.assert_array_equal(b, other.transforms["scan2.ply"])


def test_exports_keep_names_apart_when_stems_clash(tmp_path):
    tf = TransformFile(reference="a.ply", transforms={"b.ply": np.eye(4), "b.las": random_rigid(2)})
    names = {p.name for p in write_exports(tmp_path, tf, name="reg.json")}
    assert {"reg.json", "reg.a.cloudcompare.txt", "reg.b.ply.cloudcompare.txt", "reg.b.las.pdal.txt"} <= names


def test_failed_write_keeps_the_previous_file(tmp_path, tf):
    path = write_transforms(tmp_path / "transforms.json", tf)
    before = path.read_text()
    broken = TransformFile(reference="scan1.ply", transforms={}, extra={"bad": object()})
    with pytest.raises(TypeError):
        write_transforms(path, broken)
    assert path.read_text() == before
    assert [p.name for p in tmp_path.iterdir()] == ["transforms.json"]


def test_constructor_validates():
    with pytest.raises(ConfigError, match=r"transforms\['x\.ply'\]: expected a 4x4"):
        TransformFile(reference="r.ply", transforms={"x.ply": np.eye(3)})
    with pytest.raises(ConfigError, match="reserved"):
        TransformFile(reference="r.ply", transforms={}, extra={"params": {}})
