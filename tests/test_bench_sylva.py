"""benchmarks/sylva.py, the Sylva baseline: without Sylva's venv it says so in one line, never a
traceback; treereg's packages never import Sylva (GPL: a benchmark's subprocess only)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from conftest import ROOT

sys.path.insert(0, str(ROOT / "benchmarks"))

import sylva  # noqa: E402


def test_not_installed_is_one_line(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv(sylva.ENV_VAR, str(tmp_path / "no-venv"))
    assert not sylva.sylva_available()
    run = sylva.run_sylva([tmp_path / "a.ply", tmp_path / "b.ply"], tmp_path / "work")
    assert not run.ok and run.error == sylva.NOT_INSTALLED and run.transforms == {}
    assert run.registered == {"a.ply": False, "b.ply": False}
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "sylva.py"), "a.ply"], capture_output=True,
                         text=True, env={"PATH": "/usr/bin:/bin", sylva.ENV_VAR: str(tmp_path / "no-venv")}, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == sylva.NOT_INSTALLED and "Traceback" not in out.stderr


def test_venv_given_as_folder_or_interpreter(tmp_path: Path, monkeypatch) -> None:
    (tmp_path / "venv" / "bin").mkdir(parents=True)
    monkeypatch.setenv(sylva.ENV_VAR, str(tmp_path / "venv"))
    assert sylva.sylva_python() == tmp_path / "venv" / "bin" / "python"
    monkeypatch.setenv(sylva.ENV_VAR, str(tmp_path / "venv" / "bin" / "python3"))
    assert sylva.sylva_python() == tmp_path / "venv" / "bin" / "python3"


def test_double_ply_detected(tmp_path: Path) -> None:
    from treereg_core.io.scans import write_scan

    pts = np.random.default_rng(0).normal(size=(100, 3)) * 5
    write_scan(tmp_path / "d.ply", pts)
    write_scan(tmp_path / "f.ply", pts, dtype="float32")
    assert sylva._ply_is_double(tmp_path / "d.ply") and not sylva._ply_is_double(tmp_path / "f.ply")


def test_run_measured_reports_the_child(tmp_path: Path) -> None:
    m = sylva.run_measured([sys.executable, "-c", "b = bytearray(200 * 2**20); b[::4096] = b'x' * len(b[::4096]); print('done')"],
                           tmp_path / "log.txt")
    assert m.returncode == 0 and "done" in m.log and m.peak_mb > 150 and m.seconds > 0


def test_core_never_imports_sylva() -> None:
    for pkg in ("treereg_core", "treereg_viewer", "treereg_cli"):
        for path in (ROOT / pkg).rglob("*.py"):
            text = path.read_text()
            assert "import sylva" not in text and "from sylva" not in text, path
