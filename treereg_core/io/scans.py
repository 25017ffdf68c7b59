"""Reading and writing scans: PLY, LAS/LAZ, XYZ/TXT/CSV (optionally gzipped), NPY/NPZ, and the
multi-scan exchange formats E57 and PTX (`io.e57`, `io.ptx`).

`read_scans(path)` gives every scan a file holds (one for most formats, any number for E57/PTX),
each in its scanner's own frame with the pose the file (or `scanner_position`) gives it.
Every point reader returns N x 3 float64 metres; every problem a user has to fix raises
`errors.ScanError`, whose message names the file and says what is wrong and what to do.
Readers never loop over points in Python: text goes through numpy's C parser, LAS/LAZ is read
in chunks into one preallocated array. No file is memory-mapped (a mapped file that shrinks ends
the process with a bus error): every read is checked for length. Every reader checks what the
file's header promises (point counts, types, end of header) and refuses a file cut short rather
than read part of it. Rows that are no measurement (NaN, no-data values, absurdly far) are dropped with a
warning before any unit is guessed (`_valid_rows`). Writers are atomic: a temporary file beside the
target, renamed over it only when complete.
"""

from __future__ import annotations

import gzip
import io as _io
import json
import math
import os
import re
import warnings
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, TextIO

import numpy as np

from .atomic import write_atomic
from .record import RETURNS, ScanRecord
from ..errors import ScanError, ScanWarning
from ..prepare.frames import far_from_origin, far_message, one_sided, to_scanner_frame
from ..scan import MIN_POINTS, Scan

#: Plain-text point formats (x y z in the first three columns); each may also be gzipped (+".gz").
TEXT_EXTENSIONS: tuple[str, ...] = (".xyz", ".txt", ".csv")
#: Formats that hold several scans, each with a pose (`read_scans` reads them all).
MULTI_SCAN_EXTENSIONS: tuple[str, ...] = (".e57", ".ptx", ".ptx.gz")
#: Everything `read_points` understands.
POINT_EXTENSIONS: tuple[str, ...] = (
    (".ply", ".las", ".laz") + TEXT_EXTENSIONS + tuple(e + ".gz" for e in TEXT_EXTENSIONS) + (".npy", ".npz")
)
#: Everything `read_scans` understands.
READ_EXTENSIONS: tuple[str, ...] = POINT_EXTENSIONS + MULTI_SCAN_EXTENSIONS
#: Column names (lower case) of a text header or LAS field that hold the return number (1 = first).
RETURN_COLUMNS: tuple[str, ...] = ("return_number", "returnnumber", "target_index", "return_index")
#: Everything `write_scan` writes.
WRITE_EXTENSIONS: tuple[str, ...] = (".ply", ".las", ".laz")
#: User id of the LAS/LAZ VLR naming the scans of a merged cloud (JSON: {"1": "a/scan1.ply", ...}).
SCAN_NAMES_VLR = "treereg"

#: A tree cloud in metres spans at most this (1st to 99th percentile along its longest axis, file
#: units): the tallest trees are about 100 m, a scan with its surroundings a few hundred metres.
MAX_EXTENT_M = 500.0
#: A scan in metres in its scanner's frame has its points a median of at most this from the scanner.
MAX_RANGE_M = 300.0
#: What a single-tree scan typically measures in metres (extent, median range): the unit whose
#: factor brings a cloud closest to these is the one it was written in.
TYPICAL_EXTENT_M = 20.0
TYPICAL_RANGE_M = 15.0
#: A tree scan in metres spans at least this (a sapling); a smaller cloud is in a larger unit.
MIN_EXTENT_M = 0.2
#: Units a point file may be in besides metres: name, factor to metres.
OTHER_UNITS: tuple[tuple[str, float], ...] = (("centimetres", 0.01), ("millimetres", 0.001), ("kilometres", 1000.0))
#: Values files write in every coordinate of a row for "no measurement" (GIS and scanner no-data).
NO_DATA_VALUES: tuple[float, ...] = (-9999.0, -99999.0, -999999.0)
#: A point farther than this many times the points' median spread from their median point is a
#: corrupt or stray row, not a measurement (the same in any unit): 1000 x a tree scan's ~10 m is
#: 10 km, beyond any terrestrial scanner's reach.
OUTLIER_FACTOR = 1000.0
#: Points a median distance of more than this fraction of their range apart are a scene seen from the
#: origin; closer together, they sit far from the origin: not the scanner's frame (georeferenced).
MIN_SPREAD_TO_RANGE = 0.02
_SIZE_SAMPLE = 200_000
#: The coarsest coordinate resolution a scan may have: stems are fitted to millimetres.
MAX_RESOLUTION_M = 0.01
#: LAS/LAZ coordinate resolution we write (metres).
LAS_SCALE_M = 0.0001
_LAS_CHUNK = 2_000_000
_PLY_CHUNK = 2_000_000


def _warn(text: str) -> None:
    """A `ScanWarning` (what was repaired in a file)."""
    warnings.warn(text, ScanWarning, stacklevel=3)


def extension(path: str | Path) -> str:
    """The lower-case format extension of `path`, including `.gz` for gzipped text ("a.XYZ.gz" -> ".xyz.gz")."""
    suffixes = [s.lower() for s in Path(path).suffixes]
    if len(suffixes) >= 2 and suffixes[-1] == ".gz":
        return suffixes[-2] + ".gz"
    return suffixes[-1] if suffixes else ""


# ---- reading -----------------------------------------------------------------------------------
def read_points(path: str | Path, check_units: bool = True) -> np.ndarray:
    """Read the x, y, z coordinates of a point file.

    Parameters
    ----------
    path
        A file with one of `READ_EXTENSIONS`.
    check_units
        Refuse coordinates that look like centimetres or millimetres (see `check_metres`; a
        scan's own frame is checked by `record_to_scan`).

    Returns
    -------
    np.ndarray
        N x 3 float64. Rows with NaN or infinite coordinates, no-data rows and rows absurdly far
        from the rest are dropped with a `ScanWarning` (`_valid_rows`).

    Raises
    ------
    ScanError
        Missing or empty file, unknown extension, unreadable or non-numeric content, wrong shape,
        no finite points, or (with `check_units`) coordinates that are not metres.
    """
    path = Path(path)
    ext = _check_file(path)
    if ext in MULTI_SCAN_EXTENSIONS:
        records = read_records(path, check_units=check_units)
        if len(records) != 1:
            raise ScanError(str(path), f"holds {len(records)} scans; read them with read_scans")
        return records[0].points
    pts, _ = _read_single(path, ext)
    keep = _valid_rows(str(path), pts)
    pts = pts if keep is None else np.ascontiguousarray(pts[keep])
    if check_units:
        check_metres(pts, str(path))
    return pts


def _check_file(path: Path) -> str:
    """The file's format extension, after checking the file exists, is a file and is not empty."""
    ext = extension(path)
    if ext not in READ_EXTENSIONS:
        raise ScanError(
            str(path),
            f"unknown file type {ext or '(no extension)'!r}; supported: {', '.join(READ_EXTENSIONS)}",
        )
    if not path.exists():
        raise ScanError(str(path), "no such file")
    if path.is_dir():
        raise ScanError(str(path), "is a directory, not a scan file")
    if not path.is_file():  # a FIFO or device has no size: "empty" would be untrue, and reading it may block
        raise ScanError(str(path), "is not a regular file (a FIFO, device or socket), so not a scan file; give the scan file itself")
    if path.stat().st_size == 0:
        raise ScanError(str(path), "the file is empty")
    return ext


def _read_single(path: Path, ext: str) -> tuple[np.ndarray, np.ndarray | None]:
    """Points of a single-scan file and, where the format has them, 0-based return numbers."""
    ret = None
    if ext == ".ply":
        pts = _read_ply(path)
    elif ext in (".las", ".laz"):
        pts, ret = _read_las(path)
    elif ext == ".npy":
        pts = _read_npy(path)
    elif ext == ".npz":
        pts = _read_npz(path)
    else:
        pts, ret = _read_text(path, gzipped=ext.endswith(".gz"))
    return pts, ret


def read_records(path: str | Path, check_units: bool = True) -> list[ScanRecord]:
    """Every scan a file holds, as stored (`ScanRecord`: points, pose, grid, return numbers).

    Rows with NaN or infinite coordinates, no-data rows and absurdly far rows are dropped (with a
    `ScanWarning`, `_valid_rows`); with `check_units`, coordinates that look like another unit
    are refused (`check_metres`).
    """
    path = Path(path)
    ext = _check_file(path)
    if ext == ".e57":
        from .e57 import read_e57
        records = read_e57(path)
    elif ext in (".ptx", ".ptx.gz"):
        from .ptx import read_ptx
        records = read_ptx(path)
    else:
        pts, ret = _read_single(path, ext)
        records = [ScanRecord(path.name, pts, np.eye(4), None, ret)]
    out = []
    for r in records:
        label = str(path) if len(records) == 1 else f"{path} [{r.name}]"
        if len(r.points) == 0:
            raise ScanError(label, "the scan holds no valid points")
        keep = _valid_rows(label, r.points)  # warns for each kind of row dropped
        r = r if keep is None else r.select(keep)
        check_precision(r.points, label)
        if check_units:
            # Points spread like a scene seen from the origin: their distance from it tells the unit
            # too. Far and close together (georeferenced) is `record_to_scan`'s to say.
            size = _size(r.points)
            check_metres(r.points, label, scanner_frame=_seen_from_origin(r.points, size), size=size)
        out.append(r)
    return out


def read_scans(
    path: str | Path,
    angular_step_deg: tuple[float, float] | None = None,
    returns: str = "first",
    scanner_positions: list[tuple[float, float, float] | None] | None = None,
    min_points: int = MIN_POINTS,
) -> list[Scan]:
    """Every scan of a file, each in its scanner's own frame (see `record_to_scan`).

    Parameters
    ----------
    path
        Any of `READ_EXTENSIONS`; E57 and PTX files may hold several scans.
    angular_step_deg
        (phi, varphi) in degrees; None = from the file's grid, else estimated from the points.
    returns
        "first" keeps the first return of each pulse (where the file numbers returns), "all" all.
    scanner_positions
        Per scan of the file, the scanner's position in the file's coordinates (or None).
    """
    path = Path(path)
    records = read_records(path)
    positions = list(scanner_positions or [])
    if positions and len(positions) != len(records):
        raise ScanError(str(path), f"holds {len(records)} scan(s) but {len(positions)} scanner position(s) were given for it")
    positions += [None] * (len(records) - len(positions))
    return [record_to_scan(r, path if len(records) == 1 else Path(f"{path}#{r.name}"), angular_step_deg, returns,
                           pos, min_points) for r, pos in zip(records, positions)]


def record_to_scan(
    record: ScanRecord,
    source: Path,
    angular_step_deg: tuple[float, float] | None = None,
    returns: str = "first",
    scanner_position: tuple[float, float, float] | None = None,
    min_points: int = MIN_POINTS,
) -> Scan:
    """A `Scan` in its scanner's frame from a file's record.

    With `scanner_position` (in the record's coordinates) the points are shifted so the scanner is
    the origin, in float64, and the shift joins the record's pose: `scan.pose` = T_user_scan. A
    scan whose points lie kilometres from the origin without a position is refused (it is not in
    its scanner's frame); one whose points all lie to one side and show no angular grid gets a
    warning naming both flags that could help.
    """
    if returns not in RETURNS:
        raise ScanError(str(source), f"returns must be one of {', '.join(RETURNS)}, got {returns!r}")
    record = record.with_returns(returns)
    pose = record.pose
    pts = record.points
    if scanner_position is not None:
        if not np.isfinite(np.asarray(scanner_position, dtype=np.float64)).all():
            where = ", ".join(f"{float(v):g}" for v in scanner_position)
            raise ScanError(str(source), f"the scanner position given for it, ({where}), is not a point: give "
                                         "--scanner-position X Y Z as three finite numbers")
        pts, shift = to_scanner_frame(pts, scanner_position)
        pose = pose @ shift
    else:
        far = far_from_origin(pts)
        if far is not None:
            raise ScanError(str(source), far_message(far))
    scan = Scan.from_points(pts, name=record.name, source=source, angular_step_deg=angular_step_deg,
                            min_points=min_points, pose=pose, grid=record.grid)
    if scan.step.low and one_sided(pts):
        _warn(
            f"{source}: the points show no regular angular grid (step estimate {scan.step.describe()}) and all lie on "
            "one side of the origin: if the scan is not in its scanner's frame, give --scanner-position X Y Z; "
            "if it is, give the instrument's steps with --angular-step H V")
    elif scan.step.low:
        _warn(f"{source}: the angular step estimate is unreliable ({scan.step.describe()}); "
              "give the instrument's steps with --angular-step H V")
    return scan


def read_scan(
    path: str | Path,
    angular_step_deg: tuple[float, float] | None = None,
    name: str | None = None,
    min_points: int = MIN_POINTS,
    returns: str = "first",
    scanner_position: tuple[float, float, float] | None = None,
) -> Scan:
    """Read a single-scan file (scanner at the origin, metres, z up) into a `Scan`.

    Parameters
    ----------
    path
        Scan file, any of `READ_EXTENSIONS`.
    angular_step_deg
        (phi, varphi) of the instrument in degrees; estimated from the points when None.
    name
        Name of the scan; default the file's base name (the key used in transforms.json).
    min_points
        Fewer points than this is an error.
    returns, scanner_position
        As for `read_scans`.
    """
    path = Path(path)
    scans = read_scans(path, angular_step_deg=angular_step_deg, returns=returns,
                       scanner_positions=None if scanner_position is None else [scanner_position],
                       min_points=min_points)
    if len(scans) != 1:
        raise ScanError(str(path), f"holds {len(scans)} scans ({', '.join(s.name for s in scans)}); read them with read_scans")
    scan = scans[0]
    return scan if name is None else scan.with_points(scan.points, name=name)


def announced_points(path: str | Path, stop_after: int | None = None) -> tuple[int, bool] | None:
    """How many points reading `path` would give at most, known before any point is read: what its
    header announces (PLY, LAS/LAZ, NPY/NPZ arrays, every scan of an E57), or for text formats (XYZ,
    TXT, CSV, PTX, gzipped or not) its lines, counted until more than `stop_after`.

    Returns (count, announced): announced is True for a header's count, False for lines counted
    (which stop once more than `stop_after`: at least that many). None when the file's header
    cannot be read: reading the file says what is wrong. What a
    file unpacks to is not bounded by its size: a few hundred kB of LAZ, gzip or compressed NPZ can
    hold tens of millions of points.
    """
    import laspy  # laspy.errors: what a file that is no LAS raises

    path = Path(path)
    ext = extension(path)
    try:
        if ext == ".ply":
            return next(e.count for e in _ply_header(path).elements if e.name == "vertex"), True
        if ext in (".las", ".laz"):
            with laspy.open(path) as reader:
                return int(reader.header.point_count), True
        if ext == ".e57":
            from .e57 import e57_point_count
            return e57_point_count(path), True
        if ext == ".npy":
            with open(path, "rb") as fh:
                return _npy_points(fh), True
        if ext == ".npz":
            with zipfile.ZipFile(path) as z:
                return max((_npy_points(z.open(m)) for m in z.namelist() if m.endswith(".npy")), default=0), True
        if ext in READ_EXTENSIONS:  # text: at most one point per line
            return _count_lines(path, ext.endswith(".gz"), stop_after)
    except (ScanError, OSError, EOFError, ValueError, zlib.error, zipfile.BadZipFile, laspy.errors.LaspyException):
        pass
    return None


def _npy_header(fh) -> tuple[tuple[int, ...], np.dtype]:
    """The shape and type an .npy array's header announces; `fh` is left at its data."""
    version = np.lib.format.read_magic(fh)
    read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
    shape, _, dtype = read(fh)
    return shape, dtype


def _npy_points(fh) -> int:
    """The points (rows of three) an .npy array's header announces (its data is not read)."""
    return math.prod(_npy_header(fh)[0]) // 3


def _count_lines(path: Path, gzipped: bool, stop_after: int | None) -> tuple[int, bool]:
    """Lines of a text file (decompressed), counted in chunks until more than `stop_after`; (count, False)."""
    count, last = 0, b"\n"
    with (gzip.open(path, "rb") if gzipped else open(path, "rb")) as fh:
        while chunk := fh.read(1 << 24):
            count += chunk.count(b"\n")
            last = chunk[-1:]
            if stop_after is not None and count > stop_after:
                break
    return count + (last != b"\n"), False  # a last line without its newline counts


def _size(points: np.ndarray) -> tuple[float, float, float]:
    """(robust extent, spread, median range) in file units, from a subsample.

    Extent: the largest 1st-to-99th percentile span over the axes (far outliers do not count).
    Spread: median distance of the points from their median point. Range: median distance from the origin.
    """
    sample = points[:: max(1, len(points) // _SIZE_SAMPLE)]
    lo, hi = np.percentile(sample, [1.0, 99.0], axis=0)
    extent = float((hi - lo).max())
    spread = float(np.median(np.linalg.norm(sample - np.median(sample, axis=0), axis=1)))
    rng = float(np.median(np.linalg.norm(sample, axis=1)))
    return extent, spread, rng


def _seen_from_origin(points: np.ndarray, size: tuple[float, float, float] | None = None) -> bool:
    """True when the points spread like a scene seen from the origin (a scan in another unit), not
    like a scan far from the origin with its points close together (georeferenced coordinates).
    `size`: `_size(points)` when already known."""
    _, spread, rng = size or _size(points)
    return spread >= MIN_SPREAD_TO_RANGE * rng


def check_precision(points: np.ndarray, label: str) -> None:
    """Raise `ScanError` when the coordinates are single precision (float32) at a magnitude where
    float32 cannot hold a centimetre (`MAX_RESOLUTION_M`): UTM coordinates written as float32 are
    0.5 m apart at 5,000 km, and every later check would blame something else (the angular step).

    Float32 is told by every sampled coordinate being a float32 value exactly: coordinates computed
    in float64 (or scaled integers, as LAS stores them) almost never all are.
    """
    if len(points) == 0:
        return
    sample = points[:: max(1, len(points) // _SIZE_SAMPLE)]
    typical = np.median(np.abs(sample), axis=0)
    resolution = np.spacing(typical.astype(np.float32)).astype(np.float64)
    axis = int(np.argmax(resolution))
    if resolution[axis] <= MAX_RESOLUTION_M or not np.array_equal(sample.astype(np.float32), sample):
        return
    raise ScanError(
        label,
        f"the coordinates are single precision (float32) and lie some {typical[axis]:,.0f} m from the origin, "
        f"where float32 holds a coordinate only to {resolution[axis]:g} m: they lost their precision when the "
        "file was written. Export the scan as float64 (double), or shifted near the origin (e.g. minus the "
        "scanner's position) as float32, and read it again",
    )


def check_metres(points: np.ndarray, label: str, scanner_frame: bool = False,
                 size: tuple[float, float, float] | None = None) -> None:
    """Raise `ScanError`, naming the likely unit and its factor, when the points are not in metres.

    A tree cloud in metres spans `MIN_EXTENT_M` to `MAX_EXTENT_M` (and, seen from its scanner, lies
    within `MAX_RANGE_M`). Outside that, the unit is the one (`OTHER_UNITS`) whose factor brings
    the extent (and the range) closest to a typical tree scan's; the message gives the sizes in
    metres that factor would make, so the user can check. The extent does not change with a shift,
    so georeferenced clouds in metres pass (`record_to_scan` tests a scan's frame).
    """
    if len(points) == 0:
        return
    extent, _, rng = size or _size(points)
    if MIN_EXTENT_M <= extent <= MAX_EXTENT_M and (not scanner_frame or rng <= MAX_RANGE_M):
        return

    def misfit(f: float) -> float:
        out = abs(np.log10(max(extent * f, 1e-9) / TYPICAL_EXTENT_M))
        return out + (abs(np.log10(max(rng * f, 1e-9) / TYPICAL_RANGE_M)) if scanner_frame else 0.0)

    unit, f = min(OTHER_UNITS, key=lambda u: misfit(u[1]))
    seen = f"{extent * f:,.1f} m" + (f", a median {rng * f:,.1f} m from the scanner" if scanner_frame else "")
    where = f" (median distance from the scanner {_units(rng)})" if scanner_frame else ""
    raise ScanError(
        label,
        f"coordinates span {_units(extent)} units{where}; treereg expects metres and this looks like {unit}: "
        f"convert the file to metres (scale the coordinates by {f:g}, which makes the scan span {seen}) "
        "and read it again",
    )


def _units(x: float) -> str:
    """A size in file units as a person reads it: 24,620 or 0.0246."""
    return f"{x:,.0f}" if x >= 100 else f"{x:.3g}"


def _valid_rows(label: str, pts: np.ndarray) -> np.ndarray | None:
    """Which rows of a file's points are measurements: rows with NaN or infinite coordinates, no-data
    rows (`NO_DATA_VALUES`) and rows absurdly far from the rest (`OUTLIER_FACTOR`) are not. Each kind
    dropped gets one `ScanWarning` naming its count; None when every row is kept.

    Runs before any unit is guessed, so a few such rows are named as what they are, not read as
    a scan in centimetres. Raises `ScanError` when nothing is left or every point is the same.
    """
    n = len(pts)
    # The bounds first (two passes along the columns): in a clean file they show at once that no
    # row is NaN, infinite or a no-data value, and, below, that none lies far out; only a file
    # that has such rows pays for the row-by-row tests.
    # Column by column: a reduction along the long axis of an N x 3 array runs a 3-long inner loop
    # N times (80 ms for 3 M points, ten times slower).
    lo = np.array([pts[:, k].min() for k in range(3)])
    hi = np.array([pts[:, k].max() for k in range(3)])
    clean = bool(np.isfinite(lo).all() and np.isfinite(hi).all())
    keep = np.ones(n, dtype=bool) if clean else np.isfinite(pts).all(axis=1)
    if not keep.any():
        raise ScanError(label, f"all {n} points have NaN or infinite coordinates; nothing is left")
    _warn_dropped(label, n, n - int(keep.sum()), "with NaN or infinite coordinates")
    x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
    no_data = np.zeros(n, dtype=bool)
    if not (clean and lo[0] > max(NO_DATA_VALUES)):  # a no-data row's x is one of them
        cand = np.flatnonzero(keep & (x == y))
        cand = cand[(y[cand] == z[cand]) & np.isin(x[cand], NO_DATA_VALUES)]
        no_data[cand] = True
    if no_data.any():
        v = float(x[np.flatnonzero(no_data)[0]])
        keep &= ~no_data
        if not keep.any():
            raise ScanError(label, f"all {n} points are the no-data row ({v:g}, {v:g}, {v:g}); the file holds no measurement")
        _warn_dropped(label, n, int(no_data.sum()), f"at ({v:g}, {v:g}, {v:g}) (a no-data value, not a measurement)")
    far, reach, spread = _far_rows(pts, keep, (lo, hi) if clean and not no_data.any() else None)
    if far.any():
        keep &= ~far
        _warn_dropped(label, n, int(far.sum()), f"lying far outside the scan (up to {reach:.3g} units from its median "
                                                f"point, while half the points lie within {spread:.3g} units of it): corrupt or stray rows")
    _check_not_one_point(label, pts, keep)
    return None if keep.all() else keep


def _warn_dropped(label: str, n: int, n_bad: int, why: str) -> None:
    if n_bad:
        _warn(f"{label}: dropped {n_bad} of {n} points {why}")


def _far_rows(pts: np.ndarray, keep: np.ndarray, bounds: tuple[np.ndarray, np.ndarray] | None = None
              ) -> tuple[np.ndarray, float, float]:
    """Rows (among `keep`) farther than `OUTLIER_FACTOR` times the points' median spread from their
    median point (largest coordinate difference), the farthest such distance, and the spread.
    `bounds`: the kept rows' lowest and highest coordinates, when known (no row is far when they
    are near)."""
    sample = _kept_sample(pts, keep)
    centre = np.median(sample, axis=0)
    spread = float(np.median(np.abs(sample - centre).max(axis=1)))
    far = np.zeros(len(pts), dtype=bool)
    if spread == 0.0:
        return far, 0.0, 0.0  # most points are one point: `_check_not_one_point` or the step estimate says so
    limit, reach = OUTLIER_FACTOR * spread, 0.0
    if bounds is not None and max(float((bounds[1] - centre).max()), float((centre - bounds[0]).max())) <= limit:
        return far, 0.0, spread
    with np.errstate(over="ignore", invalid="ignore"):  # 1e308 - -1e308 is inf: far, as it should be
        for a in range(0, len(pts), _PLY_CHUNK):
            chunk = pts[a:a + _PLY_CHUNK]
            d = np.abs(chunk[:, 0] - centre[0])
            for k in (1, 2):
                np.maximum(d, np.abs(chunk[:, k] - centre[k]), out=d)
            hit = (d > limit) & keep[a:a + _PLY_CHUNK]
            if hit.any():
                far[a:a + _PLY_CHUNK] = hit
                reach = max(reach, float(d[hit].max()))
    return far, reach, spread


def _check_not_one_point(label: str, pts: np.ndarray, keep: np.ndarray) -> None:
    """Refuse points that are all one point (a sample first: the full check only when it is)."""
    first = pts[int(np.argmax(keep))]
    if np.any(_kept_sample(pts, keep) != first):
        return
    kept = pts[keep]
    if np.all(kept == first):
        raise ScanError(label, f"all {len(kept)} points are the same point ({first[0]:g}, {first[1]:g}, {first[2]:g}), "
                               "so the file holds no scan")


def _kept_sample(pts: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """About `_SIZE_SAMPLE` of the kept rows, evenly through the file, without an index array as long
    as the scan (the rows kept are nearly always all of them)."""
    step = max(1, len(pts) // _SIZE_SAMPLE)
    sample = pts[::step][keep[::step]]
    return sample if len(sample) else pts[keep][:_SIZE_SAMPLE]  # the kept rows all fell between the strides


def _as_xyz(path: Path, arr: np.ndarray, what: str) -> np.ndarray:
    """Check an array is N x 3 numeric and return it as float64."""
    if arr.dtype.kind not in "biuf":
        raise ScanError(str(path), f"{what} holds {arr.dtype} values, not numbers")
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ScanError(str(path), f"{what} has shape {arr.shape}; expected N x 3 (x, y, z)")
    if arr.shape[0] == 0:
        raise ScanError(str(path), f"{what} holds no points")
    return np.ascontiguousarray(arr, dtype=np.float64)


def _read_npy(path: Path) -> np.ndarray:
    try:
        with open(path, "rb") as fh:
            shape, dtype = _npy_header(fh)
            if dtype.kind in "biuf" and len(shape) == 2 and shape[1] == 3:
                have = (os.fstat(fh.fileno()).st_size - fh.tell()) // (3 * dtype.itemsize)
                if have < shape[0]:
                    raise ScanError(str(path), f"the .npy file is truncated: its header announces {shape[0]} points, "
                                               f"the file holds {have}")
            fh.seek(0)
            # Read, not memory-mapped: a float64 array's map became the scan's points, so the file
            # overwritten or cut later changed them, or ended the process with a bus error.
            arr = np.load(fh, allow_pickle=False)
    except ScanError:
        raise
    except (ValueError, OSError, EOFError) as e:
        raise ScanError(str(path), f"not a readable .npy array ({e})") from None
    return _as_xyz(path, arr, "the array")


def _read_npz(path: Path) -> np.ndarray:
    try:
        with np.load(path, allow_pickle=False) as z:
            keys = list(z.keys())
            if not keys:
                raise ScanError(str(path), "the .npz archive holds no arrays")
            if len(keys) > 1 and "points" not in keys:
                # Which array holds the scan is not ours to guess: say what is there.
                raise ScanError(str(path), f"the .npz archive holds {len(keys)} arrays ({', '.join(keys[:10])}) and "
                                           "none is named 'points': save the scan's N x 3 array alone, or under the "
                                           "name 'points'")
            key = "points" if "points" in keys else keys[0]
            arr = z[key]
    except ScanError:
        raise
    except (ValueError, OSError, EOFError) as e:
        raise ScanError(str(path), f"not a readable .npz archive ({e})") from None
    return _as_xyz(path, arr, f"array {key!r}")


#: PLY scalar types -> numpy (the PLY spec's names and their sized aliases).
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
#: A PLY header longer than this (bytes) has no end_header: the file is not a PLY, or cut in its header.
_PLY_MAX_HEADER = 1 << 16


@dataclass(frozen=True)
class _PlyElement:
    name: str
    count: int
    props: tuple[tuple[str, str], ...]  # (name, PLY type, or "list")


@dataclass(frozen=True)
class _PlyHeader:
    format: str  # "ascii", "binary_little_endian" or "binary_big_endian"
    offset: int  # byte offset of the data
    lines: int  # lines of the header, end_header included
    elements: tuple[_PlyElement, ...]


def _ply_header(path: Path) -> _PlyHeader:
    """The header of a PLY file, checked: it ends (end_header), has a known format, a vertex element
    and x, y, z properties of a type that can hold coordinates."""
    with open(path, "rb") as fh:
        head = fh.read(_PLY_MAX_HEADER)
    end = re.search(rb"^end_header[ \t]*\r?\n", head, flags=re.MULTILINE)
    if not head.startswith(b"ply"):
        raise ScanError(str(path), "not a readable PLY file (it does not start with 'ply')")
    if end is None:
        raise ScanError(str(path), "the PLY header has no end_header line: the file is cut inside its header, "
                                   "or not a PLY file")
    lines = [ln.strip() for ln in head[:end.start()].decode("ascii", errors="replace").splitlines()]
    fmt = next((ln.split()[1] for ln in lines if ln.startswith("format ") and len(ln.split()) > 1), "")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ScanError(str(path), f"the PLY header names no known format (format {fmt or '(missing)'!r}; "
                                   "expected ascii, binary_little_endian or binary_big_endian)")
    elements: list[list] = []
    for ln in lines:
        words = ln.split()
        if words[:1] == ["element"]:
            if len(words) != 3 or not words[2].isdigit():
                raise ScanError(str(path), f"the PLY header line {ln[:60]!r} is not 'element NAME COUNT'")
            elements.append([words[1], int(words[2]), []])
        elif words[:1] == ["property"] and elements:
            kind = "list" if words[1:2] == ["list"] else (words[1] if len(words) == 3 else "?")
            elements[-1][2].append((words[-1], kind))
    header = _PlyHeader(fmt, end.end(), len(lines) + 1, tuple(_PlyElement(n, c, tuple(p)) for n, c, p in elements))
    _check_ply_vertices(path, header)
    return header


def _check_ply_vertices(path: Path, header: _PlyHeader) -> None:
    """Refuse a PLY whose vertices cannot be a scan: none, no x y z, or x y z of a type that cannot
    hold coordinates (a list, or 8-bit integers: 256 values at most)."""
    vertex = next((e for e in header.elements if e.name == "vertex"), None)
    if vertex is None:
        raise ScanError(str(path), "the PLY file holds no points (no vertex element)")
    types = dict(vertex.props)
    missing = [c for c in "xyz" if c not in types]
    if missing:
        raise ScanError(str(path), f"the PLY vertex element has no {', '.join(missing)} property "
                                   f"(it has {', '.join(types) or 'none'})")
    for c in "xyz":
        if types[c] == "list":
            raise ScanError(str(path), f"the PLY file declares {c} as a list property, not one number per point: "
                                       "export the scan with float or double x, y, z")
        if types[c] not in _PLY_TYPES:
            raise ScanError(str(path), f"the PLY file declares {c} with the unknown type {types[c]!r}")
        if np.dtype(_PLY_TYPES[types[c]]).itemsize == 1:
            info = np.iinfo(_PLY_TYPES[types[c]])
            raise ScanError(str(path), f"the PLY file declares {c} as {types[c]} (whole numbers {info.min} to "
                                       f"{info.max}), which cannot hold a scan's coordinates: export the scan "
                                       "with float or double x, y, z")


def _read_ply(path: Path) -> np.ndarray:
    try:
        header = _ply_header(path)
    except OSError as e:
        raise ScanError(str(path), f"cannot read the file ({e.strerror or e})") from None
    first = header.elements[0]
    if first.name == "vertex" and all(t in _PLY_TYPES for _, t in first.props):
        if header.format == "ascii":
            return _read_ply_ascii(path, header)
        return _read_ply_binary(path, header)
    import trimesh  # another layout (lists among the vertex properties, vertices not first)

    try:
        geom = trimesh.load(path, file_type="ply", process=False)
    except Exception as e:  # trimesh raises many types for malformed files
        raise ScanError(str(path), f"not a readable PLY file ({type(e).__name__}: {e})") from None
    vertices = getattr(geom, "vertices", None)
    if vertices is None or len(vertices) == 0:
        raise ScanError(str(path), "the PLY file holds no points (no vertex element)")
    return _as_xyz(path, np.asarray(vertices), "the vertex element")


def _ply_count_message(path: Path, n: int, have: int, what: str = "points", shrank: bool = False) -> ScanError:
    """The header and the data disagree: too little data is a truncated file, too much a wrong count."""
    if have < n:
        # A file that was whole when its size was checked and then came up short was cut while read
        # (a copy or download still being written, a shared drive): reading it again later may work.
        when = " (it shrank while being read: read it again once it is complete)" if shrank else ""
        return ScanError(str(path), f"the PLY file is truncated: its header announces {n} {what}, the file holds {have}{when}")
    return ScanError(str(path), f"the PLY file holds more than its header announces: its header announces {n} "
                                f"{what}, the file holds {have}; the file is damaged (fix the count in its header "
                                "or export it again)")


def _read_into(fh, buf: np.ndarray, path: Path, n: int, done: int, itemsize: int) -> None:
    """Fill `buf` (whole records) from `fh`, or raise the truncation `ScanError`: the file can shrink
    after its size was checked, and a short read must be named, not reshaped or used in part (`done`:
    the points read before this buffer, for the count the message gives)."""
    view = memoryview(buf).cast("B")
    got = 0
    while got < len(view):
        k = fh.readinto(view[got:])
        if not k:
            raise _ply_count_message(path, n, done + got // itemsize, shrank=True)
        got += k


def _read_ply_binary(path: Path, header: _PlyHeader) -> np.ndarray:
    """x, y, z of a binary PLY's vertices: read straight into the scan's array when the file holds
    nothing else, else read in chunks of records and copied into float64 (other properties are
    never held whole: one full-resolution copy of the scan, no more). Every read is checked for
    length and nothing is memory-mapped: a file that shrinks while read (a bus error under a map)
    is named as truncated."""
    order = "<" if header.format == "binary_little_endian" else ">"
    vertex = header.elements[0]
    record = np.dtype([(name, order + _PLY_TYPES[t]) for name, t in vertex.props])
    n = vertex.count
    if n <= 0:
        raise ScanError(str(path), "the PLY file holds no points (its vertex element is empty)")
    try:
        with open(path, "rb", buffering=0) as fh:
            have = (os.fstat(fh.fileno()).st_size - header.offset) // record.itemsize
            # With the vertices the only element, the file's size is known: more whole records is a wrong count.
            if have < n or (len(header.elements) == 1 and have > n):
                raise _ply_count_message(path, n, have)
            fh.seek(header.offset)
            names = [name for name, _ in vertex.props]
            types = {t for _, t in vertex.props}
            if names == ["x", "y", "z"] and len(types) == 1 and record[0].kind == "f":
                # Only x, y, z of one float type (what scanners' exporters and treereg write): one
                # read of the file into the array the scan keeps (floats converted once).
                flat = np.empty((n, 3), dtype=record[0])
                _read_into(fh, flat, path, n, 0, record.itemsize)
                return flat.astype(np.float64, copy=False)
            out = np.empty((n, 3), dtype=np.float64)
            buf = np.empty(min(n, _PLY_CHUNK), dtype=record)
            for a in range(0, n, _PLY_CHUNK):
                chunk = buf[: min(_PLY_CHUNK, n - a)]
                _read_into(fh, chunk, path, n, a, record.itemsize)
                for k, name in enumerate("xyz"):
                    out[a:a + len(chunk), k] = chunk[name]
            return out
    except OSError as e:
        raise ScanError(str(path), f"cannot read the file ({e.strerror or e})") from None


def _data_lines(path: Path, offset: int) -> int:
    """Lines of data from byte `offset` to the end of the file, counted in chunks (a last line
    without a newline counts; blank lines at the end do not)."""
    count = 0
    with open(path, "rb") as fh:
        fh.seek(offset)
        while chunk := fh.read(1 << 24):
            count += chunk.count(b"\n")
        size = fh.tell() - offset
        fh.seek(offset + max(0, size - 4096))
        tail = fh.read()
    body = tail.rstrip()
    if not body and size <= 4096:
        return 0
    return count - tail[len(body):].count(b"\n") + 1


def _read_ply_ascii(path: Path, header: _PlyHeader) -> np.ndarray:
    """x, y, z of an ASCII PLY's vertices (numpy's C parser), after checking the file holds as many
    lines as its header announces (one per vertex, face, ...): a file cut short or with a wrong
    count is named, not read in part."""
    vertex = header.elements[0]
    n = vertex.count
    if n <= 0:
        raise ScanError(str(path), "the PLY file holds no points (its vertex element is empty)")
    have = _data_lines(path, header.offset)
    total = sum(e.count for e in header.elements)
    if have < n:
        raise _ply_count_message(path, n, have)
    if have != total:
        what = "points" if len(header.elements) == 1 else f"lines of data ({n} points and {total - n} other items)"
        raise _ply_count_message(path, total, have, what)
    names = [name for name, _ in vertex.props]
    cols = tuple(names.index(c) for c in "xyz")
    try:
        with open(path, encoding="ascii", errors="replace") as fh:
            for _ in range(header.lines):
                fh.readline()
            return np.loadtxt(fh, dtype=np.float64, usecols=cols, max_rows=n, ndmin=2, comments=None)
    except ValueError:
        raise ScanError(str(path), _first_bad_line(path, False, None, header.lines, cols)) from None


def _read_las(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    import laspy

    try:
        with laspy.open(path) as reader:
            n = int(reader.header.point_count)
            if n == 0:
                raise ScanError(str(path), "the LAS/LAZ file holds no points")
            if not reader.header.are_points_compressed:
                _check_las_size(path, reader.header, n)
            out = np.empty((n, 3), dtype=np.float64)
            ret = np.empty(n, dtype=np.int16)
            i = 0
            try:
                # Chunks keep memory bounded: only x, y, z (and the return number) are ever held.
                for chunk in reader.chunk_iterator(_LAS_CHUNK):
                    m = min(len(chunk), n - i)
                    out[i : i + m, 0] = chunk.x[:m]
                    out[i : i + m, 1] = chunk.y[:m]
                    out[i : i + m, 2] = chunk.z[:m]
                    ret[i : i + m] = np.asarray(chunk.return_number[:m], dtype=np.int16) - 1
                    i += m
            except Exception as e:  # lazrs raises its own types for a file cut short
                raise ScanError(str(path), f"the LAZ file is truncated or damaged: its header announces {n} points, "
                                           f"{i} could be read ({type(e).__name__}: {e})") from None
            if i < n:
                raise ScanError(str(path), f"the LAS/LAZ file is truncated: its header announces {n} points, the file holds {i}")
    except ScanError:
        raise
    except Exception as e:  # laspy / lazrs raise their own types for bad files
        raise ScanError(str(path), f"not a readable LAS/LAZ file ({type(e).__name__}: {e})") from None
    # Writers that do not number returns leave 0 (-1 here): then there is nothing to select on.
    return out, (ret if (ret >= 0).all() and (ret > 0).any() else None)


def _check_las_size(path: Path, header, n: int) -> None:
    """An uncompressed LAS file holds exactly its header's count of fixed-size records (before any
    extended VLRs): fewer is a truncated file, more a wrong count; either is named, not read in part."""
    end = int(header.start_of_first_evlr) if getattr(header, "number_of_evlrs", 0) else path.stat().st_size
    have = max(0, end - int(header.offset_to_point_data)) // int(header.point_format.size)
    if have < n:
        raise ScanError(str(path), f"the LAS file is truncated: its header announces {n} points, the file holds {have}")
    if have > n:
        raise ScanError(str(path), f"the LAS file holds more than its header announces: its header announces {n} "
                                   f"points, the file holds {have}; the file is damaged (export it again)")


# ---- text --------------------------------------------------------------------------------------
def _open_text(path: Path, gzipped: bool) -> TextIO:
    if gzipped:
        return _io.TextIOWrapper(gzip.open(path, "rb"), encoding="utf-8-sig", errors="replace")
    return open(path, encoding="utf-8-sig", errors="replace")  # -sig: drop a byte-order mark


def _is_comment(line: str) -> bool:
    s = line.strip()
    return not s or s.startswith("#") or s.startswith("//")


def _split(line: str, delimiter: str | None) -> list[str]:
    return [f.strip() for f in line.strip().split(delimiter)]


def _is_number(field: str) -> bool:
    try:
        float(field)
    except ValueError:
        return False
    return True


def _is_header(fields: list[str]) -> bool:
    """A header names its columns: none of the first three fields is a number ("x y z", "X,Y,Z,i").

    A row with some numbers and some text ("1 a 3") is a broken data row, not a header, so it is
    reported instead of silently skipped.
    """
    return not any(_is_number(f) for f in fields[:3])


#: Bytes that never occur in a text file (control characters other than tab, newlines, form feed).
_BINARY_BYTES = bytes(set(range(32)) - {9, 10, 11, 12, 13, 26})


def _check_text(path: Path, gzipped: bool) -> None:
    """Refuse a file that is not text (a binary file given an .xyz name), without echoing its bytes."""
    try:
        with (gzip.open(path, "rb") if gzipped else open(path, "rb")) as fh:
            head = fh.read(1 << 16)
    except (OSError, EOFError, gzip.BadGzipFile) as e:
        raise ScanError(str(path), f"cannot read the file ({e})") from None
    if b"\0" in head or len(head.translate(None, _BINARY_BYTES)) < 0.99 * len(head):
        raise ScanError(str(path), f"not a text file (it holds binary data): a {extension(path)} scan is text, "
                                   "x y z on each line; check that this is the scan, and that its extension names its format")


def _sniff(path: Path, gzipped: bool) -> tuple[str | None, int, tuple[int, ...]]:
    """Delimiter (None = whitespace), the number of lines to skip before the data, and the columns
    to read: x, y, z and, when a header or comment line names one, the return number.

    Comment lines ('#', '//') and blank lines may come first; then at most one header line. A
    header naming x, y and z ("id,x,y,z") says where they are; else they are the first three columns.
    """
    _check_text(path, gzipped)
    try:
        with _open_text(path, gzipped) as fh:
            head = [fh.readline(1 << 16) for _ in range(64)]  # bounded, even for a binary file
    except (OSError, EOFError, gzip.BadGzipFile) as e:
        raise ScanError(str(path), f"cannot read the file ({e})") from None
    head = [h for h in head if h]
    lineno = 0
    cols = None
    while lineno < len(head) and _is_comment(head[lineno]):
        cols = cols or _named_columns(head[lineno].strip().lstrip("#/ "))
        lineno += 1
    if lineno == len(head):
        raise ScanError(str(path), "the file holds no points (only blank or comment lines)")
    first = head[lineno]
    delimiter = "," if "," in first else (";" if ";" in first else None)
    skip = lineno
    if _is_header(_split(first, delimiter)):
        skip += 1  # one header line ("x y z", "X,Y,Z,intensity", ...)
        cols = cols or _named_columns(first)
        rest = [h for h in head[skip:] if not _is_comment(h)]
        if rest:
            # the delimiter is better read off a data line than off the header
            delimiter = "," if "," in rest[0] else (";" if ";" in rest[0] else None)
    data = [h for h in head[skip:] if not _is_comment(h)]
    if data and _decimal_commas(data):
        fix = "or replace each ',' by '.' in the file" if ";" in data[0] or len(data[0].split()) >= 3 else \
            "commas separate its columns too, so no line can be read as x y z"
        raise ScanError(str(path), f"the numbers are written with decimal commas ({data[0].strip()[:60]!r}), and "
                                   "treereg reads a decimal point: export the scan with '.' as the decimal separator "
                                   f"({fix}) and read it again")
    return delimiter, skip, cols or (0, 1, 2)


_DECIMAL_COMMA = re.compile(r"[-+]?\d*,\d+(?:[eE][-+]?\d+)?")


def _decimal_commas(lines: list[str]) -> bool:
    """True when the data lines write numbers with a decimal comma: "1,5;2,3;4,7", "1,5 2,3 4,7", or
    commas both ways, "1,5,2,3,4,7" (which would read as six numbers: every second one a fraction's
    digits, all of one width, some with a leading zero no whole number is written with)."""
    lines = [ln.split("#")[0].strip() for ln in lines[:16]]
    if not all("," in ln for ln in lines):
        return False
    if all(";" in ln or len(ln.split()) >= 3 for ln in lines):  # another separator: each field one number
        fields = [f for ln in lines for f in _split(ln, ";" if ";" in ln else None)[:3]]
        return all(_DECIMAL_COMMA.fullmatch(f) or _is_number(f) for f in fields) and \
            any(_DECIMAL_COMMA.fullmatch(f) for f in fields)
    rows = [_split(ln, ",") for ln in lines]
    if any(len(r) < 6 or len(r) % 2 or len(r) != len(rows[0]) for r in rows):
        return False
    whole = [f for r in rows for f in r[0::2]]
    fractions = [f for r in rows for f in r[1::2]]
    return all(re.fullmatch(r"[-+]?\d+", f) for f in whole) and all(f.isdigit() for f in fractions) and \
        len({len(f) for f in fractions}) == 1 and (len(fractions[0]) == 1 or any(f[0] == "0" for f in fractions))


def _named_columns(line: str) -> tuple[int, ...] | None:
    """The columns of x, y, z (and of the return number, see `RETURN_COLUMNS`) a header line names,
    or None when it does not name all of x, y and z. Units after a name ("X[m]", "y (m)") are ignored."""
    names = [re.sub(r"[\[(].*$", "", f).strip().strip("\"'").lower() for f in re.split(r"[,;\s]+", line.strip())]
    if not {"x", "y", "z"} <= set(names):
        return None
    ret = [i for i, n in enumerate(names) if n in RETURN_COLUMNS]
    return tuple(names.index(c) for c in "xyz") + tuple(ret[:1])


def _read_text(path: Path, gzipped: bool) -> tuple[np.ndarray, np.ndarray | None]:
    delimiter, skip, cols = _sniff(path, gzipped)
    try:
        with _open_text(path, gzipped) as fh:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # numpy warns "input contained no data"; handled below
                pts = np.loadtxt(
                    fh, dtype=np.float64, comments=("#", "//"), delimiter=delimiter,
                    skiprows=skip, usecols=cols, ndmin=2,
                )
    except ValueError:
        raise ScanError(str(path), _first_bad_line(path, gzipped, delimiter, skip, cols[:3])) from None
    except (OSError, EOFError, gzip.BadGzipFile) as e:
        raise ScanError(str(path), f"cannot read the file ({e})") from None
    if pts.shape[0] == 0:
        raise ScanError(str(path), "the file holds no points (only a header)")
    if len(cols) == 3:
        return pts, None
    ret = pts[:, 3]
    ok = np.isfinite(ret) & (ret >= 1)
    return np.ascontiguousarray(pts[:, :3]), (ret.astype(np.int16) - 1 if ok.all() else None)


def _first_bad_line(path: Path, gzipped: bool, delimiter: str | None, skip: int,
                    cols: tuple[int, ...] = (0, 1, 2)) -> str:
    """Describe the first line numpy could not parse (x, y, z in columns `cols`). Runs only after a
    parse error, and stops at the first bad line, so the Python loop is never paid on a good file."""
    with _open_text(path, gzipped) as fh:
        for lineno, line in enumerate(fh, start=1):
            if lineno <= skip or _is_comment(line):
                continue
            if line.translate(str.maketrans("", "", _BINARY_BYTES.decode())) != line or "\ufffd" in line:
                return f"line {lineno} is not text (binary or non-UTF-8 bytes): the file is damaged, or not a text scan"
            body = line.split("#")[0]
            fields = _split(body, delimiter)
            if len(fields) <= max(cols):
                sep = "commas" if delimiter == "," else (f"{delimiter!r}" if delimiter else "spaces")
                where = "the first three columns" if cols == (0, 1, 2) else f"columns {', '.join(str(c + 1) for c in cols)}"
                return (f"line {lineno} has {len(fields)} column(s) ({line.strip()[:60]!r}); "
                        f"x y z are needed in {where}, separated by {sep}")
            for col in cols:
                if not _is_number(fields[col]):
                    return (f"line {lineno}, column {col + 1}: {fields[col]!r} is not a number "
                            f"(the line reads {line.strip()[:60]!r})")
    return "the text could not be parsed as x y z numbers"


# ---- writing -----------------------------------------------------------------------------------
def write_scan(path: str | Path, points_or_scan: np.ndarray | Scan, dtype: str = "float64",
               scan_id: np.ndarray | None = None, scan_names: Mapping[int, str] | None = None) -> Path:
    """Write points (or a `Scan`'s points) as PLY (binary little-endian) or LAS/LAZ, atomically.

    Parameters
    ----------
    path
        Target file; the extension picks the format (`WRITE_EXTENSIONS`).
    points_or_scan
        N x 3 coordinates in metres, or a `Scan`.
    dtype
        PLY only: "float64" (default, exact) or "float32" (half the size, ~1 um at 10 m).
        LAS/LAZ always store integers at `LAS_SCALE_M` resolution.
    scan_id
        Optional N integers 0..65535 saying which scan each point came from (a merged cloud): the
        PLY gets a `scan_id` vertex property (a scalar field in CloudCompare), LAS/LAZ the
        standard `point_source_id`.
    scan_names
        Optional {scan number: scan name} for `scan_id` (the merged cloud's scans): PLY header
        comments `comment scan_id 1 = "a/scan1.ply"`, a LAS/LAZ VLR (user id `SCAN_NAMES_VLR`)
        holding them as JSON.

    Returns
    -------
    Path
        The written file.
    """
    path = Path(path)
    pts = points_or_scan.points if isinstance(points_or_scan, Scan) else np.asarray(points_or_scan)
    ext = extension(path)
    if ext not in WRITE_EXTENSIONS:
        raise ScanError(str(path), f"cannot write {ext or '(no extension)'!r} files; supported: {', '.join(WRITE_EXTENSIONS)}")
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ScanError(str(path), f"points to write have shape {pts.shape}; expected N x 3")
    pts = np.asarray(pts, dtype=np.float64)
    if not np.isfinite(pts).all():
        raise ScanError(str(path), "points to write contain NaN or infinite values")
    ids = None
    if scan_id is not None:
        ids = np.asarray(scan_id)
        if ids.shape != (len(pts),) or (len(ids) and (ids.min() < 0 or ids.max() > 65535)):
            raise ValueError(f"scan_id must hold one integer 0..65535 per point, got shape {ids.shape}")
        ids = ids.astype(np.uint16)
    tagged = {} if ids is None else {"scan_id": ids, "scan_names": dict(scan_names or {})}
    if ext == ".ply":
        if dtype not in ("float64", "float32"):
            raise ValueError(f"dtype must be 'float64' or 'float32', got {dtype!r}")
        write_atomic(path, lambda tmp: _write_ply(tmp, pts, dtype, **tagged))
    else:
        write_atomic(path, lambda tmp: _write_las(tmp, pts, compress=ext == ".laz", **tagged))
    return path


def _write_ply(path: Path, pts: np.ndarray, dtype: str, scan_id: np.ndarray | None = None,
               scan_names: Mapping[int, str] | None = None) -> None:
    ply_type = "double" if dtype == "float64" else "float"
    fields = [("x", dtype), ("y", dtype), ("z", dtype)]
    extra = ""
    if scan_id is not None:
        fields.append(("scan_id", "uint16"))
        extra = "property ushort scan_id\n"
    # A name as JSON text: ASCII (as the header must be), on one line, whatever the name holds.
    names = "".join(f"comment scan_id {k} = {json.dumps(n)}\n" for k, n in sorted((scan_names or {}).items()))
    header = (
        f"ply\nformat binary_little_endian 1.0\ncomment written by treereg\n{names}"
        f"element vertex {len(pts)}\n"
        f"property {ply_type} x\nproperty {ply_type} y\nproperty {ply_type} z\n{extra}end_header\n"
    )
    rec = np.empty(len(pts), dtype=np.dtype([(n, np.dtype(t).newbyteorder("<")) for n, t in fields]))
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if scan_id is not None:
        rec["scan_id"] = scan_id
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(rec.tobytes())


def _write_las(path: Path, pts: np.ndarray, compress: bool, scan_id: np.ndarray | None = None,
               scan_names: Mapping[int, str] | None = None) -> None:
    import laspy

    header = laspy.LasHeader(point_format=0, version="1.2")
    header.scales = np.full(3, LAS_SCALE_M)
    # Offset at the (rounded) minimum keeps the int32 range for clouds far from the origin.
    header.offsets = np.floor(pts.min(axis=0)) if len(pts) else np.zeros(3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    if scan_id is not None:
        las.point_source_id = scan_id
    if scan_names:
        text = json.dumps({str(k): n for k, n in sorted(scan_names.items())})
        las.vlrs.append(laspy.VLR(SCAN_NAMES_VLR, 1, "scan name per point_source_id", text.encode("ascii")))
    with open(path, "wb") as fh:
        las.write(fh, do_compress=compress, laz_backend=laspy.LazBackend.Lazrs if compress else None)
