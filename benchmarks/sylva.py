"""Sylva (PyPI `sylva-rs`), the peer tool, as a black-box baseline for the benchmarks only.

Sylva is GPL: it is never a dependency of treereg, never imported here and none of its code is
read or copied. It is installed in a separate venv and run as a subprocess through its documented
command line (`sylva coreg --help`)::

    python3 -m venv /work/sylva-venv && /work/sylva-venv/bin/pip install sylva-rs

`TREEREG_SYLVA_PYTHON` names that venv (its folder) or its interpreter (`.../bin/python`); default
/work/sylva-venv. The command run for stations a.ply, b.ply, ... is

    <venv>/bin/sylva --no-progress coreg a.ply b.ply ... --reference 0 -o <workdir>/sylva_out

which writes `<out>/transforms.json` ("reference": the index of the reference scan; "scans": one
entry per input in input order, with "index", "name", "registered" and "world_from_scan", a
row-major 4x4 mapping that scan's points into the world frame, which is the reference scan's
frame; "levelling" beside it, the identity on scans without a recorded attitude) plus one
`<name>.dat` per scan (the same 4x4, four text rows) and report.txt. `run_sylva` returns each
station's T_first_station = inv(W_first) @ W_station (the identity's product when the first input
is the reference, as here): the convention of treereg's truth.json and transforms.json
(`T_ref_scan`, scan1 = the first station).

Sylva 0.3.0 panics ("index out of bounds" in its ground refit) on double-precision PLY files,
which treereg writes by default; a float32 PLY of the same points (about a micrometre of rounding
at 10 m) or a LAZ file reads fine. `run_sylva` hands such a PLY over as a float32 copy in the work
folder, so a benchmark is best written as float32 PLY in the first place (both tools then read the
same files).

`run_measured` (also used for `treereg register` by bench_survey) runs a command and reports its
wall time and the peak resident memory of that one child and its descendants (`os.wait4` in a
small wrapper interpreter, so the benchmark's own memory is never counted).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

ENV_VAR = "TREEREG_SYLVA_PYTHON"
DEFAULT_VENV = Path("/work/sylva-venv")
NOT_INSTALLED = "Sylva not installed: pip install sylva-rs in a separate venv"


@dataclass(frozen=True)
class Measured:
    """A finished child process: exit status, wall time, peak memory, and its output (the log)."""

    returncode: int
    seconds: float
    peak_mb: float
    log: str
    timed_out: bool = False


@dataclass(frozen=True)
class SylvaRun:
    """One Sylva coregistration of a set of stations.

    transforms: {station file name: T_first_station} for every station Sylva registered (the
        first station is the identity); a station it did not register is absent.
    registered: {station file name: whether Sylva registered it}, every input in order.
    error: one line when Sylva failed or left stations out, else None.
    """

    ok: bool
    transforms: dict[str, np.ndarray]
    registered: dict[str, bool]
    seconds: float
    peak_mb: float
    error: str | None
    command: tuple[str, ...] = ()
    version: str = ""
    log_path: Path | None = None
    converted: tuple[str, ...] = field(default=())


def sylva_python() -> Path:
    """The interpreter of Sylva's venv (`TREEREG_SYLVA_PYTHON`: the venv's folder or its python)."""
    given = os.environ.get(ENV_VAR, "").strip()
    p = Path(given) if given else DEFAULT_VENV
    return p / "bin" / "python" if p.is_dir() else p


def sylva_command() -> list[str]:
    """The command that starts Sylva's CLI: the venv's `sylva` script beside its interpreter, else
    the interpreter calling the console script's entry point (`sylva.cli:main`, from its metadata)."""
    py = sylva_python()
    script = py.parent / "sylva"
    if script.is_file():
        return [str(script)]
    return [str(py), "-c", "import sys; from sylva.cli import main; sys.argv[0] = 'sylva'; sys.exit(main())"]


@lru_cache(maxsize=None)
def _version(cmd: tuple[str, ...]) -> str | None:
    try:
        r = subprocess.run([*cmd, "--version"], capture_output=True, text=True, timeout=120)
    except (OSError, subprocess.SubprocessError):
        return None
    if r.returncode != 0:
        return None
    return (r.stdout.strip() or r.stderr.strip()) or "sylva"


def sylva_version() -> str | None:
    """`sylva --version` of the venv's Sylva ("sylva 0.3.0"), or None when it is not installed."""
    py = sylva_python()
    if not py.exists():
        return None
    return _version(tuple(sylva_command()))


def sylva_available() -> bool:
    """Whether Sylva's venv is there and its CLI answers `--version`."""
    return sylva_version() is not None


# Started by a fresh, small interpreter: Linux counts in a child's ru_maxrss the resident set of the
# process it was forked from (exec records the old memory's high-water mark), so a child started
# straight from a benchmark that has just simulated a survey would report the benchmark's peak.
_WRAPPER = (
    "import os, subprocess, sys\n"
    "p = subprocess.Popen(sys.argv[2:])\n"
    "_, status, usage = os.wait4(p.pid, 0)\n"
    "p.returncode = code = os.waitstatus_to_exitcode(status)\n"
    "open(sys.argv[1], 'w').write(str(usage.ru_maxrss))\n"
    "sys.exit(code if code >= 0 else 128 - code)\n"
)


def run_measured(cmd: list[str], log_path: Path, cwd: Path | None = None, timeout_s: float | None = None,
                 env: dict[str, str] | None = None) -> Measured:
    """Run `cmd` with its stdout and stderr into `log_path`; wall time and the child's peak RSS.

    The peak is `ru_maxrss` of `os.wait4` on that child, taken by a small wrapper interpreter that
    starts it (see `_WRAPPER`): the largest resident set of the child or of any descendant it
    waited for, so several runs in one benchmark do not mix. On a timeout the whole process group
    is killed.
    """
    log_path.parent.mkdir(parents=True, exist_ok=True)
    rss_file = log_path.with_name(log_path.name + ".maxrss")
    if rss_file.exists():
        rss_file.unlink()
    timed_out = False
    with open(log_path, "wb") as log:
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-c", _WRAPPER, str(rss_file), *cmd], stdout=log,
                                stderr=subprocess.STDOUT, cwd=cwd, env=env, start_new_session=True)
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            timed_out = True
            os.killpg(proc.pid, 9)
            proc.wait()
        seconds = time.perf_counter() - t0
    try:
        peak_mb = int(rss_file.read_text()) / 1024.0
    except (OSError, ValueError):
        peak_mb = float("nan")  # killed before its child ended
    text = log_path.read_text(errors="replace")
    return Measured(proc.returncode, seconds, peak_mb, text, timed_out)


def _ply_is_double(path: Path) -> bool:
    """Whether a PLY's vertex coordinates are doubles (its ASCII header, nothing else, is read)."""
    if path.suffix.lower() != ".ply":
        return False
    with open(path, "rb") as fh:
        head = fh.read(4096)
    header = head.split(b"end_header", 1)[0].decode("ascii", errors="replace")
    return any(line.split()[:3] in (["property", "double", "x"], ["property", "float64", "x"])
               for line in header.splitlines())


def _sylva_inputs(paths: list[Path], workdir: Path) -> tuple[list[Path], tuple[str, ...]]:
    """The files to hand Sylva: double PLYs as float32 copies in `workdir` (see the module's doc)."""
    from treereg_core.io.scans import read_points, write_scan

    out, converted = [], []
    for k, p in enumerate(paths):
        if _ply_is_double(p):
            dst = workdir / "sylva_in" / f"{k:03d}" / p.name  # one folder each: same names stay apart
            if not dst.is_file():
                dst.parent.mkdir(parents=True, exist_ok=True)
                write_scan(dst, read_points(p, check_units=False), dtype="float32")
            out.append(dst)
            converted.append(p.name)
        else:
            out.append(p)
    return out, tuple(converted)


def _last_line(text: str) -> str:
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    panics = [ln for ln in lines if "panicked at" in ln or ln.startswith(("index out of", "Error", "error"))]
    return (panics[-1] if panics else lines[-1] if lines else "no output")[:300]


def run_sylva(paths: list[Path], workdir: Path, timeout_s: float | None = None,
              extra_args: tuple[str, ...] = ()) -> SylvaRun:
    """Coregister the station files `paths` (the first is the reference) with Sylva's defaults.

    Never raises for Sylva's own failures (not installed, a crash, a timeout, stations left out):
    they come back as `ok=False` with a one-line `error`.
    """
    paths = [Path(p) for p in paths]
    names = [p.name for p in paths]
    version = sylva_version()
    if version is None:
        return SylvaRun(False, {}, {n: False for n in names}, 0.0, 0.0, NOT_INSTALLED)
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    inputs, converted = _sylva_inputs(paths, workdir)
    out = workdir / "sylva_out"
    result = out / "transforms.json"
    if result.exists():
        result.unlink()  # never read a previous run's result
    cmd = [*sylva_command(), "--no-progress", "coreg", *map(str, inputs), "--reference", "0",
           "-o", str(out), *extra_args]
    m = run_measured(cmd, workdir / "sylva.log", cwd=workdir, timeout_s=timeout_s)

    def failed(msg: str) -> SylvaRun:
        return SylvaRun(False, {}, {n: False for n in names}, m.seconds, m.peak_mb, msg, tuple(cmd),
                        version, workdir / "sylva.log", converted)

    if m.timed_out:
        return failed(f"Sylva stopped after {timeout_s:.0f} s (timeout)")
    if m.returncode != 0 or not result.is_file():
        return failed(f"Sylva exited with {m.returncode}: {_last_line(m.log)}")
    try:
        data = json.loads(result.read_text())
        entries = sorted(data["scans"], key=lambda s: int(s["index"]))
        if [int(s["index"]) for s in entries] != list(range(len(paths))):
            return failed(f"Sylva's transforms.json lists scans {[s['index'] for s in entries]}, "
                          f"not the {len(paths)} inputs")
        worlds = [np.asarray(s["world_from_scan"], dtype=np.float64) if s.get("registered") else None
                  for s in entries]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        return failed(f"Sylva's transforms.json could not be read: {exc}")
    registered = {n: w is not None for n, w in zip(names, worlds)}
    W0 = worlds[0]
    if W0 is None:
        return SylvaRun(False, {}, registered, m.seconds, m.peak_mb, "Sylva did not register the first station",
                        tuple(cmd), version, workdir / "sylva.log", converted)
    W0_inv = np.linalg.inv(W0)
    transforms = {n: W0_inv @ w for n, w in zip(names, worlds) if w is not None}
    missing = [n for n, ok in registered.items() if not ok]
    error = f"Sylva left {len(missing)} of {len(names)} stations unregistered: {', '.join(missing)}" if missing else None
    return SylvaRun(not missing, transforms, registered, m.seconds, m.peak_mb, error, tuple(cmd), version,
                    workdir / "sylva.log", converted)


if __name__ == "__main__":  # python benchmarks/sylva.py a.ply b.ply ... : Sylva's T_first_station
    if not sylva_available():
        print(NOT_INSTALLED)
        sys.exit(0)
    import tempfile

    with tempfile.TemporaryDirectory(prefix="sylva_") as tmp:
        run = run_sylva([Path(a) for a in sys.argv[1:]], Path(tmp))
    print(f"{run.version}: {'ok' if run.ok else run.error}; {run.seconds:.1f} s, {run.peak_mb:.0f} MB")
    for name, T in run.transforms.items():
        print(name)
        print(np.array2string(T, precision=6, suppress_small=True))
