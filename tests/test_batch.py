"""`treereg batch` as a user runs it: a folder of trees or a manifest in, per-tree transforms and a
report out; resumable; a bad tree never stops the others; the same transforms on a Dask cluster."""

from __future__ import annotations

import base64
import csv
import json
import os
import re
import shutil
import zlib

import numpy as np
import pytest

from conftest import ROOT
from treereg_cli.main import main
from treereg_core.batch import runner
from treereg_core.batch.jobs import find_jobs
from treereg_core.batch.picture import png_bytes
from treereg_core.io.transforms import read_transforms
from treereg_core.simulate.cases import benchmark_cases, write_case

N_TREES = 3
#: Batching is tested on the coarse stage alone where the fine one adds only time.
FAST = ["--until", "coarse"]


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    """Three small simulated trees, each in its folder with truth.json."""
    root = tmp_path_factory.mktemp("campaign")
    for k, spec in enumerate(benchmark_cases(N_TREES, seed=2, small=True)):
        write_case(spec.build(), root / f"tree{k + 1}")
    return root


@pytest.fixture(scope="module")
def pooled(campaign, tmp_path_factory):
    """The campaign registered (coarse) by a pool of two processes: every scan a best guess, never
    verified (verification needs the fine stage), so the exit status is 1."""
    out = tmp_path_factory.mktemp("pooled")
    assert main(["batch", str(campaign), "--out", str(out), "--workers", "2", *FAST]) == 1
    assert {r["status"] for r in _rows(out / "summary.csv")} == {"unverified"}
    return out


def _rows(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _transforms(out, tree):
    """Every matrix of a tree's transform file: the verified ones and the unverified best guesses."""
    doc = json.loads((out / tree / "transforms.json").read_text())
    got = {k: np.asarray(v) for k, v in read_transforms(out / tree / "transforms.json").transforms.items()}
    got.update({k: np.asarray(v["matrix"]) for k, v in doc.get("unverified", {}).items()})
    return got


@pytest.mark.slow
def test_batch_registers_every_tree_and_reports(campaign, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["batch", str(campaign), "--out", str(out), "--workers", "2"]) == 0  # coarse and fine
    rows = _rows(out / "summary.csv")
    assert [r["tree"] for r in rows] == ["tree1", "tree2", "tree3"]
    for r in rows:
        assert r["status"] == "ok" and r["verified"] == "3" and r["unverified"] == "0"
        # Against truth.json. The first tree (leaf-on, ground, 0.08 deg steps) keeps 0.35-0.4 deg of yaw
        # from the surfaces: 2.9-3.1 cm over its points out to the ground 10 m away, 7 mm on the tree.
        assert float(r["max_disp_err_m"]) < 0.035 and float(r["max_rot_err_deg"]) < 0.5
        assert (out / r["tree"] / "transforms.json").is_file()
        assert (out / r["tree"] / "transforms.scan2.cloudcompare.txt").is_file()
    scans = _rows(out / "scans.csv")
    assert {s["verdict"] for s in scans} == {"reference", "verified"} and len(scans) == 3 * N_TREES
    page = (out / "report.html").read_text()
    pictures = re.findall(r'src="data:image/png;base64,([^"]+)"', page)
    assert len(pictures) == N_TREES and "http" not in page.split("<body>")[1]  # self-contained
    png = base64.b64decode(pictures[0])
    assert png.startswith(b"\x89PNG") and png[12:16] == b"IHDR"
    assert "3 trees (3 run, 0 already done)" in capsys.readouterr().out


@pytest.mark.slow
def test_a_bad_tree_fails_alone_and_a_rerun_resumes(campaign, tmp_path, capsys):
    src = tmp_path / "trees"
    for t in ("tree1", "tree2"):
        shutil.copytree(campaign / t, src / t)
    (src / "tree2" / "scan2.ply").write_text("this is not a ply file\n")
    out = tmp_path / "out"
    assert main(["batch", str(src), "--out", str(out), "--workers", "1", *FAST]) == 1
    rows = {r["tree"]: r for r in _rows(out / "summary.csv")}
    assert rows["tree1"]["status"] == "unverified" and rows["tree1"]["exit_code"] == "1"  # coarse only: guesses
    assert rows["tree2"]["status"] == "failed" and rows["tree2"]["exit_code"] == "2"
    assert "scan2.ply: not a readable PLY file" in rows["tree2"]["message"]
    assert not (out / "tree2" / "transforms.json").exists()
    capsys.readouterr()

    # Resumed: nothing is run again; a tree whose files changed is; a changed parameter reruns all.
    assert main(["batch", str(src), "--out", str(out), "--workers", "1", *FAST]) == 1
    assert "(0 run, 2 already done)" in capsys.readouterr().out
    (src / "tree2" / "scan2.ply").write_bytes((campaign / "tree2" / "scan2.ply").read_bytes())
    assert main(["batch", str(src), "--out", str(out), "--workers", "1", *FAST]) == 1
    assert "(1 run, 1 already done)" in capsys.readouterr().out
    assert _rows(out / "summary.csv")[1]["status"] == "unverified" and (out / "tree2" / "transforms.json").is_file()
    cfg = tmp_path / "p.json"
    cfg.write_text(json.dumps({"coarse": {"iterations": 500}}))
    assert main(["batch", str(src), "--out", str(out), "--workers", "1", "--config", str(cfg), *FAST]) == 1
    assert "(2 run, 0 already done)" in capsys.readouterr().out
    assert main(["batch", str(src), "--out", str(out), "--workers", "1", "--config", str(cfg), "--redo", *FAST]) == 1
    assert "(2 run, 0 already done)" in capsys.readouterr().out


def test_manifest_with_steps_and_bad_manifests(campaign, tmp_path, capsys):
    man = tmp_path / "campaign.csv"
    def rel(tree: str, scan: str) -> str:  # paths relative to the manifest's folder
        return os.path.relpath(campaign / tree / scan, tmp_path)

    step = json.loads((campaign / "tree1" / "truth.json").read_text())["angular_step_deg"]
    man.write_text("tree,scans,angular_step\n"
                   f"a,{rel('tree1', 'scan1.ply')};{rel('tree1', 'scan2.ply')},{step[0]} {step[1]}\n")
    jobs = find_jobs(man)
    assert jobs[0].name == "a" and jobs[0].angular_step_deg == tuple(step) and len(jobs[0].scans) == 2
    out = tmp_path / "res"
    assert main(["batch", str(man), "--out", str(out), "--workers", "1", *FAST]) == 1  # coarse only: unverified
    assert sorted(_transforms(out, "a")) == ["scan1.ply", "scan2.ply"]
    for text, message in [
        ("tree,files\na,x.ply;y.ply\n", r"campaign\.csv: the first line must name the columns"),
        ("tree,scans\na,x.ply\n", r"campaign\.csv, line 2: tree 'a' needs at least two scan files"),
        ("tree,scans,angular_step\na,x.ply;y.ply,fast\n", r"line 2: angular_step 'fast' is not a number list"),
        ("tree,scans\na,x.ply;y.ply\na,x.ply;y.ply\n", r"line 3: tree 'a' is listed twice"),
    ]:
        man.write_text(text)
        capsys.readouterr()
        assert main(["batch", str(man), "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and re.search(message, err), err


@pytest.mark.slow
def test_dask_cluster_gives_the_same_transforms(campaign, pooled, tmp_path, monkeypatch):
    distributed = pytest.importorskip("distributed")
    # The cluster's processes must import this checkout's treereg, as a real cluster runs the same install.
    monkeypatch.setenv("PYTHONPATH", str(ROOT))
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        on_dask = tmp_path / "dask"
        assert main(["batch", str(campaign), "--out", str(on_dask), "--dask", cluster.scheduler_address, *FAST]) == 1
    for k in range(1, N_TREES + 1):
        a, b = _transforms(pooled, f"tree{k}"), _transforms(on_dask, f"tree{k}")
        assert len(a) == 3 and a.keys() == b.keys() and all(np.array_equal(a[n], b[n]) for n in a)


def test_unreachable_scheduler_is_one_line(campaign, tmp_path, capsys, monkeypatch):
    pytest.importorskip("distributed")
    monkeypatch.setattr(runner, "DASK_CONNECT_TIMEOUT", "2s")
    assert main(["batch", str(campaign), "--out", str(tmp_path / "o"), "--dask", "tcp://127.0.0.1:9", *FAST]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("treereg: error: --dask tcp://127.0.0.1:9: cannot reach the Dask scheduler")


def test_png_is_a_valid_image():
    img = np.zeros((4, 5, 3), dtype=np.uint8)
    img[1, 2] = (255, 0, 0)
    data = png_bytes(img)
    w, h = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    assert (w, h) == (5, 4)
    idat = data[data.index(b"IDAT") + 4:data.index(b"IEND") - 8]
    raw = zlib.decompress(idat)
    assert len(raw) == 4 * (1 + 5 * 3) and raw[1 * 16 + 1 + 2 * 3] == 255
