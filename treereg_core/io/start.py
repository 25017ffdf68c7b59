"""Start pose files (`treereg register --initial SCAN=FILE`, the batch manifest's start column).

A start file is either CloudCompare's matrix text — 4 rows of 4 numbers, as `register --exports`
writes them and CloudCompare's Edit > Apply transformation shows them (other lines, a title or a
timestamp, are ignored) — or a transforms.json written earlier, whose entry for the scan is taken
(from "transforms", else its best guess under "unverified"), or a params.json the app saved, whose
"starts" (the start poses in force when it was saved, `starts_doc`) are such a transforms.json.
Either way the matrix maps the scan's points as its file gives them onto the reference's points as
its file gives them (T_ref_scan).

Every problem is one `ConfigError` naming the file: missing, unreadable, not text, not 4x4, NaN,
not rigid (checked as a file header's pose is: `record.rigid_pose`), no entry for the scan. That
the scan exists and is not the reference is checked against the scans (`Pipeline.start`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..coarse.start import StartPose
from ..errors import ConfigError
from ..text import shown
from .json_input import parse_json, read_user_bytes
from .record import NotRigid, rigid_pose
from .transforms import cloudcompare_rows

#: A start file is a few hundred bytes (a transforms.json a few kB per scan).
MAX_START_BYTES = 16 * 1024 * 1024
#: The key of the start poses the app saves beside its parameters in params.json (`starts_doc`).
STARTS_KEY = "starts"


def read_start(path: str | Path, scan: str) -> StartPose:
    """The start pose of `scan` in the file `path` (see the module docstring)."""
    path = Path(path)
    data = read_user_bytes(path, "start pose file (4 rows of 4 numbers, or a transforms.json)", MAX_START_BYTES)
    text = data.decode("utf-8-sig", errors="replace")
    reference = None
    if text.lstrip().startswith(("{", "[")):
        doc = parse_json(data, str(path))
        T, reference = _from_json(doc, path, scan)
    else:
        if "\ufffd" in text or "\x00" in text:
            raise ConfigError(f"{path}: not a text file, so neither a matrix (4 rows of 4 numbers) nor a transforms.json")
        T = _from_text(text, path)
    try:
        M = rigid_pose(T)
    except NotRigid as e:
        raise ConfigError(f"{path}: the start pose {e}") from None
    M = np.array(M, dtype=np.float64)
    M.setflags(write=False)
    return StartPose(T_ref_scan=M, source=shown(str(path)), reference=reference)


def _from_text(text: str, path: Path) -> np.ndarray:
    rows = cloudcompare_rows(text)
    if len(rows) != 4:
        raise ConfigError(f"{path}: expected a 4x4 matrix (4 rows of 4 numbers, as CloudCompare writes it), "
                          f"found {len(rows)} such row(s)")
    return np.array(rows, dtype=np.float64)


def _matrix(value: Any, path: Path, where: str) -> np.ndarray:
    try:
        M = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"{path}: {where} is not a 4x4 matrix of numbers") from None
    if M.shape != (4, 4):
        raise ConfigError(f"{path}: {where} is not a 4x4 matrix (4 rows of 4 numbers), its shape is {M.shape}")
    return M


def starts_doc(reference: str, starts: Mapping[str, StartPose]) -> dict[str, Any]:
    """The start poses as a transforms.json a start file may be (the app's starts.json, and the
    "starts" entry it saves beside the parameters in params.json): {"reference", "transforms": {scan:
    4x4}, "sources": {scan: where from}}."""
    return {"reference": reference,
            "transforms": {n: np.asarray(s.T_ref_scan, dtype=float).tolist() for n, s in starts.items()},
            "sources": {n: s.source for n, s in starts.items()}}


def saved_starts(doc: Any) -> Any:
    """The start poses in a parameter file the app saved (its top-level "starts", `starts_doc`), else
    `doc` itself: a start file may be such a params.json."""
    if isinstance(doc, dict) and "transforms" not in doc and isinstance(doc.get(STARTS_KEY), dict):
        return doc[STARTS_KEY]
    return doc


def _from_json(doc: Any, path: Path, scan: str) -> tuple[np.ndarray, str | None]:
    """A JSON 4x4 (a list of 4 rows), a transforms.json's entry for `scan` and its reference, or that of
    the start poses a params.json holds (`saved_starts`)."""
    doc = saved_starts(doc)
    if isinstance(doc, list):
        return _matrix(doc, path, "the matrix"), None
    if not isinstance(doc, dict) or not isinstance(doc.get("transforms"), dict):
        raise ConfigError(f"{path}: a JSON start file is a transforms.json (with \"reference\" and \"transforms\") "
                          "or a list of 4 rows of 4 numbers")
    reference = doc.get("reference")
    if not isinstance(reference, str) or not reference:
        raise ConfigError(f"{path}: 'reference' must be a scan name, got {shown(repr(reference))}")
    if scan == reference and scan not in doc["transforms"]:  # it maps by the identity (refused as a start)
        return np.eye(4), reference
    if scan in doc["transforms"]:
        return _matrix(doc["transforms"][scan], path, f"transforms[{shown(repr(scan))}]"), reference
    guess = (doc.get("unverified") or {}).get(scan) if isinstance(doc.get("unverified") or {}, dict) else None
    if isinstance(guess, dict) and "matrix" in guess:
        return _matrix(guess["matrix"], path, f"unverified[{shown(repr(scan))}].matrix"), reference
    listed = [n for n in doc["transforms"] if n != reference]
    raise ConfigError(f"{path}: holds no transform for {shown(repr(scan))}"
                      + (f"; it has {', '.join(shown(repr(n)) for n in listed)}" if listed else ""))
