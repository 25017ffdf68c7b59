"""The trees of a campaign: a folder of tree folders, or a CSV manifest.

A folder: every sub-folder holding scan files is a tree, named by the folder; its scans are taken
in the order its truth.json lists them (simulated cases) or else sorted by name, the first being
the reference. A manifest (`.csv`): one row per tree with the columns

    tree, scans[, angular_step][, target][, initial]

`scans` lists the files separated by ';' (paths relative to the manifest's folder, reference
first); `angular_step` is "H" or "H V" in degrees; `target` is "X Y", the target tree's stem in the
reference scan's frame (metres); `initial` gives scans start poses, as `register --initial` does:
"SCAN=FILE" entries separated by ';' (the scan's name as transforms.json names it, the file relative
to the manifest's folder: 4 rows of 4 numbers or a transforms.json, `io.start`). Problems with the manifest itself raise `ConfigError` naming the
file and the line; a tree whose files are missing is still a job, and fails on its own.
"""

from __future__ import annotations

import csv
import os
import re
from dataclasses import dataclass
from pathlib import Path

from ..errors import ConfigError
from ..io.cases import TRUTH_NAME
from ..io.scans import READ_EXTENSIONS, extension
from ..io.transforms import read_transforms


@dataclass(frozen=True)
class TreeJob:
    """One tree to register.

    name : the tree's name (its output folder).
    scans : scan files, reference first.
    angular_step_deg : (phi, varphi) for this tree's scans, or None (the parameters', else estimated).
    target_xy_m : the target stem's position in the reference frame, or None.
    truth : a truth.json with the true transforms (simulated cases), or None.
    starts : (scan name, start file) per scan the user gave a start pose (`register --initial`).
    """

    name: str
    scans: tuple[Path, ...]
    angular_step_deg: tuple[float, float] | None = None
    target_xy_m: tuple[float, float] | None = None
    truth: Path | None = None
    starts: tuple[tuple[str, Path], ...] = ()


#: Names of what `treereg batch` writes that a scan reader would take: the matrix files in each tree's
#: folder (`io.transforms.export_names`) and the summary beside them. Never read back as scans.
MATRIX_SUFFIXES = (".cloudcompare.txt", ".pdal.txt")
SUMMARY_NAMES = ("summary.csv", "scans.csv", "report.html")

#: The longest file or folder name (bytes) nearly every file system takes (NAME_MAX): a tree's folder.
MAX_NAME_BYTES = 255
#: Characters no tree folder is named with: NUL cannot be in a path at all, the other controls would
#: break the lines that name the tree.
_CONTROL = re.compile("[\x00-\x1f\x7f]")


def find_jobs(source: str | Path) -> list[TreeJob]:
    """The trees of a folder of tree folders or of a CSV manifest."""
    src = Path(source)
    if not src.exists():
        raise ConfigError(f"{src}: no such folder or manifest")
    if src.is_file():
        if src.suffix.lower() != ".csv":
            raise ConfigError(f"{src}: a batch takes a folder of tree folders or a .csv manifest")
        return read_manifest(src)
    jobs = []
    for d in sorted(p for p in src.iterdir() if p.is_dir() and not p.name.startswith(".")):
        if is_batch_output(d):  # an earlier campaign's results: its summary is not a tree's scans
            continue
        files = scan_files(d)
        if files:
            truth = d / TRUTH_NAME
            jobs.append(TreeJob(d.name, tuple(files), truth=truth if truth.is_file() else None))
    if not jobs:
        raise ConfigError(f"{src}: no tree folders with scan files found (one sub-folder per tree, "
                          f"holding its scans: {', '.join(READ_EXTENSIONS)})")
    return jobs


def is_batch_output(folder: Path) -> bool:
    """`folder` holds a campaign's summary (an output folder of `treereg batch`)."""
    return all((folder / name).is_file() for name in SUMMARY_NAMES)


def scan_files(folder: Path) -> list[Path]:
    """A tree folder's scan files: in truth.json's order when there is one, else sorted by name.
    The matrix files batch writes are never among them."""
    files = sorted(p for p in folder.iterdir() if p.is_file() and extension(p) in READ_EXTENSIONS
                   and not p.name.lower().endswith(MATRIX_SUFFIXES))
    truth = folder / TRUTH_NAME
    if truth.is_file():
        try:
            order = read_transforms(truth).names
        except ConfigError:
            return files
        named = [folder / n for n in order if (folder / n).is_file()]
        return named + [f for f in files if f not in named]
    return files


def _floats(text: str, n: tuple[int, ...], where: str, what: str) -> tuple[float, ...]:
    parts = text.replace(",", " ").split()
    try:
        values = tuple(float(v) for v in parts)
    except ValueError:
        raise ConfigError(f"{where}: {what} {text!r} is not a number list") from None
    if len(values) not in n or not all(v == v and abs(v) != float("inf") for v in values):
        raise ConfigError(f"{where}: {what} needs {' or '.join(map(str, n))} numbers, got {text!r}")
    return values


#: A manifest's columns.
COLUMNS = ("tree", "scans", "angular_step", "target", "initial")


def _starts(text: str, folder: Path, where: str) -> tuple[tuple[str, Path], ...]:
    """The `initial` cell: "SCAN=FILE; SCAN=FILE" (files relative to the manifest's folder). The files
    are read with the tree (a bad one fails that tree, as a missing scan does)."""
    out: list[tuple[str, Path]] = []
    for entry in (e.strip() for e in text.split(";")):
        if not entry:
            continue
        scan, eq, file = entry.partition("=")
        if not (eq and scan.strip() and file.strip()):
            raise ConfigError(f"{where}: initial {entry!r} is not SCAN=FILE (e.g. scan2.ply=start2.txt)")
        if any(n == scan.strip() for n, _ in out):
            raise ConfigError(f"{where}: initial gives {scan.strip()!r} a start pose twice")
        out.append((scan.strip(), folder / file.strip()))
    return tuple(out)


def read_manifest(path: Path) -> list[TreeJob]:
    """The trees of a CSV manifest (see the module docstring)."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: cannot read the manifest ({e})") from None
    rows = list(csv.reader(line for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")))
    if not rows:
        raise ConfigError(f"{path}: the manifest is empty")
    head = [h.strip().lower() for h in rows[0]]
    if "tree" not in head or "scans" not in head:
        raise ConfigError(f"{path}: the first line must name the columns: tree, scans[, angular_step][, target]"
                          f"[, initial]; got {', '.join(head)}")
    unknown = [h for h in head if h not in COLUMNS]
    if unknown:
        raise ConfigError(f"{path}: unknown column(s) {', '.join(unknown)}; columns are {', '.join(COLUMNS)}")
    col = {h: i for i, h in enumerate(head)}
    jobs: list[TreeJob] = []
    seen: set[str] = set()
    for lineno, row in enumerate(rows[1:], start=2):
        where = f"{path}, line {lineno}"
        cell = {h: (row[i].strip() if i < len(row) else "") for h, i in col.items()}
        name = cell["tree"]
        if not name or "/" in name or "\\" in name or name in (".", "..") or _CONTROL.search(name):
            raise ConfigError(f"{where}: the tree name {name!r} cannot name a folder")
        size = len(os.fsencode(name))
        if size > MAX_NAME_BYTES:
            raise ConfigError(f"{where}: the tree name {name[:40]!r}... is {size} bytes long; it names the tree's "
                              f"folder, which can have at most {MAX_NAME_BYTES}")
        if name in seen:
            raise ConfigError(f"{where}: tree {name!r} is listed twice")
        seen.add(name)
        files = tuple(path.parent / f.strip() for f in cell["scans"].split(";") if f.strip())
        if len(files) < 2:
            raise ConfigError(f"{where}: tree {name!r} needs at least two scan files separated by ';'")
        step = None
        if cell.get("angular_step"):
            v = _floats(cell["angular_step"], (1, 2), where, "angular_step")
            if min(v) <= 0:
                raise ConfigError(f"{where}: angular_step must be positive, got {cell['angular_step']!r}")
            step = (v[0], v[-1])
        target = None
        if cell.get("target"):
            v = _floats(cell["target"], (2,), where, "target")
            target = (v[0], v[1])
        truth = files[0].parent / TRUTH_NAME
        jobs.append(TreeJob(name, files, step, target, truth if truth.is_file() else None,
                            _starts(cell.get("initial", ""), path.parent, where)))
    if not jobs:
        raise ConfigError(f"{path}: the manifest lists no trees")
    return jobs
