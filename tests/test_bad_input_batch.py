"""Hostile input, round 2 (issue 17), `treereg batch`: a failed re-run never deletes the previous
verified result, the results folder is never inside the input nor one of its files, resume looks at
the scans' content and re-checks the results it trusts, and SIGTERM stops the workers."""

from __future__ import annotations

import csv
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hostile import REPO, _env, changed, cli, ctrl_c_default, fingerprint, one_line, sandbox  # noqa: F401
from treereg_cli.main import main
from treereg_core.demo import DEMO_DIR
from treereg_core.io.transforms import read_transforms

DEMO = ("scan1.ply", "scan2.ply", "scan3.ply", "truth.json")


def _campaign(root: Path, trees: tuple[str, ...] = ("tree1",)) -> Path:
    """A campaign folder: one tree folder per name, each holding the demo scans."""
    for tree in trees:
        (root / tree).mkdir(parents=True)
        for name in DEMO:
            shutil.copy(DEMO_DIR / name, root / tree / name)
    return root


@pytest.fixture(scope="module")
def verified(tmp_path_factory):
    """A campaign of one tree registered and verified (the fine stage): `work/` to break and run again
    (see `rerun`), `pristine/` a copy of both folders as they were."""
    root = tmp_path_factory.mktemp("verified")
    camp = _campaign(root / "work" / "camp")
    assert main(["batch", str(camp), "--out", str(root / "work" / "res"), "--workers", "1"]) == 0
    shutil.copytree(root / "work", root / "pristine")
    return root


@pytest.fixture()
def rerun(verified):
    """The verified campaign and its results as they were, at the paths they were registered from
    (the resume fingerprint has the scans' paths)."""
    work = verified / "work"
    shutil.rmtree(work)
    shutil.copytree(verified / "pristine", work)
    return work / "camp", work / "res"


def _batch(capsys, camp: Path, res: Path, *more: str) -> tuple[int, str, str]:
    capsys.readouterr()
    rc = main(["batch", str(camp), "--out", str(res), "--workers", "1", *more])
    got = capsys.readouterr()
    return rc, got.out, got.err.replace("\r", "\n")


# ---- a failed re-run keeps the previous verified result --------------------------------------------------
def test_a_failed_rerun_keeps_the_previous_verified_result(rerun, capsys):
    camp, res = rerun
    (camp / "tree1" / "scan2.ply").write_text("this is not a ply file\n")
    before = fingerprint(res / "tree1")
    kept = (r"^  tree1: failed: .*scan2\.ply: [^;]*; the previous verified result of "
            r"\d{4}-\d\d-\d\d \d\d:\d\d is kept \(this run replaced none of its files\)$")
    for _ in range(2):  # the run that fails, then the resumed one: both say so
        rc, _, err = _batch(capsys, camp, res)
        assert rc == 1
        assert any(re.match(kept, ln) for ln in err.splitlines()), err
        # transforms.json, the matrices and the picture are the previous ones; only result.json says what happened
        assert changed(before, fingerprint(res / "tree1"), allowed=("result.json",)) == []
        row = list(csv.DictReader(open(res / "summary.csv", newline="")))[0]
        assert row["status"] == "failed" and re.match(kept.removeprefix(r"^  tree1: failed: "), row["message"])
    assert read_transforms(res / "tree1" / "transforms.json").names == ["scan1.ply", "scan2.ply", "scan3.ply"]


# ---- the results folder and the input ------------------------------------------------------------------
@pytest.mark.parametrize("where", [".", "results", "tree1"])
def test_results_in_or_at_the_input_folder_are_refused(sandbox, capsys, where):
    camp = sandbox / "camp"
    (camp / "tree1").mkdir(parents=True)
    for name in DEMO:
        shutil.copy(sandbox / "scans" / name, camp / "tree1" / name)
    before = fingerprint(sandbox)
    rc, err = cli(capsys, "batch", camp, "--out", camp / where, "--workers", "1")
    assert rc == 2
    one_line(err, r"^treereg: error: .*camp.*: is (the input folder|inside the input folder .*camp); the results "
                  r"would be read as scans by the next run: choose a folder outside it \(e\.g\. .*camp_results\)$")
    assert changed(before, fingerprint(sandbox)) == []


def test_a_results_folder_is_never_read_as_scans(verified, capsys, tmp_path):
    res = verified / "pristine" / "res"
    before = fingerprint(res)
    rc, err = cli(capsys, "batch", res, "--out", tmp_path / "again", "--workers", "1")
    assert rc == 2  # its matrix files (.txt) and summary CSVs are not scans
    one_line(err, r"^treereg: error: .*res: no tree folders with scan files found")
    assert changed(before, fingerprint(res)) == []


def test_a_manifest_that_is_an_output_is_refused(sandbox, capsys):
    s = sandbox / "scans"
    man = s / "summary.csv"  # where the results' summary.csv would go with --out beside it
    man.write_text("tree,scans\na,scan1.ply;scan2.ply\n")
    before = fingerprint(sandbox)
    rc, err = cli(capsys, "batch", man, "--out", s, "--workers", "1")
    assert rc == 2
    one_line(err, r"^treereg: error: .*scans/summary\.csv: .*summary\.csv is the input .*summary\.csv; treereg never "
                  r"replaces an input: choose another --out folder$")
    assert changed(before, fingerprint(sandbox)) == []


# ---- resume ------------------------------------------------------------------------------------------
def test_resume_sees_a_scan_replaced_with_the_same_size_and_time(rerun, capsys):
    camp, res = rerun
    scan = camp / "tree1" / "scan3.ply"
    st = scan.stat()
    data = bytearray(scan.read_bytes())  # the last two points swapped: same size, same cloud, other bytes
    data[-48:] = data[-24:] + data[-48:-24]
    scan.write_bytes(bytes(data))
    os.utime(scan, ns=(st.st_atime_ns, st.st_mtime_ns))  # as `cp -p` leaves it
    rc, out, _ = _batch(capsys, camp, res)
    assert rc == 0 and "(1 run, 0 already done)" in out


@pytest.mark.parametrize("damage, why", [
    ("delete transforms.json", r"its transforms\.json is missing"),
    ("garbage transforms.json", r"its transforms\.json does not read \(not valid JSON.*\)"),
    ("garbage transforms.scan2.pdal.txt", r"its transforms\.scan2\.pdal\.txt does not read \(PDAL matrix: .*\)"),
])
@pytest.mark.slow
def test_resume_reruns_a_result_that_no_longer_reads(rerun, capsys, damage, why):
    camp, res = rerun
    action, name = damage.split()
    if action == "delete":
        (res / "tree1" / name).unlink()
    else:
        (res / "tree1" / name).write_text("1 2 3\n")
    rc, out, err = _batch(capsys, camp, res)
    assert rc == 0 and "(1 run, 0 already done)" in out, out
    assert any(re.match(rf"^  tree1: {why}; registering it again$", ln) for ln in err.splitlines()), err
    assert read_transforms(res / "tree1" / "transforms.json").names == ["scan1.ply", "scan2.ply", "scan3.ply"]


# ---- SIGTERM (and Ctrl-C) stop the workers ----------------------------------------------------------------
def _descendants(pid: int) -> list[int]:
    """Every live process below `pid` (from /proc)."""
    parent: dict[int, int] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                fields = Path(f"/proc/{d}/stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if fields[0] != "Z":
                parent[int(d)] = int(fields[1])
    found, frontier = [], [pid]
    while frontier:
        kids = [p for p, pp in parent.items() if pp in frontier]
        found += kids
        frontier = kids
    return found


def _cmdline(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return b""


def _alive(pids: list[int]) -> list[int]:
    live = []
    for p in pids:
        try:
            if Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z":
                live.append(p)
        except OSError:
            pass
    return live


@pytest.mark.slow
@pytest.mark.parametrize("how", ["SIGTERM to batch", "Ctrl-C to its process group"])
def test_sigterm_stops_batch_and_its_workers(tmp_path, how):
    camp = _campaign(tmp_path / "camp", ("tree1", "tree2"))
    res = tmp_path / "res"
    proc = subprocess.Popen([sys.executable, "-m", "treereg_cli", "batch", camp, "--out", res, "--workers", "2"],
                            cwd=REPO, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True,
                            preexec_fn=ctrl_c_default)
    workers: list[int] = []
    everyone: list[int] = []
    try:
        deadline = time.monotonic() + 60
        while len(workers) < 2 and time.monotonic() < deadline:  # both workers started (and the resource tracker)
            time.sleep(0.2)
            workers = [p for p in _descendants(proc.pid) if b"spawn_main" in _cmdline(p)]
        assert len(workers) >= 2, "the workers never started"
        time.sleep(0.5)  # starting (importing), or at work on their trees
        everyone = _descendants(proc.pid)
        if how.startswith("SIGTERM"):
            proc.send_signal(signal.SIGTERM)
        else:
            os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=60)
        err = "\n".join(ln for ln in err.decode().splitlines() if not ln.startswith("2 trees from"))  # the header
        time.sleep(0.5)
        assert _alive(everyone) == [], "worker processes left running"
        if how.startswith("SIGTERM"):
            assert proc.returncode == 143, err
            one_line(err, r"^treereg: terminated \(SIGTERM\); no file was left half-written or replaced by a partial result$")
        else:
            assert proc.returncode == 130, err
            one_line(err, r"^treereg: interrupted \(Ctrl-C\); no file was left half-written or replaced by a partial result$")
        assert not [p for p in res.rglob("*") if p.name.endswith(".tmp")]  # nothing half-written
    finally:
        if proc.poll() is None:
            proc.kill()
        for p in _alive(everyone + workers):  # the pre-change code orphans them: end them here
            os.kill(p, signal.SIGKILL)
