"""Scans with the same file name in different folders (one folder per station, as many scanners
export) are named by folder everywhere: the CLI's lines, transforms.json, the merged cloud, the
matrix files, batch and the app (issue 18, point 7)."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys

import laspy
import numpy as np
import pytest

from hostile import REPO, _env, cli, one_line, view_started
from treereg_cli.common import read_scans
from treereg_cli.main import main
from treereg_core.batch.jobs import TreeJob
from treereg_core.batch.runner import run_batch
from treereg_core.demo import DEMO_DIR
from treereg_core.errors import ConfigError
from treereg_core.io.naming import file_stem, scan_names
from treereg_core.io.scans import read_records
from treereg_core.io.transforms import export_names, parse_cloudcompare_matrix, parse_pdal_matrix, read_transforms
from treereg_core.params import Params

NAMES = ["a/scan1.ply", "b/scan1.ply", "c/scan1.ply"]


@pytest.fixture(scope="module")
def stations(tmp_path_factory):
    """The demo's three scans, each as scan1.ply in a folder of its own (a, b, c), and the demo's
    truth under those names."""
    root = tmp_path_factory.mktemp("stations")
    for k, d in enumerate("abc"):
        (root / d).mkdir()
        shutil.copy(DEMO_DIR / f"scan{k + 1}.ply", root / d / "scan1.ply")
    truth = json.loads((DEMO_DIR / "truth.json").read_text())
    by_demo = {f"scan{k + 1}.ply": name for k, name in enumerate(NAMES)}
    truth["reference"] = by_demo[truth["reference"]]
    truth["transforms"] = {by_demo[n]: T for n, T in truth["transforms"].items()}
    (root / "truth.json").write_text(json.dumps(truth))
    return root


def test_clashing_names_take_the_shortest_folder_suffix_and_the_others_keep_theirs():
    assert scan_names([("s/a/scan1.ply", "scan1.ply"), ("s/b/scan1.ply", "scan1.ply"), ("s/b/scan2.ply", "scan2.ply")]) \
        == ["a/scan1.ply", "b/scan1.ply", "scan2.ply"]
    # Deeper only where needed: each scan as deep as tells it from the others.
    assert scan_names([("site1/a/scan1.ply", "scan1.ply"), ("site2/a/scan1.ply", "scan1.ply"), ("b/scan1.ply", "scan1.ply")]) \
        == ["site1/a/scan1.ply", "site2/a/scan1.ply", "b/scan1.ply"]
    # Scans named inside their files: by file where two files hold the same name, else as they are.
    assert scan_names([("x.e57", "Station 1"), ("y.e57", "Station 1"), ("y.e57", "Station 2")]) \
        == ["x.e57#Station 1", "y.e57#Station 1", "Station 2"]
    assert scan_names([("a/site.e57", "Station 1"), ("b/site.e57", "Station 1")]) \
        == ["a/site.e57#Station 1", "b/site.e57#Station 1"]


def test_the_same_scan_given_twice_is_one_line_naming_it():
    with pytest.raises(ConfigError, match=r"^\./a/scan1\.ply: given twice \(also as a/scan1\.ply\); give each scan once$"):
        scan_names([("a/scan1.ply", "scan1.ply"), ("./a/scan1.ply", "scan1.ply")])


def test_register_given_one_file_twice_says_so_in_one_line(stations, tmp_path, capsys):
    rc, err = cli(capsys, "register", stations / "a" / "scan1.ply", stations / "a" / "scan1.ply",
                  "--out", tmp_path / "t.json")
    assert rc == 2 and not (tmp_path / "t.json").exists()
    one_line(err, r"^treereg: error: .*a/scan1\.ply: given twice; give each scan once$")


def test_files_named_after_scans_never_make_folders():
    assert file_stem("a/scan1.ply") == "a_scan1" and file_stem("scan2.ply") == "scan2"
    files = [f for pair in export_names(NAMES + ["a_scan1.ply"], "t.json").values() for f in pair]
    assert len(set(files)) == len(files) and not any("/" in f or "\\" in f for f in files)
    assert export_names(NAMES, "t.json")["b/scan1.ply"] == ("t.b_scan1.cloudcompare.txt", "t.b_scan1.pdal.txt")


def test_the_view_commands_reader_names_scans_by_folder_only_where_needed(stations, tmp_path):
    files = [str(stations / n) for n in NAMES]
    assert [s.name for s in read_scans(files[:2], Params())] == NAMES[:2]
    (tmp_path / "x").mkdir()
    shutil.copy(DEMO_DIR / "scan2.ply", tmp_path / "x" / "scan2.ply")
    assert [s.name for s in read_scans([files[0], str(tmp_path / "x" / "scan2.ply")], Params())] == ["scan1.ply", "scan2.ply"]


@pytest.mark.slow
def test_register_names_them_in_transforms_json_the_merged_clouds_and_the_exports(stations, tmp_path, capsys):
    out = tmp_path / "res" / "t.json"
    merged = tmp_path / "res" / "m.las"
    capsys.readouterr()
    assert main(["register", *(str(stations / n) for n in NAMES), "--out", str(out), "--exports",
                 "--merged", str(merged), "--details"]) == 0
    lines = capsys.readouterr().out
    assert "b/scan1.ply -> a/scan1.ply" in lines and re.search(r"^\s+c/scan1\.ply\s+verified", lines, re.M)
    # The summary: a row per scan, by its name, the reference as such.
    assert re.search(r"^\s+a/scan1\.ply\s+reference$", lines, re.M) and re.search(r"^\s+b/scan1\.ply\s+verified\s+0\.9", lines, re.M)
    tf = read_transforms(out)
    assert tf.reference == "a/scan1.ply" and list(tf.transforms) == NAMES
    assert set(tf.extra["sources"]) == set(NAMES)
    # Each scan's matrices in a file of its own, beside --out (no folder made), holding its transform.
    assert sorted(p.name for p in out.parent.iterdir()) == sorted(
        ["t.json", "m.las", "t.registered.e57"] + [f"t.{d}_scan1.{k}.txt" for d in "abc" for k in ("cloudcompare", "pdal")])
    for name, d in zip(NAMES, "abc"):
        assert np.allclose(parse_cloudcompare_matrix((out.parent / f"t.{d}_scan1.cloudcompare.txt").read_text()), tf.matrix(name))
        assert np.allclose(parse_pdal_matrix((out.parent / f"t.{d}_scan1.pdal.txt").read_text()), tf.matrix(name))
    assert [r.name for r in read_records(out.parent / "t.registered.e57")] == NAMES
    las = laspy.read(merged)
    vlr = next(v for v in las.header.vlrs if v.user_id == "treereg")
    assert json.loads(vlr.record_data) == {"1": NAMES[0], "2": NAMES[1], "3": NAMES[2]}
    assert sorted(set(np.asarray(las.point_source_id).tolist())) == [1, 2, 3]
    # Read back by name: evaluate finds each scan and its truth under its folder name.
    capsys.readouterr()
    assert main(["evaluate", str(out), "--truth", str(stations / "truth.json")]) == 0
    table = capsys.readouterr().out
    rows = [r for r in table.splitlines() if r.startswith("| b/scan1.ply -> a/scan1.ply |")
            or r.startswith("| c/scan1.ply -> a/scan1.ply |")]
    assert len(rows) == 2
    assert all(float(r.split("|")[6]) < 0.2 for r in rows), table  # rotation error (deg) against the truth


def test_the_merged_ply_names_its_scans(stations, tmp_path):
    merged = tmp_path / "m.ply"
    main(["register", *(str(stations / n) for n in NAMES), "--until", "coarse", "--keep-unverified",
          "--out", str(tmp_path / "t.json"), "--merged", str(merged)])
    header = merged.read_bytes().split(b"end_header")[0].decode("ascii")
    assert [f'comment scan_id {k + 1} = "{n}"' in header for k, n in enumerate(NAMES)] == [True] * 3


def test_batch_names_a_trees_scans_by_folder(stations, tmp_path):
    job = TreeJob("tree1", tuple(stations / n for n in NAMES[:2]))
    (done,), ran = run_batch([job], Params(), tmp_path, workers=1)
    assert done.status == "ok", done.message
    assert [s.name for s in done.scans] == NAMES[:2]
    d = tmp_path / "tree1"
    assert list(read_transforms(d / "transforms.json").transforms) == NAMES[:2]
    # Its files flat in the tree's folder, named safely, and found sound on a resume (nothing re-run).
    assert sorted(p.name for p in d.iterdir()) == sorted(
        ["result.json", "transforms.json", "picture.png"] + [f"transforms.{x}_scan1.{k}.txt" for x in "ab"
                                                             for k in ("cloudcompare", "pdal")])
    assert run_batch([job], Params(), tmp_path, workers=1)[1] == 0


def test_view_starts_with_scans_of_the_same_file_name(stations):
    proc = subprocess.Popen([sys.executable, "-m", "treereg_cli", "view", *(str(stations / n) for n in NAMES[:2]),
                             "--port", "0"], cwd=REPO, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    try:
        lines = view_started(proc)
    finally:
        proc.terminate()
        proc.wait(timeout=20)
    assert any("treereg view: http://" in ln for ln in lines), lines
    assert not any("error" in ln for ln in lines), lines
