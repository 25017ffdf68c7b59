"""Reading and writing scans: PLY, LAS/LAZ, XYZ/TXT/CSV (optionally gzipped), NPY/NPZ.

Every reader returns N x 3 float64 metres; every problem a user has to fix raises
`errors.ScanError`, whose message names the file and says what is wrong and what to do.
Readers never loop over points in Python: text goes through numpy's C parser, LAS/LAZ is read
in chunks into one preallocated array, NPY is memory-mapped. Writers are atomic: a temporary file
beside the target, renamed over it only when complete.
"""

from __future__ import annotations

import gzip
import io as _io
import warnings
from pathlib import Path
from typing import TextIO

import numpy as np

from .atomic import write_atomic
from ..errors import ScanError
from ..scan import MIN_POINTS, Scan

#: Plain-text point formats (x y z in the first three columns); each may also be gzipped (+".gz").
TEXT_EXTENSIONS: tuple[str, ...] = (".xyz", ".txt", ".csv")
#: Everything `read_points` understands.
READ_EXTENSIONS: tuple[str, ...] = (
    (".ply", ".las", ".laz") + TEXT_EXTENSIONS + tuple(e + ".gz" for e in TEXT_EXTENSIONS) + (".npy", ".npz")
)
#: Everything `write_scan` writes.
WRITE_EXTENSIONS: tuple[str, ...] = (".ply", ".las", ".laz")

#: A tree cloud in metres spans at most this (1st to 99th percentile along its longest axis, file
#: units): the tallest trees are about 100 m, a scan with its surroundings a few hundred metres.
MAX_EXTENT_M = 500.0
#: A scan in metres in its scanner's frame has its points a median of at most this from the scanner.
MAX_RANGE_M = 300.0
#: What a single-tree scan typically measures in metres (extent, median range): the unit whose
#: factor brings a cloud closest to these is the one it was written in.
TYPICAL_EXTENT_M = 20.0
TYPICAL_RANGE_M = 15.0
#: Units a point file may be in besides metres: name, factor to metres.
OTHER_UNITS: tuple[tuple[str, float], ...] = (("centimetres", 0.01), ("millimetres", 0.001))
#: Points a median distance of more than this fraction of their range apart are a scene seen from the
#: origin; closer together, they sit far from the origin: not the scanner's frame (georeferenced).
MIN_SPREAD_TO_RANGE = 0.02
_SIZE_SAMPLE = 200_000
#: LAS/LAZ coordinate resolution we write (metres).
LAS_SCALE_M = 0.0001
_LAS_CHUNK = 2_000_000


class ScanWarning(UserWarning):
    """Something in a scan file was repaired (e.g. rows with NaN dropped); the message says what."""


def extension(path: str | Path) -> str:
    """The lower-case format extension of `path`, including `.gz` for gzipped text ("a.XYZ.gz" -> ".xyz.gz")."""
    suffixes = [s.lower() for s in Path(path).suffixes]
    if len(suffixes) >= 2 and suffixes[-1] == ".gz":
        return suffixes[-2] + ".gz"
    return suffixes[-1] if suffixes else ""


# ---- reading -----------------------------------------------------------------------------------
def read_points(path: str | Path, check_units: bool = True, scanner_frame: bool = False) -> np.ndarray:
    """Read the x, y, z coordinates of a point file.

    Parameters
    ----------
    path
        A file with one of `READ_EXTENSIONS`.
    check_units
        Refuse coordinates that look like centimetres or millimetres (see `check_metres`).
    scanner_frame
        The points are one station's scan: the scanner must be at the origin (`check_scanner_frame`),
        and the distance from it also tells the units.

    Returns
    -------
    np.ndarray
        N x 3 float64. Rows with NaN or infinite coordinates are dropped with a `ScanWarning`.

    Raises
    ------
    ScanError
        Missing or empty file, unknown extension, unreadable or non-numeric content, wrong shape,
        no finite points, (with `check_units`) coordinates that are not metres, or (with
        `scanner_frame`) a scan far from its scanner's origin.
    """
    path = Path(path)
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
    if path.stat().st_size == 0:
        raise ScanError(str(path), "the file is empty")
    if ext == ".ply":
        pts = _read_ply(path)
    elif ext in (".las", ".laz"):
        pts = _read_las(path)
    elif ext == ".npy":
        pts = _read_npy(path)
    elif ext == ".npz":
        pts = _read_npz(path)
    else:
        pts = _read_text(path, gzipped=ext.endswith(".gz"))
    pts = _drop_non_finite(path, pts)
    if scanner_frame:
        check_scanner_frame(pts, str(path))
    if check_units:
        check_metres(pts, str(path), scanner_frame=scanner_frame)
    return pts


def read_scan(
    path: str | Path,
    angular_step_deg: tuple[float, float] | None = None,
    name: str | None = None,
    min_points: int = MIN_POINTS,
) -> Scan:
    """Read a scan file (scanner at the origin, metres, z up) into a `Scan`.

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
    """
    path = Path(path)
    pts = read_points(path, scanner_frame=True)
    return Scan.from_points(
        pts, name=name or path.name, source=path, angular_step_deg=angular_step_deg, min_points=min_points
    )


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


def check_scanner_frame(points: np.ndarray, label: str) -> None:
    """Raise `ScanError` when the points are not in their scanner's frame (scanner at the origin).

    Georeferenced (e.g. UTM) or project coordinates put a scan far from the origin while its points
    stay close together; angles seen from the origin then mean nothing (the angular step estimate
    becomes 1e-6 deg) and every later stage would be silently wrong.
    """
    if len(points) == 0:
        return
    _, spread, rng = _size(points)
    if rng > MAX_RANGE_M and spread < MIN_SPREAD_TO_RANGE * rng:
        raise ScanError(
            label,
            f"the points lie {rng:,.0f} units from the origin but within {spread:,.0f} of each other "
            "(median distances), so this scan is not in its scanner's own frame (georeferenced or project "
            "coordinates?); treereg needs each scan with its scanner at the origin: subtract the scanner's "
            "position from the coordinates (or export the scan in the scanner's frame) and read it again",
        )


def check_metres(points: np.ndarray, label: str, scanner_frame: bool = False) -> None:
    """Raise `ScanError`, naming the likely unit and its factor, when the points are not in metres.

    A tree cloud in metres spans at most `MAX_EXTENT_M` (and, seen from its scanner, lies within
    `MAX_RANGE_M`). Beyond that, the unit is the one (centimetres or millimetres) whose factor brings
    the extent (and the range) closest to a typical tree scan's; the message gives the sizes in
    metres that factor would make, so the user can check. The extent does not change with a shift,
    so georeferenced clouds in metres pass (`check_scanner_frame` is the test for those).
    """
    if len(points) == 0:
        return
    extent, _, rng = _size(points)
    if extent <= MAX_EXTENT_M and (not scanner_frame or rng <= MAX_RANGE_M):
        return

    def misfit(f: float) -> float:
        out = abs(np.log10(max(extent * f, 1e-9) / TYPICAL_EXTENT_M))
        return out + (abs(np.log10(max(rng * f, 1e-9) / TYPICAL_RANGE_M)) if scanner_frame else 0.0)

    unit, f = min(OTHER_UNITS, key=lambda u: misfit(u[1]))
    seen = f"{extent * f:,.1f} m" + (f", a median {rng * f:,.1f} m from the scanner" if scanner_frame else "")
    where = f" (median distance from the scanner {rng:,.0f})" if scanner_frame else ""
    raise ScanError(
        label,
        f"coordinates span {extent:,.0f} units{where}; treereg expects metres and this looks like {unit}: "
        f"convert the file to metres (scale the coordinates by {f:g}, which makes the scan span {seen}) "
        "and read it again",
    )


def _drop_non_finite(path: Path, pts: np.ndarray) -> np.ndarray:
    finite = np.isfinite(pts).all(axis=1)
    n_bad = int(len(pts) - finite.sum())
    if n_bad == 0:
        return pts
    if n_bad == len(pts):
        raise ScanError(str(path), f"all {n_bad} points have NaN or infinite coordinates; nothing is left")
    warnings.warn(
        f"{path}: dropped {n_bad} of {len(pts)} points with NaN or infinite coordinates",
        ScanWarning,
        stacklevel=3,
    )
    return np.ascontiguousarray(pts[finite])


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
        arr = np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        raise ScanError(str(path), f"not a readable .npy array ({e})") from None
    return _as_xyz(path, arr, "the array")


def _read_npz(path: Path) -> np.ndarray:
    try:
        with np.load(path, allow_pickle=False) as z:
            keys = list(z.keys())
            if not keys:
                raise ScanError(str(path), "the .npz archive holds no arrays")
            key = "points" if "points" in keys else keys[0]
            arr = z[key]
    except ScanError:
        raise
    except (ValueError, OSError, EOFError) as e:
        raise ScanError(str(path), f"not a readable .npz archive ({e})") from None
    return _as_xyz(path, arr, f"array {key!r}")


def _read_ply(path: Path) -> np.ndarray:
    import trimesh

    try:
        geom = trimesh.load(path, file_type="ply", process=False)
    except Exception as e:  # trimesh raises many types for malformed files
        raise ScanError(str(path), f"not a readable PLY file ({type(e).__name__}: {e})") from None
    vertices = getattr(geom, "vertices", None)
    if vertices is None or len(vertices) == 0:
        raise ScanError(str(path), "the PLY file holds no points (no vertex element)")
    return _as_xyz(path, np.asarray(vertices), "the vertex element")


def _read_las(path: Path) -> np.ndarray:
    import laspy

    try:
        with laspy.open(path) as reader:
            n = int(reader.header.point_count)
            if n == 0:
                raise ScanError(str(path), "the LAS/LAZ file holds no points")
            out = np.empty((n, 3), dtype=np.float64)
            i = 0
            # Chunks keep memory bounded: only x, y, z of the whole file are ever held.
            for chunk in reader.chunk_iterator(_LAS_CHUNK):
                m = len(chunk)
                out[i : i + m, 0] = chunk.x
                out[i : i + m, 1] = chunk.y
                out[i : i + m, 2] = chunk.z
                i += m
    except ScanError:
        raise
    except Exception as e:  # laspy / lazrs raise their own types for bad files
        raise ScanError(str(path), f"not a readable LAS/LAZ file ({type(e).__name__}: {e})") from None
    return out[:i]


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


def _sniff(path: Path, gzipped: bool) -> tuple[str | None, int]:
    """Delimiter (None = whitespace) and the number of lines to skip before the data.

    Comment lines ('#', '//') and blank lines may come first; then at most one header line.
    """
    try:
        with _open_text(path, gzipped) as fh:
            head = [fh.readline(1 << 16) for _ in range(64)]  # bounded, even for a binary file
    except (OSError, EOFError, gzip.BadGzipFile) as e:
        raise ScanError(str(path), f"cannot read the file ({e})") from None
    head = [h for h in head if h]
    lineno = 0
    while lineno < len(head) and _is_comment(head[lineno]):
        lineno += 1
    if lineno == len(head):
        raise ScanError(str(path), "the file holds no points (only blank or comment lines)")
    first = head[lineno]
    delimiter = "," if "," in first else (";" if ";" in first else None)
    skip = lineno
    if _is_header(_split(first, delimiter)):
        skip += 1  # one header line ("x y z", "X,Y,Z,intensity", ...)
        rest = [h for h in head[skip:] if not _is_comment(h)]
        if rest:
            # the delimiter is better read off a data line than off the header
            delimiter = "," if "," in rest[0] else (";" if ";" in rest[0] else None)
    return delimiter, skip


def _read_text(path: Path, gzipped: bool) -> np.ndarray:
    delimiter, skip = _sniff(path, gzipped)
    try:
        with _open_text(path, gzipped) as fh:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # numpy warns "input contained no data"; handled below
                pts = np.loadtxt(
                    fh, dtype=np.float64, comments=("#", "//"), delimiter=delimiter,
                    skiprows=skip, usecols=(0, 1, 2), ndmin=2,
                )
    except ValueError:
        raise ScanError(str(path), _first_bad_line(path, gzipped, delimiter, skip)) from None
    except (OSError, EOFError, gzip.BadGzipFile) as e:
        raise ScanError(str(path), f"cannot read the file ({e})") from None
    if pts.shape[0] == 0:
        raise ScanError(str(path), "the file holds no points (only a header)")
    return pts


def _first_bad_line(path: Path, gzipped: bool, delimiter: str | None, skip: int) -> str:
    """Describe the first line numpy could not parse. Runs only after a parse error, and stops at
    the first bad line, so the Python loop is never paid on a good file."""
    with _open_text(path, gzipped) as fh:
        for lineno, line in enumerate(fh, start=1):
            if lineno <= skip or _is_comment(line):
                continue
            body = line.split("#")[0]
            fields = _split(body, delimiter)
            if len(fields) < 3:
                sep = "commas" if delimiter == "," else (f"{delimiter!r}" if delimiter else "spaces")
                return (f"line {lineno} has {len(fields)} column(s) ({line.strip()[:60]!r}); "
                        f"x y z are needed in the first three columns, separated by {sep}")
            for col, f in enumerate(fields[:3], start=1):
                if not _is_number(f):
                    return (f"line {lineno}, column {col}: {f!r} is not a number "
                            f"(the line reads {line.strip()[:60]!r})")
    return "the text could not be parsed as x y z numbers"


# ---- writing -----------------------------------------------------------------------------------
def write_scan(path: str | Path, points_or_scan: np.ndarray | Scan, dtype: str = "float64") -> Path:
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
    if ext == ".ply":
        if dtype not in ("float64", "float32"):
            raise ValueError(f"dtype must be 'float64' or 'float32', got {dtype!r}")
        write_atomic(path, lambda tmp: _write_ply(tmp, pts, dtype))
    else:
        write_atomic(path, lambda tmp: _write_las(tmp, pts, compress=ext == ".laz"))
    return path


def _write_ply(path: Path, pts: np.ndarray, dtype: str) -> None:
    ply_type = "double" if dtype == "float64" else "float"
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment written by treereg\n"
        f"element vertex {len(pts)}\n"
        f"property {ply_type} x\nproperty {ply_type} y\nproperty {ply_type} z\nend_header\n"
    )
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(np.ascontiguousarray(pts, dtype=np.dtype(dtype).newbyteorder("<")).tobytes())


def _write_las(path: Path, pts: np.ndarray, compress: bool) -> None:
    import laspy

    header = laspy.LasHeader(point_format=0, version="1.2")
    header.scales = np.full(3, LAS_SCALE_M)
    # Offset at the (rounded) minimum keeps the int32 range for clouds far from the origin.
    header.offsets = np.floor(pts.min(axis=0)) if len(pts) else np.zeros(3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    with open(path, "wb") as fh:
        las.write(fh, do_compress=compress, laz_backend=laspy.LazBackend.Lazrs if compress else None)
