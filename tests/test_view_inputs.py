"""What `treereg view` opens (issue 32, item 6): a truth.json it cannot use is a warning, never a
reason not to start; `--no-truth` stops looking; and the app reads scans, the demo's too, as
`treereg register` does, so the two give the same transforms on the same files."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

from hostile import _env, view_started
from treereg_cli.main import build_parser
from treereg_cli.view import scans_and_truth
from treereg_core.demo import DEMO_DIR
from treereg_core.errors import ConfigError
from treereg_core.params import Params


def _args(*argv: str):
    return build_parser().parse_args(["view", *argv])


@pytest.fixture()
def beside(tmp_path):
    """Two demo scans in a folder of their own (a truth.json is put beside them by each test)."""
    for name in ("scan1.ply", "scan2.ply"):
        shutil.copy(DEMO_DIR / name, tmp_path / name)
    return tmp_path


def test_the_demo_is_read_as_register_reads_its_files():
    # The steps come from each scan, as `treereg register scan1.ply ...` finds them, not from the
    # simulator's record in truth.json (the app and the command line were 1.2 mm apart so).
    scans, truth = scans_and_truth(_args(), Params())
    recorded = json.loads((DEMO_DIR / "truth.json").read_text())["angular_step_deg"]
    from treereg_cli.common import read_scans

    as_register = read_scans([str(DEMO_DIR / s.name) for s in scans], Params())
    assert [s.angular_step_deg for s in scans] == [s.angular_step_deg for s in as_register]
    assert all("estimated" in s.step.describe() for s in scans), [s.step.describe() for s in scans]
    assert any(s.angular_step_deg != tuple(recorded) for s in scans)  # what the app used before
    assert truth is not None and sorted(truth) == ["scan1.ply", "scan2.ply", "scan3.ply"]


@pytest.mark.parametrize("content, said", [
    ({"poses": {}}, r"missing key 'reference'"),
    ("{not json", r"not valid JSON|JSON"),
])
def test_a_truth_json_it_cannot_read_is_a_warning_and_no_truth_is_used(beside, content, said):
    (beside / "truth.json").write_text(content if isinstance(content, str) else json.dumps(content))
    with pytest.warns(UserWarning, match=said + r".*not read as the truth of these scans"):
        scans, truth = scans_and_truth(_args(str(beside / "scan1.ply"), str(beside / "scan2.ply")), Params())
    assert truth is None and len(scans) == 2


def test_a_truth_json_of_other_scans_is_not_their_truth(beside):
    eye = np.eye(4).tolist()
    (beside / "truth.json").write_text(json.dumps({"reference": "a.ply", "transforms": {"a.ply": eye, "b.ply": eye}}))
    with pytest.warns(UserWarning, match="names none of these scans"):
        _, truth = scans_and_truth(_args(str(beside / "scan1.ply"), str(beside / "scan2.ply")), Params())
    assert truth is None


def test_no_truth_stops_looking_and_a_given_truth_must_be_read(beside):
    shutil.copy(DEMO_DIR / "truth.json", beside / "truth.json")
    files = [str(beside / "scan1.ply"), str(beside / "scan2.ply")]
    assert scans_and_truth(_args(*files), Params())[1] is not None
    assert scans_and_truth(_args(*files, "--no-truth"), Params())[1] is None
    (beside / "other.json").write_text("{}")
    with pytest.raises(ConfigError, match="other.json"):  # asked for by name: an error, not a warning
        scans_and_truth(_args(*files, "--truth", str(beside / "other.json")), Params())
    with pytest.raises(ConfigError, match="--truth and --no-truth"):
        scans_and_truth(_args(*files, "--truth", str(beside / "truth.json"), "--no-truth"), Params())


@pytest.mark.slow
def test_view_starts_beside_a_foreign_truth_json_with_one_warning(beside):
    (beside / "truth.json").write_text(json.dumps({"poses": {}}))
    proc = subprocess.Popen([sys.executable, "-m", "treereg_cli", "view", "scan1.ply", "scan2.ply", "--port", "0"],
                            cwd=beside, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        lines = view_started(proc)
        assert any("treereg view: http://" in ln for ln in lines), lines
        warned = [ln for ln in lines if "truth.json" in ln]
        assert len(warned) == 1 and re.match(r"^treereg: warning: .*truth\.json: missing key 'reference': not read", warned[0]), lines
    finally:
        proc.terminate()
        proc.wait(timeout=30)
