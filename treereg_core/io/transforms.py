"""Transform files: transforms.json, CloudCompare matrix text and PDAL matrix strings.

`transforms.json` is the one result file every stage and tool agrees on::

    {"reference": "scan1.ply",
     "transforms": {"scan2.ply": [[r00, r01, r02, tx], ..., [0, 0, 0, 1]], ...},
     "params": {...}, "software": "treereg 0.1.0", ...extra keys}

Keys of "transforms" are the scans' names (`io.naming`: the files' base names, by folder where two
share one: "a/scan1.ply"); each 4x4 (row-major) is `T_ref_scan`, mapping a
point of that scan into the reference frame. The reference may be absent (it maps by the identity).
Other top-level keys (metrics, angular steps, stations, ...) are kept in `TransformFile.extra`.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .._version import __version__
from ..errors import ConfigError
from ..geometry.rigid import invert
from ..params import Params, changed_from_defaults, loosened, loosened_text, to_dict
from ..scan import Scan, ScanHeader
from . import atomic
from .json_input import load_json
from .naming import file_safe, file_stem
from .atomic import write_text_atomic

#: Largest |R^T R - I| entry accepted for the rotation part of a transform.
ORTHONORMAL_TOL = 1e-6
#: Top-level keys with a fixed meaning; everything else goes to `TransformFile.extra`.
RESERVED_KEYS: tuple[str, ...] = ("reference", "transforms", "params", "software")
DEFAULT_NAME = "transforms.json"


def check_transform(T: Any, where: str) -> np.ndarray:
    """Return `T` as a 4x4 float64 rigid transform or raise `ConfigError` naming `where`.

    Checks: 4x4 of numbers, all finite, last row 0 0 0 1, rotation part orthonormal within
    `ORTHONORMAL_TOL` and a proper rotation (determinant +1, not a mirror).
    """
    try:
        M = np.array(T, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: not a 4x4 matrix of numbers") from None
    if M.shape != (4, 4):
        raise ConfigError(f"{where}: expected a 4x4 matrix (4 rows of 4 numbers), got shape {M.shape}")
    if not np.isfinite(M).all():
        raise ConfigError(f"{where}: the matrix contains NaN or infinite values")
    if np.abs(M[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-9:
        raise ConfigError(f"{where}: the last row must be 0 0 0 1, got {' '.join(repr(float(v)) for v in M[3])}")
    R = M[:3, :3]
    dev = float(np.abs(R.T @ R - np.eye(3)).max())
    if dev > ORTHONORMAL_TOL:
        raise ConfigError(
            f"{where}: the rotation part is not orthonormal (|R^T R - I| = {dev:.2g} > {ORTHONORMAL_TOL:g}); "
            "a rigid transform cannot scale or shear"
        )
    if np.linalg.det(R) < 0:
        raise ConfigError(f"{where}: the rotation part is a reflection (determinant -1), not a rotation")
    return M


@dataclass(frozen=True, eq=False)
class TransformFile:
    """The content of a transforms.json.

    Attributes
    ----------
    reference
        Base name of the reference scan (e.g. "scan1.ply").
    transforms
        Scan base name -> 4x4 `T_ref_scan` (read-only float64 arrays).
    params
        The parameters used (as `params.to_dict` gives them).
    software
        "treereg <version>".
    extra
        Any other top-level keys (metrics, "angular_step_deg", "stations", ...), JSON-ready values.
    """

    reference: str
    transforms: dict[str, np.ndarray]
    params: dict[str, Any] = field(default_factory=dict)
    software: str = f"treereg {__version__}"
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.reference, str) or not self.reference:
            raise ConfigError(f"reference: expected a scan name, got {self.reference!r}")
        checked = {}
        for name, T in dict(self.transforms).items():
            M = check_transform(T, f"transforms[{name!r}]")
            M.setflags(write=False)
            checked[str(name)] = M
        clash = sorted(set(self.extra) & set(RESERVED_KEYS))
        if clash:
            raise ConfigError(f"extra: keys {clash} are reserved; use the dataclass fields")
        object.__setattr__(self, "transforms", checked)
        object.__setattr__(self, "params", dict(self.params))
        object.__setattr__(self, "extra", dict(self.extra))

    @property
    def names(self) -> list[str]:
        """All scans: the reference first, then the others in file order."""
        return [self.reference] + [n for n in self.transforms if n != self.reference]

    def matrix(self, name: str) -> np.ndarray:
        """`T_ref_scan` of scan `name` (the identity for the reference when it is not listed)."""
        if name in self.transforms:
            return self.transforms[name]
        if name == self.reference:
            return np.eye(4)
        raise KeyError(f"no transform for {name!r}; scans are {self.names}")


# ---- JSON --------------------------------------------------------------------------------------
def _jsonable(obj: Any) -> Any:
    """Plain JSON values: arrays -> lists, numpy scalars -> Python, NaN/inf -> null, Path -> str."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return _jsonable(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Path):
        return str(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return _jsonable(dataclasses.asdict(obj))
    return obj


def _matrix_json(T: np.ndarray, indent: str) -> str:
    """A 4x4 as a JSON list of rows, one row per line (readable), floats in full precision."""
    rows = [json.dumps([float(v) for v in row]) for row in T]
    inner = (",\n" + indent + "  ").join(rows)
    return "[\n" + indent + "  " + inner + "\n" + indent + "]"


def transforms_json_text(tf: TransformFile) -> str:
    """The text of transforms.json for `tf` (what `write_transforms` writes)."""
    doc: dict[str, Any] = {
        "reference": tf.reference,
        "transforms": {name: f"@@T{i}@@" for i, name in enumerate(tf.transforms)},
        "params": _jsonable(tf.params),
        "software": tf.software,
    }
    doc.update(_jsonable(tf.extra))
    text = json.dumps(doc, indent=2, allow_nan=False)
    # json.dumps would put each of the 16 numbers on its own line; rows read better.
    for i, T in enumerate(tf.transforms.values()):
        text = text.replace(f'"@@T{i}@@"', _matrix_json(T, "    "), 1)
    return text + "\n"


def write_transforms(path: str | Path, tf: TransformFile) -> Path:
    """Write `tf` as JSON to `path`, atomically (temporary file, then rename)."""
    path = Path(path)
    write_text_atomic(path, transforms_json_text(tf))
    return path


def read_transforms(path: str | Path) -> TransformFile:
    """Read and validate a transforms.json (also truth.json of a simulated case).

    Raises
    ------
    ConfigError
        Missing file, invalid JSON, a missing or mistyped key, or a matrix that is not a finite
        rigid 4x4; the message names the file and the key.
    """
    path = Path(path)
    data = load_json(path, "transform file")
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a JSON object with 'reference' and 'transforms'")
    for key in ("reference", "transforms"):
        if key not in data:
            raise ConfigError(f"{path}: missing key {key!r}")
    reference = data["reference"]
    if not isinstance(reference, str) or not reference:
        raise ConfigError(f"{path}: 'reference' must be a scan file name, got {reference!r}")
    transforms = data["transforms"]
    if not isinstance(transforms, dict):
        raise ConfigError(f"{path}: 'transforms' must be an object of scan name -> 4x4 matrix")
    checked = {name: check_transform(T, f"{path}: transforms[{name!r}]") for name, T in transforms.items()}
    params = data.get("params", {})
    if not isinstance(params, dict):
        raise ConfigError(f"{path}: 'params' must be an object")
    software = data.get("software", "")
    if not isinstance(software, str):
        raise ConfigError(f"{path}: 'software' must be a string")
    extra = {k: v for k, v in data.items() if k not in RESERVED_KEYS}
    return TransformFile(reference=reference, transforms=checked, params=params, software=software, extra=extra)


# ---- CloudCompare / PDAL -----------------------------------------------------------------------
def _num(v: float) -> str:
    """Shortest text that reads back as exactly the same float64."""
    return repr(float(v))


def cloudcompare_matrix_text(T: np.ndarray) -> str:
    """CloudCompare's matrix text: 4 lines of 4 numbers, row-major, full precision.

    Paste into Edit > Apply transformation, or save as .txt and load there.
    """
    M = check_transform(T, "CloudCompare matrix")
    return "\n".join(" ".join(_num(v) for v in row) for row in M) + "\n"


_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|[-+]?(?:nan|inf)", re.IGNORECASE)


def parse_cloudcompare_matrix(text: str) -> np.ndarray:
    """Read a 4x4 from CloudCompare's matrix text (the 4 lines of 4 numbers; other lines ignored).

    CloudCompare's console and saved files may add a title or timestamp line; only the lines that
    hold exactly four numbers count, and there must be exactly four of them.
    """
    rows = cloudcompare_rows(text)
    if len(rows) != 4:
        raise ConfigError(f"CloudCompare matrix: expected 4 lines of 4 numbers, found {len(rows)}")
    return check_transform(rows, "CloudCompare matrix")


def cloudcompare_rows(text: str) -> list[list[float]]:
    """The lines of `text` that hold exactly four numbers (CloudCompare's matrix rows), as numbers."""
    rows = []
    for line in text.splitlines():
        tokens = line.replace(",", " ").split()
        if len(tokens) == 4 and all(_NUMBER.fullmatch(t) for t in tokens):
            rows.append([float(t) for t in tokens])
    return rows


def pdal_matrix_string(T: np.ndarray) -> str:
    """The `matrix` option of PDAL's filters.transformation: 16 numbers, row-major, space separated."""
    M = check_transform(T, "PDAL matrix")
    return " ".join(_num(v) for v in M.ravel())


def parse_pdal_matrix(text: str) -> np.ndarray:
    """Read the 16-number PDAL matrix string back into a 4x4."""
    tokens = text.split()
    if len(tokens) != 16:
        raise ConfigError(f"PDAL matrix: expected 16 numbers, found {len(tokens)}")
    try:
        values = [float(t) for t in tokens]
    except ValueError as e:
        raise ConfigError(f"PDAL matrix: {e}") from None
    return check_transform(np.reshape(values, (4, 4)), "PDAL matrix")


def _stems(names: list[str]) -> dict[str, str]:
    """File stem per scan name for the export files (`naming.file_stem`: `a/scan1.ply` -> `a_scan1`,
    never a folder); where two stems would clash, the whole names made safe (`b.ply`, `b.las`), and
    numbered where even those would (`a/b.ply` beside `a_b.ply`)."""
    stems = {n: file_stem(n) for n in names}
    for fallback in (file_safe, lambda n: f"{file_safe(n)}~{names.index(n) + 1}"):
        counts = Counter(stems.values())
        stems.update({n: fallback(n) for n, s in stems.items() if counts[s] > 1})
    return stems


def export_names(names: Sequence[str], name: str = DEFAULT_NAME) -> dict[str, tuple[str, str]]:
    """Per scan, the names of its CloudCompare and PDAL matrix files: `<output stem>.<scan stem>.cloudcompare.txt`
    and `.pdal.txt`, named after the transform file so that two cases written into one folder do
    not overwrite each other's matrices."""
    out = Path(name).stem
    return {scan: (f"{out}.{stem}.cloudcompare.txt", f"{out}.{stem}.pdal.txt") for scan, stem in _stems(list(names)).items()}


def registered_e57_name(name: str = DEFAULT_NAME) -> str:
    """The registered scans' E57 written beside transform file `name` (`register --exports`):
    `<output stem>.registered.e57`, named after it as `export_names` are, never a fixed name."""
    return f"{Path(name).stem}.registered.e57"


def export_paths(out_dir: str | Path, names: Sequence[str], name: str = DEFAULT_NAME) -> list[Path]:
    """The files `write_exports` writes for scans `names`: the transform file first, then per scan
    its CloudCompare and PDAL matrix files (`export_names`); checked before a run, written after it."""
    out = Path(out_dir)
    paths = [out / name]
    for cc, pdal in export_names(names, name).values():
        paths += [out / cc, out / pdal]
    return paths


def refused_names(tf: TransformFile) -> list[str]:
    """The scans of a registration that `tf` gives no transform: its unverified best guesses (unless
    kept) and the scans it could not register."""
    listed = [*(tf.extra.get("unverified") or {}), *(tf.extra.get("unregistered") or {})]
    return [n for n in dict.fromkeys(listed) if n not in tf.transforms and n != tf.reference]


def stale_exports(out_dir: str | Path, tf: TransformFile, name: str = DEFAULT_NAME,
                  inputs: Sequence[str | Path] = ()) -> list[Path]:
    """The matrix files in `out_dir` that an earlier export under `name` wrote for scans `tf` now
    refuses (`refused_names`): left there, they would read as results beside a transform file that
    says otherwise. Only the exact names `export_names` gives those scans (with every scan of the
    run, or with the placed ones and that scan: the sets an earlier run may have exported), never
    one written now nor one of `inputs`; only regular files that exist."""
    refused = refused_names(tf)
    placed = set(export_paths(out_dir, tf.names, name))
    out = Path(out_dir)
    found: list[Path] = []
    for scan in refused:
        for names in ([*tf.names, *refused], [*tf.names, scan]):
            for file in export_names(names, name)[scan]:
                p = out / file
                # A link there was made by the user, not written by us (we write through links).
                if (p not in placed and p not in found and p.is_file() and not p.is_symlink()
                        and not atomic.is_one_of(p, inputs)):
                    found.append(p)
    return found


def write_exports(out_dir: str | Path, tf: TransformFile, name: str = DEFAULT_NAME,
                  inputs: Sequence[str | Path] = ()) -> list[Path]:
    """Write `name` (transforms.json) and, per scan, its CloudCompare and PDAL matrix files
    (`export_names`: e.g. `transforms.scan2.cloudcompare.txt`) into `out_dir`, and remove the
    matrix files an earlier export left for scans `tf` now refuses (`stale_exports`; never one of
    `inputs`).

    The reference gets its (identity) files too, so every scan can be treated the same way.
    The files are written as one batch: all of them (and the removals) or, on an error or Ctrl-C,
    none replace what was there. Returns the written paths (`export_paths`), transforms.json first.
    """
    paths = export_paths(out_dir, tf.names, name)
    with atomic.batch():
        write_transforms(paths[0], tf)
        for scan, cc, pdal in zip(tf.names, paths[1::2], paths[2::2]):
            T = tf.matrix(scan)
            write_text_atomic(cc, cloudcompare_matrix_text(T))
            write_text_atomic(pdal, pdal_matrix_string(T) + "\n")
        for stale in stale_exports(out_dir, tf, name, inputs):
            atomic.remove_atomic(stale)
    return paths


# Ten parameters: the scans, transforms and parameters, and by keyword every block of the file
# (stage, metrics, verdicts, quality, sources, time); CLI, batch and app each fill a different set.
def registration_file(scans: Sequence[Scan | ScanHeader], transforms: dict[str, np.ndarray], params: Params, *, stage: str,
                      metrics: dict[str, Any], verdicts: dict[str, tuple[str, tuple[str, ...], str]] | None = None,
                      quality: dict[str, Any] | None = None, keep_unverified: bool = False,
                      sources: dict[str, str] | None = None, seconds: float | None = None,
                      stage_seconds: dict[str, float] | None = None) -> TransformFile:
    """The TransformFile of a registration (what `treereg register` writes and the app exports).

    "transforms" holds the reference and the verified scans (and, with `keep_unverified`, the best
    guesses too, marked as such in "quality"); "unverified" the best guesses with the reasons
    ({"matrix": 4x4, "why": [...]}); "unregistered" the scans without any transform and why;
    "quality" the verdict and evidence per scan and the numbers of every registered pair. Without
    `verdicts` every transform given counts as verified (a caller that has no verification).

    `transforms` holds the registered scans in their scanner frames, as the pipeline gives them. A
    scan with a pose (`Scan.pose`, T_user_scan: an E57/PTX pose or a scanner position the user
    gave) is mapped back, so each matrix maps the scan's points *as its file gives them* onto the
    reference's points as its file gives them: T = pose_ref @ T_ref_scan @ inv(pose_scan). The poses
    are recorded under "poses" (only when one is not the identity). Besides the matrices it records
    the parameters used, the stage the transforms come from, every scan's angular steps (and how
    they were found), the per-pair metrics and, when known, the source files and the time taken
    (in all, and per stage: `stage_seconds`, wall time, "read" for reading the files).
    """
    transforms = user_frame_transforms(scans, transforms)
    verdicts = verdicts or {name: ("verified", (), "") for name in transforms}
    kept: dict[str, np.ndarray] = {}
    unverified: dict[str, Any] = {}
    unregistered: dict[str, str] = {}
    for s in scans:
        verdict, reasons, _ = verdicts.get(s.name, ("failed", ("not registered",), ""))
        T = transforms.get(s.name)
        if T is None:
            if s is not scans[0]:
                unregistered[s.name] = "; ".join(reasons) or "not registered"
            continue
        if verdict == "verified" or s is scans[0] or keep_unverified:
            kept[s.name] = T
        if verdict != "verified" and s is not scans[0]:
            unverified[s.name] = {"matrix": np.asarray(T, dtype=float), "why": list(reasons)}
    extra: dict[str, Any] = {"stage": stage}
    # Which pose the matrices are: "fine" runs on to the placement, where every scan is solved from the
    # verified fine pairs together (not each pair's own fine result, which the app shows beside it).
    extra["pose"] = {"fine": "placement (all scans solved together from the verified fine registrations)",
                     "coarse": "coarse (each scan's pair with the reference)"}.get(stage, stage)
    if seconds is not None:
        extra["seconds"] = round(float(seconds), 3)
    if stage_seconds:
        extra["stage_seconds"] = {k: round(float(v), 3) for k, v in stage_seconds.items()}
    extra["angular_step_deg"] = {s.name: list(s.angular_step_deg) for s in scans}
    extra["angular_step_source"] = {s.name: s.step.describe() for s in scans}
    if any(not np.allclose(s.pose, np.eye(4)) for s in scans):
        extra["poses"] = {s.name: s.pose for s in scans}
    if sources:
        extra["sources"] = dict(sources)
    extra["metrics"] = metrics
    if unverified:
        extra["unverified"] = unverified
    if unregistered:
        extra["unregistered"] = unregistered
    # Which parameters differ from the defaults ({key: [value, default]}); a verdict reached with a
    # verification threshold looser than its default says so (tightened ones cannot verify more).
    extra["params_changed"] = changed_from_defaults(params)
    if quality is not None:
        extra["quality"] = _with_loosened(quality, params, scans[0].name)
    if keep_unverified and unverified:
        extra["kept_unverified"] = sorted(unverified)
    return TransformFile(reference=scans[0].name, transforms=kept, params=to_dict(params), extra=extra)


def _with_loosened(quality: dict[str, Any], params: Params, reference: str) -> dict[str, Any]:
    """`quality` with "loosened" ({key: [value, default]}) and, on every verified scan and pair, a "note"
    saying it was verified under those thresholds; unchanged when none is looser than its default."""
    loose = loosened(params)
    if not loose:
        return quality
    note = loosened_text(loose)
    scans = {n: (dict(e, note=note) if e.get("verdict") == "verified" and n != reference else e)
             for n, e in quality.get("scans", {}).items()}
    edges = [dict(e, note=note) if e.get("verdict") == "verified" else e for e in quality.get("edges", [])]
    return {**quality, "loosened": {k: list(v) for k, v in loose.items()}, "scans": scans, "edges": edges}


def user_frame_transforms(scans: Sequence[Scan | ScanHeader], transforms: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Transforms between scanner frames mapped into the frames the users' files give the scans:
    pose_ref @ T_ref_scan @ inv(pose_scan) (unchanged when every pose is the identity)."""
    ref = scans[0]
    poses = {s.name: s.pose for s in scans}
    out = {}
    for name, T in transforms.items():
        P = poses.get(name, np.eye(4))
        out[name] = ref.pose @ np.asarray(T) @ invert(P)
    return out
