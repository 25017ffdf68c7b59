"""E57 (ASTM E2807), the exchange format every scanner vendor writes: read and write via pye57.

An E57 file holds any number of scans ("data3D" entries). Each scan stores its points in its own
frame and may carry a pose (rotation quaternion + translation) placing it in the file's frame;
scanners write unregistered scans with no pose (the identity). We read every scan in its own
frame and keep its pose (`ScanRecord.pose`), so registration runs where the angular grid is
regular, and we honour the file's row/column grid (the exact angular step), its invalid-point
flags and its return numbers.

We write a registered set as one multi-scan E57: each scan's points in its own frame, its
registered pose in the pose field, so CloudCompare and other E57 readers open it registered.

Reading is one call per scan (`read_e57_scan`): a chunked reader can replace its body.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import ScanError
from .atomic import write_atomic
from .record import POSE_TOL, NotRigid, ScanRecord, rigid_pose

#: Integer fields are read as int64 ('q'), the only integer type pye57's buffers take whole.
_INT, _FLOAT = "q", "d"


def _pye57():
    try:
        import pye57
    except ImportError:  # pragma: no cover - a dependency, but say so plainly if it is missing
        raise ScanError("E57", "reading E57 files needs the pye57 package: pip install pye57") from None
    return pye57


def pose_matrix(rotation_wxyz: Sequence[float], translation: Sequence[float]) -> np.ndarray:
    """4 x 4 T_file_scan from an E57 pose (unit quaternion w, x, y, z and a translation)."""
    from scipy.spatial.transform import Rotation

    w, x, y, z = (float(v) for v in rotation_wxyz)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()  # scipy wants the scalar last
    T[:3, 3] = np.asarray(translation, dtype=np.float64)
    return T


def pose_quaternion(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(w, x, y, z) unit quaternion and translation of a rigid 4 x 4 (the E57 pose fields)."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(np.asarray(T, dtype=np.float64)[:3, :3]).as_quat()
    q = np.array([w, x, y, z])
    return (q if w >= 0 else -q), np.asarray(T, dtype=np.float64)[:3, 3].copy()


def _read_fields(e57, header, fields: dict[str, str]) -> dict[str, np.ndarray]:
    """Read the named point fields of one scan into numpy arrays of the given dtypes."""
    from pye57 import libe57

    n = header.point_count
    data, buffers = {}, libe57.VectorSourceDestBuffer()
    for name, dtype in fields.items():
        data[name] = np.empty(n, dtype)
        buffers.append(libe57.SourceDestBuffer(e57.image_file, name, data[name], n, True, True))
    reader = header.points.reader(buffers)
    try:
        got = reader.read()
    finally:
        reader.close()
    return {k: v[:got] for k, v in data.items()}


def _scan_name(header, stem: str, k: int) -> str:
    try:
        name = str(header["name"].value()).strip()
    except Exception:  # libe57 raises its own type for an absent child
        name = ""
    return name or f"{stem}#{k + 1}"


def _file_pose(header, what: str) -> np.ndarray:
    """The pose an E57 scan header gives, checked rigid (`rigid_pose`): a unit quaternion and a finite
    translation. Scipy would quietly normalise a quaternion of another length (a scale); refused here."""
    q = np.asarray(header.rotation, dtype=np.float64)
    t = np.asarray(header.translation, dtype=np.float64)
    try:
        if not (np.isfinite(q).all() and np.isfinite(t).all()):
            raise NotRigid("holds NaN or infinite numbers")
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > POSE_TOL:
            raise NotRigid(f"is not rigid: its rotation quaternion has length {norm:.3g}, not 1 (a scale); "
                           "export the scan with a rigid pose (rotation and translation only)")
        return rigid_pose(pose_matrix(q, t))
    except NotRigid as e:
        raise NotRigid(f"{what}: the pose in the scan's header {e}") from None


def read_e57_scan(e57, index: int, stem: str) -> ScanRecord:
    """Scan `index` of an open `pye57.E57`: points in the scan's own frame, its pose, grid, returns."""
    header = e57.get_header(index)
    present = set(header.point_fields)
    fields: dict[str, str] = {}
    if {"cartesianX", "cartesianY", "cartesianZ"} <= present:
        fields.update(cartesianX=_FLOAT, cartesianY=_FLOAT, cartesianZ=_FLOAT)
        invalid = "cartesianInvalidState"
    elif {"sphericalRange", "sphericalAzimuth", "sphericalElevation"} <= present:
        fields.update(sphericalRange=_FLOAT, sphericalAzimuth=_FLOAT, sphericalElevation=_FLOAT)
        invalid = "sphericalInvalidState"
    else:
        raise ValueError(f"scan {index + 1} has neither cartesian nor spherical coordinates")
    extra = [f for f in (invalid, "rowIndex", "columnIndex", "returnIndex") if f in present]
    fields.update({f: _INT for f in extra})
    d = _read_fields(e57, header, fields)
    if "cartesianX" in d:
        pts = np.column_stack([d["cartesianX"], d["cartesianY"], d["cartesianZ"]])
    else:
        r, az, el = d["sphericalRange"], d["sphericalAzimuth"], d["sphericalElevation"]
        pts = np.column_stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)])
    grid = (d["rowIndex"], d["columnIndex"]) if "rowIndex" in d and "columnIndex" in d else None
    name = _scan_name(header, stem, index)
    pose = _file_pose(header, f"scan {index + 1} ({name})") if header.has_pose() else np.eye(4)
    rec = ScanRecord(name, pts, pose, grid, d.get("returnIndex"))
    if invalid in d:  # 0 = valid; 1 = a direction without a range, 2 = nothing
        rec = rec.select(d[invalid] == 0)
    return rec


def read_e57(path: str | Path) -> list[ScanRecord]:
    """Every scan of an E57 file, in file order (see `read_e57_scan`).

    Raises
    ------
    ScanError
        Not a readable E57 file, or a file that holds no scans. Names that repeat get `#k` added,
        so every scan keeps its own key in transforms.json.
    """
    path = Path(path)
    pye57 = _pye57()
    try:
        with pye57.E57(str(path)) as e57:
            records = [read_e57_scan(e57, k, path.stem) for k in range(e57.scan_count)]
    except ScanError:
        raise
    except NotRigid as e:  # refused here, not after a whole run that computed with it
        raise ScanError(str(path), str(e)) from None
    except Exception as e:  # libe57 raises its own exception types for malformed files
        raise ScanError(str(path), f"not a readable E57 file ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})") from None
    if not records:
        raise ScanError(str(path), "the E57 file holds no scans (no data3D entries)")
    names = [r.name for r in records]
    if len(set(names)) != len(names):
        records = [ScanRecord(f"{r.name}#{k + 1}", r.points, r.pose, r.grid, r.return_index)
                   for k, r in enumerate(records)]
    return records


def e57_point_count(path: str | Path) -> int:
    """The points every scan of an E57 file announces in its header (no point is read)."""
    pye57 = _pye57()
    try:
        with pye57.E57(str(path)) as e57:
            return sum(int(e57.get_header(k).point_count) for k in range(e57.scan_count))
    except Exception as e:  # libe57 raises its own exception types for malformed files
        raise ScanError(str(path), f"not a readable E57 file ({type(e).__name__})") from None


def _text(name: str) -> str:
    """A scan name as E57 text, which is UTF-8: the bytes of a file name that is not (kept by Python
    as lone surrogates) are written as \\xff escapes."""
    try:
        return name.encode("utf-8").decode("utf-8")
    except UnicodeEncodeError:
        try:
            return name.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
        except UnicodeEncodeError:
            return name.encode("utf-8", "backslashreplace").decode("utf-8")


def write_e57(path: str | Path, scans: Sequence[tuple[str, np.ndarray, np.ndarray]]) -> Path:
    """Write a multi-scan E57, atomically: (name, points in the scan's own frame, 4 x 4 pose) per scan.

    The pose places the scan in the file's frame (for a registration: T_ref_scan, or the
    reference's pose times it), so any E57 reader shows the scans registered. Coordinates are
    stored as pye57 stores them (32-bit floats in the scan's own frame: micrometres within a few
    hundred metres of the scanner); the pose is stored in double precision, so a georeferenced
    pose keeps its millimetres.
    """
    path = Path(path)
    pye57 = _pye57()
    if not scans:
        raise ScanError(str(path), "no scans to write")

    def write(tmp: Path) -> None:
        tmp.unlink()  # libE57 creates the file itself
        e57 = pye57.E57(str(tmp), mode="w")
        try:
            for name, pts, T in scans:
                pts = np.asarray(pts, dtype=np.float64)
                q, t = pose_quaternion(T)
                e57.write_scan_raw({"cartesianX": pts[:, 0], "cartesianY": pts[:, 1], "cartesianZ": pts[:, 2]},
                                   name=_text(str(name)), rotation=q, translation=t)
        finally:
            e57.close()

    return write_atomic(path, write)


def write_registered_e57(path: str | Path, scans: Sequence, tf) -> Path:
    """A registration as one E57: every registered scan in its own frame, posed by the transform
    file (`io.transforms.TransformFile`, matrices in the users' frames) times its own pose, so the
    file opens with every scan where the registration puts it, in the reference's frame."""
    out = []
    for s in scans:
        if s.name in tf.transforms or s.name == tf.reference:
            out.append((s.name, s.points, np.asarray(tf.matrix(s.name)) @ s.pose))
    return write_e57(path, out)
