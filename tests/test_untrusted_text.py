"""Text from outside in what treereg prints and writes (issue 29): scan file names and tree folder
names forge no line of output and send no control to the terminal (`text.shown`), start no formula
in the batch CSVs and no element in its report; a re-run's exports leave none of an earlier run's
matrices beside a result that refuses their scan; a full disk under stdout and a manifest's
impossible tree names are one line each."""

from __future__ import annotations

import csv
import os
import re
import shutil
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path

import pytest

from hostile import REPO, _env, cli, one_line
from treereg_cli.main import main
from treereg_core.batch.report import csv_cell
from treereg_core.io import atomic
from treereg_core.io.transforms import read_transforms
from treereg_core.simulate.cases import benchmark_cases, write_case

#: A newline that would print a line of its own ("scan9.ply: verified ..."), and escape sequences
#: that would set the terminal's title and clear its screen.
FORGED = "x\nscan9.ply: verified.ply"
TITLE = "\x1b]0;pwned\x07\x1b[2J.ply"
#: How each is shown: one line, the controls as escapes.
FORGED_SHOWN = "x\\nscan9.ply: verified.ply"
TITLE_SHOWN = "\\x1b]0;pwned\\x07\\x1b[2J.ply"


@pytest.fixture(scope="module")
def case_dir(tmp_path_factory):
    case = benchmark_cases(3, seed=0, small=True)[1].build()
    d = tmp_path_factory.mktemp("case")
    write_case(case, d)
    return d


def _no_control(text: str) -> None:
    assert not re.search("[\x00-\x08\x0b\x0c\x0e-\x1f\x7f]", text), repr(text)  # \t \n \r are ours


# ---- names on the terminal ------------------------------------------------------------------------
@pytest.mark.slow
def test_hostile_scan_names_forge_no_line_and_reach_the_terminal_escaped(case_dir, tmp_path, capsys):
    d = tmp_path / "scans"
    d.mkdir()
    shutil.copy(case_dir / "scan1.ply", d / "scan1.ply")
    shutil.copy(case_dir / "scan2.ply", d / FORGED)
    shutil.copy(case_dir / "scan3.ply", d / TITLE)
    out = tmp_path / "res" / "t.json"
    capsys.readouterr()
    rc = main(["register", str(d / "scan1.ply"), str(d / FORGED), str(d / TITLE), "--out", str(out), "--exports",
               "--details"])
    got = capsys.readouterr()
    assert rc in (0, 1), got.err
    _no_control(got.out + got.err)
    lines = (got.out + got.err).replace("\r", "\n").splitlines()
    assert not [ln for ln in lines if ln.strip().startswith("scan9.ply")], "a line forged by a file name"
    # Each name on its own verdict line, escaped, and the pair lines name them so.
    for name in (FORGED_SHOWN, TITLE_SHOWN):
        assert re.search(rf"^  {re.escape(name)} +\S", got.out, re.M), got.out
    assert f"\n{TITLE_SHOWN} -> {FORGED_SHOWN}\n" in got.out
    # ... and the summary's rows too (a row per scan, starting with its name).
    assert len(re.findall(rf"^  {re.escape(FORGED_SHOWN)} +(verified|unverified|failed) ", got.out, re.M)) == 1, got.out
    # transforms.json keys its scans by the names printed; the files named after them hold no control.
    tf = read_transforms(out)
    keys = [*tf.transforms, *tf.extra.get("unverified", {}), *tf.extra.get("unregistered", {})]
    assert sorted(keys) == sorted(["scan1.ply", FORGED_SHOWN, TITLE_SHOWN])
    assert set(tf.extra["sources"]) == set(keys)
    for p in out.parent.iterdir():
        _no_control(p.name)


def test_a_bad_scan_with_a_hostile_name_is_one_escaped_line(case_dir, tmp_path, capsys):
    bad = tmp_path / FORGED
    bad.write_bytes(b"ply\nformat nonsense\n")
    rc, err = cli(capsys, "register", case_dir / "scan1.ply", bad, "--out", tmp_path / "t.json")
    assert rc == 2 and not (tmp_path / "t.json").exists()
    _no_control(err)
    one_line(err, rf"^treereg: error: .*{re.escape(FORGED_SHOWN)}: ")


# ---- the batch's CSVs and report -----------------------------------------------------------------
IMG = "<img src=x onerror=alert(1)>"


class _Tags(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.tags: list[tuple[str, dict]] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))


def test_batch_names_start_no_formula_and_no_element(case_dir, tmp_path, capsys):
    root = tmp_path / "campaign"
    scans = {"=1+2": ("-2+3.ply", "@SUM(A1).ply"), "\tTAB": ("scan1.ply", "scan2.ply"),
             IMG: (f"{IMG}.ply", "+1+cmd.ply")}
    for tree, (ref, tgt) in scans.items():
        (root / tree).mkdir(parents=True)
        shutil.copy(case_dir / "scan1.ply", root / tree / ref)
        shutil.copy(case_dir / "scan2.ply", root / tree / tgt)
    out = tmp_path / "out"
    capsys.readouterr()
    assert main(["batch", str(root), "--out", str(out), "--workers", "1", "--until", "coarse"]) == 1  # unverified
    got = capsys.readouterr()
    _no_control(got.out + got.err)
    assert "\tTAB" not in got.err and re.search(r"^  \\tTAB: unverified: ", got.err, re.M), got.err  # shown
    with open(out / "summary.csv", newline="") as fh:
        trees = list(csv.DictReader(fh))
    with open(out / "scans.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert sorted(r["tree"] for r in trees) == sorted(["'=1+2", "'\tTAB", IMG])
    assert sorted(r["scan"] for r in rows) == sorted(["'-2+3.ply", "'@SUM(A1).ply", "scan1.ply", "scan2.ply",
                                                      f"{IMG}.ply", "'+1+cmd.ply"])
    for r in trees + rows:  # no cell, the messages naming the scans included, opens a formula
        assert not [v for v in r.values() if v[:1] in ("=", "+", "-", "@", "\t", "\r")], r
    page = (out / "report.html").read_text()
    parser = _Tags()
    parser.feed(page)
    assert [a["src"][:22] for t, a in parser.tags if t == "img"] == ["data:image/png;base64,"] * 3  # the pictures only
    assert not [a for _, a in parser.tags if "onerror" in a]
    assert page.count("&lt;img src=x onerror=alert(1)&gt;") >= 2  # the tree and its scan, shown as text


def test_a_csv_cell_is_prefixed_where_a_spreadsheet_would_start_a_formula():
    for text in ("=1+2", "+A1", "-2+3", "@SUM(A1)", "\tx", "\rx", "-", "=HYPERLINK(\"x\")"):
        assert csv_cell(text) == "'" + text
    for text in ("tree1", "-0.5", "12", "1e-3", "", "a=b"):
        assert csv_cell(text) == text


# ---- stale exports --------------------------------------------------------------------------------
def test_a_rerun_removes_the_exports_of_a_scan_it_no_longer_places(case_dir, tmp_path, capsys):
    res = tmp_path / "res"
    out = res / "t.json"
    s1, s2 = str(case_dir / "scan1.ply"), str(case_dir / "scan2.ply")
    assert main(["register", s1, s2, "--out", str(out), "--exports"]) == 0  # scan2 verified
    stale = [res / "t.scan2.cloudcompare.txt", res / "t.scan2.pdal.txt"]
    assert all(p.is_file() for p in stale)
    # What is not ours stays: another name, another output's matrices, a link the user made.
    theirs = [res / "t.scan9.pdal.txt", res / "u.scan2.pdal.txt", res / "notes.txt"]
    for p in theirs:
        p.write_text("not treereg's\n")
    (tmp_path / "elsewhere.txt").write_text("linked\n")
    (res / "t.scan3.pdal.txt").symlink_to(tmp_path / "elsewhere.txt")
    capsys.readouterr()
    # The same scans stopped before verification: scan2 is now a best guess, not placed.
    assert main(["register", s1, s2, "--out", str(out), "--exports", "--until", "coarse"]) == 1
    printed = capsys.readouterr().out
    tf = read_transforms(out)
    assert list(tf.transforms) == ["scan1.ply"] and "scan2.ply" in tf.extra["unverified"]
    assert not any(p.exists() for p in stale)
    assert [ln for ln in printed.splitlines() if ln.startswith("removed ")] == [
        f"removed {stale[0]}, {stale[1]}: an earlier run's matrices of scans this run does not place"]
    assert all(p.read_text() == "not treereg's\n" for p in theirs)
    assert (res / "t.scan3.pdal.txt").is_symlink() and (tmp_path / "elsewhere.txt").read_text() == "linked\n"
    assert sorted(p.name for p in res.iterdir()) == sorted(
        ["t.json", "t.registered.e57", "t.scan1.cloudcompare.txt", "t.scan1.pdal.txt", "t.scan3.pdal.txt",
         *(p.name for p in theirs)])


@pytest.mark.slow
def test_a_batch_rerun_removes_the_matrices_its_tree_no_longer_has(case_dir, tmp_path, capsys):
    tree, out = tmp_path / "camp" / "tree1", tmp_path / "out"
    tree.mkdir(parents=True)
    for name in ("scan1.ply", "scan2.ply", "scan3.ply"):
        shutil.copy(case_dir / name, tree / name)
    run = ["batch", str(tmp_path / "camp"), "--out", str(out), "--workers", "1"]
    assert main(run) == 0
    gone = [out / "tree1" / "transforms.scan3.cloudcompare.txt", out / "tree1" / "transforms.scan3.pdal.txt"]
    assert all(p.is_file() for p in gone)
    (tree / "scan3.ply").unlink()
    assert main([*run, "--redo"]) == 0  # as good a result: it replaces the earlier one's files
    assert not any(p.exists() for p in gone) and (out / "tree1" / "transforms.scan2.pdal.txt").is_file()


def test_a_removal_waits_for_its_batch_and_a_failed_batch_removes_nothing(tmp_path):
    stale = tmp_path / "t.scan2.pdal.txt"
    stale.write_text("old\n")
    with pytest.raises(RuntimeError):
        with atomic.batch():
            atomic.write_text_atomic(tmp_path / "t.json", "{}")
            assert atomic.remove_atomic(stale) == stale and stale.exists()  # not before the renames
            raise RuntimeError("a later write failed")
    assert stale.read_text() == "old\n" and not (tmp_path / "t.json").exists()
    with atomic.batch():
        atomic.write_text_atomic(tmp_path / "t.json", "{}")
        atomic.remove_atomic(stale)
    assert not stale.exists() and (tmp_path / "t.json").read_text() == "{}"


# ---- crashes ----------------------------------------------------------------------------------------
@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
def test_stdout_on_a_full_disk_is_one_line_and_exit_2():
    with open("/dev/full", "w") as full:
        p = subprocess.run([sys.executable, "-m", "treereg_cli", "params", "--explain"], cwd=REPO, env=_env(),
                           stdout=full, stderr=subprocess.PIPE, text=True, timeout=60)
    assert p.returncode == 2, p.stderr
    assert "Exception ignored" not in p.stderr
    one_line(p.stderr, r"^treereg: error: cannot write the output \(No space left on device\); "
                       r"what was printed is incomplete$")


@pytest.mark.parametrize("tree, why", [
    ("t" * 300, r"the tree name 't{40}'\.\.\. is 300 bytes long; it names the tree's folder, which can have at most 255"),
    ("a\x00b", r"the tree name 'a\\x00b' cannot name a folder"),
])
def test_a_manifests_impossible_tree_name_is_one_line_naming_the_row(case_dir, tmp_path, capsys, tree, why):
    manifest = tmp_path / "trees.csv"
    manifest.write_text(f"tree,scans\nok,{case_dir}/scan1.ply;{case_dir}/scan2.ply\n"
                        f"{tree},{case_dir}/scan1.ply;{case_dir}/scan2.ply\n")
    rc, err = cli(capsys, "batch", manifest, "--out", tmp_path / "out")
    assert rc == 2 and not (tmp_path / "out").exists()
    one_line(err, rf"^treereg: error: {re.escape(str(manifest))}, line 3: {why}$")
