"""Reading and writing scans: PLY, LAS/LAZ, XYZ/TXT/CSV (optionally gzipped), NPY/NPZ, and the
multi-scan exchange formats E57 and PTX (`io.e57`, `io.ptx`).

`read_scans(path)` gives every scan a file holds (one for most formats, any number for E57/PTX),
each in its scanner's own frame with the pose the file (or `scanner_position`) gives it.
Every point reader returns N x 3 float64 metres; every problem a user has to fix raises
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
from .record import RETURNS, ScanRecord
from ..errors import ScanError
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
_PLY_CHUNK = 2_000_000


class ScanWarning(UserWarning):
    """Something in a scan file was repaired (e.g. rows with NaN dropped); the message says what."""


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
        N x 3 float64. Rows with NaN or infinite coordinates are dropped with a `ScanWarning`.

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
    pts = _drop_non_finite(path, pts)
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

    Rows with NaN or infinite coordinates are dropped (with a `ScanWarning`); with `check_units`,
    millimetre-looking coordinates are refused (`check_metres`).
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
        finite = np.isfinite(r.points).all(axis=1)
        if not finite.all():
            _drop_non_finite(Path(label), r.points)  # warns, or raises when nothing is left
            r = r.select(finite)
        if len(r.points) == 0:
            raise ScanError(label, "the scan holds no valid points")
        if check_units:
            # Points spread like a scene seen from the origin: their distance from it tells the unit
            # too. Far and close together (georeferenced) is `record_to_scan`'s to say.
            check_metres(r.points, label, scanner_frame=_seen_from_origin(r.points))
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
        pts, shift = to_scanner_frame(pts, scanner_position)
        pose = pose @ shift
    else:
        far = far_from_origin(pts)
        if far is not None:
            raise ScanError(str(source), far_message(far))
    scan = Scan.from_points(pts, name=record.name, source=source, angular_step_deg=angular_step_deg,
                            min_points=min_points, pose=pose, grid=record.grid)
    if scan.step.low and one_sided(pts):
        warnings.warn(
            f"{source}: the points show no regular angular grid (step estimate {scan.step.describe()}) and all lie on "
            "one side of the origin: if the scan is not in its scanner's frame, give --scanner-position X Y Z; "
            "if it is, give the instrument's steps with --angular-step H V",
            ScanWarning, stacklevel=2)
    elif scan.step.low:
        warnings.warn(f"{source}: the angular step estimate is unreliable ({scan.step.describe()}); "
                      "give the instrument's steps with --angular-step H V", ScanWarning, stacklevel=2)
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


def _seen_from_origin(points: np.ndarray) -> bool:
    """True when the points spread like a scene seen from the origin (a scan in another unit), not
    like a scan far from the origin with its points close together (georeferenced coordinates)."""
    _, spread, rng = _size(points)
    return spread >= MIN_SPREAD_TO_RANGE * rng


def check_metres(points: np.ndarray, label: str, scanner_frame: bool = False) -> None:
    """Raise `ScanError`, naming the likely unit and its factor, when the points are not in metres.

    A tree cloud in metres spans at most `MAX_EXTENT_M` (and, seen from its scanner, lies within
    `MAX_RANGE_M`). Beyond that, the unit is the one (centimetres or millimetres) whose factor brings
    the extent (and the range) closest to a typical tree scan's; the message gives the sizes in
    metres that factor would make, so the user can check. The extent does not change with a shift,
    so georeferenced clouds in metres pass (`record_to_scan` tests a scan's frame).
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
    if np.isfinite(pts).all():
        return pts
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


#: PLY scalar types -> numpy (the PLY spec's names and their sized aliases).
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def _ply_binary_layout(path: Path) -> tuple[int, int, np.dtype] | None:
    """(byte offset of the vertex data, vertex count, vertex record dtype) of a binary PLY whose
    first element is the vertex element with scalar properties only; None for any other layout
    (ASCII, lists before the vertices, ...), which the general reader handles."""
    with open(path, "rb") as fh:
        if fh.read(4) != b"ply\n":
            return None
        lines: list[str] = []
        while True:
            raw = fh.readline(1 << 12)
            if not raw:
                return None
            line = raw.decode("ascii", errors="replace").strip()
            if line == "end_header":
                break
            lines.append(line)
            if len(lines) > 500:
                return None
        offset = fh.tell()
    fmt = next((ln.split()[1] for ln in lines if ln.startswith("format ")), "")
    order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt)
    elements = [ln.split() for ln in lines if ln.startswith(("element ", "property "))]
    if order is None or not elements or elements[0][:2] != ["element", "vertex"] or len(elements[0]) != 3:
        return None
    props: list[tuple[str, str]] = []
    for e in elements[1:]:
        if e[0] == "element":
            break
        if len(e) != 3 or e[1] not in _PLY_TYPES:
            return None  # a list property: the general reader
        props.append((e[2], order + _PLY_TYPES[e[1]]))
    names = [n for n, _ in props]
    if not {"x", "y", "z"} <= set(names) or len(set(names)) != len(names):
        return None
    return offset, int(elements[0][2]), np.dtype(props)


def _read_ply(path: Path) -> np.ndarray:
    try:
        layout = _ply_binary_layout(path)
    except (OSError, ValueError):
        layout = None
    if layout is not None:
        return _read_ply_binary(path, *layout)
    import trimesh

    try:
        geom = trimesh.load(path, file_type="ply", process=False)
    except Exception as e:  # trimesh raises many types for malformed files
        raise ScanError(str(path), f"not a readable PLY file ({type(e).__name__}: {e})") from None
    vertices = getattr(geom, "vertices", None)
    if vertices is None or len(vertices) == 0:
        raise ScanError(str(path), "the PLY file holds no points (no vertex element)")
    return _as_xyz(path, np.asarray(vertices), "the vertex element")


def _read_ply_binary(path: Path, offset: int, n: int, record: np.dtype) -> np.ndarray:
    """x, y, z of a binary PLY's vertices, memory-mapped and copied once, in chunks, into float64
    (other properties are never loaded: one full-resolution copy of the scan, no more)."""
    if n <= 0:
        raise ScanError(str(path), "the PLY file holds no points (its vertex element is empty)")
    have = (path.stat().st_size - offset) // record.itemsize
    if have < n:
        raise ScanError(str(path), f"the PLY file is truncated: its header announces {n} points, "
                                   f"the file holds {have}")
    vertices = np.memmap(path, dtype=record, mode="r", offset=offset, shape=(n,))
    out = np.empty((n, 3), dtype=np.float64)
    for a in range(0, n, _PLY_CHUNK):
        chunk = vertices[a:a + _PLY_CHUNK]
        for k, name in enumerate("xyz"):
            out[a:a + len(chunk), k] = chunk[name]
    del vertices
    return out


def _read_las(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    import laspy

    try:
        with laspy.open(path) as reader:
            n = int(reader.header.point_count)
            if n == 0:
                raise ScanError(str(path), "the LAS/LAZ file holds no points")
            out = np.empty((n, 3), dtype=np.float64)
            ret = np.empty(n, dtype=np.int16)
            i = 0
            # Chunks keep memory bounded: only x, y, z (and the return number) are ever held.
            for chunk in reader.chunk_iterator(_LAS_CHUNK):
                m = len(chunk)
                out[i : i + m, 0] = chunk.x
                out[i : i + m, 1] = chunk.y
                out[i : i + m, 2] = chunk.z
                ret[i : i + m] = np.asarray(chunk.return_number, dtype=np.int16) - 1
                i += m
    except ScanError:
        raise
    except Exception as e:  # laspy / lazrs raise their own types for bad files
        raise ScanError(str(path), f"not a readable LAS/LAZ file ({type(e).__name__}: {e})") from None
    ret = ret[:i]
    # Writers that do not number returns leave 0 (-1 here): then there is nothing to select on.
    return out[:i], (ret if (ret >= 0).all() and (ret > 0).any() else None)


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


def _sniff(path: Path, gzipped: bool) -> tuple[str | None, int, int | None]:
    """Delimiter (None = whitespace), the number of lines to skip before the data, and the column
    holding the return number (None when no header or comment line names one).

    Comment lines ('#', '//') and blank lines may come first; then at most one header line.
    """
    try:
        with _open_text(path, gzipped) as fh:
            head = [fh.readline(1 << 16) for _ in range(64)]  # bounded, even for a binary file
    except (OSError, EOFError, gzip.BadGzipFile) as e:
        raise ScanError(str(path), f"cannot read the file ({e})") from None
    head = [h for h in head if h]
    lineno = 0
    ret_col = None
    while lineno < len(head) and _is_comment(head[lineno]):
        ret_col = _return_column(head[lineno].strip().lstrip("#/ ")) if ret_col is None else ret_col
        lineno += 1
    if lineno == len(head):
        raise ScanError(str(path), "the file holds no points (only blank or comment lines)")
    first = head[lineno]
    delimiter = "," if "," in first else (";" if ";" in first else None)
    skip = lineno
    if _is_header(_split(first, delimiter)):
        skip += 1  # one header line ("x y z", "X,Y,Z,intensity", ...)
        ret_col = _return_column(first) if ret_col is None else ret_col
        rest = [h for h in head[skip:] if not _is_comment(h)]
        if rest:
            # the delimiter is better read off a data line than off the header
            delimiter = "," if "," in rest[0] else (";" if ";" in rest[0] else None)
    return delimiter, skip, ret_col


def _return_column(line: str) -> int | None:
    """Index of the column a header line names as the return number (see `RETURN_COLUMNS`)."""
    names = [f.strip().lower() for f in line.split(";")[0].replace(",", " ").split()]
    hit = [i for i, n in enumerate(names) if n in RETURN_COLUMNS]
    return hit[0] if hit and names[:3] == ["x", "y", "z"] else None


def _read_text(path: Path, gzipped: bool) -> tuple[np.ndarray, np.ndarray | None]:
    delimiter, skip, ret_col = _sniff(path, gzipped)
    cols = (0, 1, 2) if ret_col is None else (0, 1, 2, ret_col)
    try:
        with _open_text(path, gzipped) as fh:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # numpy warns "input contained no data"; handled below
                pts = np.loadtxt(
                    fh, dtype=np.float64, comments=("#", "//"), delimiter=delimiter,
                    skiprows=skip, usecols=cols, ndmin=2,
                )
    except ValueError:
        raise ScanError(str(path), _first_bad_line(path, gzipped, delimiter, skip)) from None
    except (OSError, EOFError, gzip.BadGzipFile) as e:
        raise ScanError(str(path), f"cannot read the file ({e})") from None
    if pts.shape[0] == 0:
        raise ScanError(str(path), "the file holds no points (only a header)")
    if ret_col is None:
        return pts, None
    ret = pts[:, 3]
    ok = np.isfinite(ret) & (ret >= 1)
    return np.ascontiguousarray(pts[:, :3]), (ret.astype(np.int16) - 1 if ok.all() else None)


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
def write_scan(path: str | Path, points_or_scan: np.ndarray | Scan, dtype: str = "float64",
               scan_id: np.ndarray | None = None) -> Path:
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
    tagged = {} if ids is None else {"scan_id": ids}
    if ext == ".ply":
        if dtype not in ("float64", "float32"):
            raise ValueError(f"dtype must be 'float64' or 'float32', got {dtype!r}")
        write_atomic(path, lambda tmp: _write_ply(tmp, pts, dtype, **tagged))
    else:
        write_atomic(path, lambda tmp: _write_las(tmp, pts, compress=ext == ".laz", **tagged))
    return path


def _write_ply(path: Path, pts: np.ndarray, dtype: str, scan_id: np.ndarray | None = None) -> None:
    ply_type = "double" if dtype == "float64" else "float"
    fields = [("x", dtype), ("y", dtype), ("z", dtype)]
    extra = ""
    if scan_id is not None:
        fields.append(("scan_id", "uint16"))
        extra = "property ushort scan_id\n"
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment written by treereg\n"
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


def _write_las(path: Path, pts: np.ndarray, compress: bool, scan_id: np.ndarray | None = None) -> None:
    import laspy

    header = laspy.LasHeader(point_format=0, version="1.2")
    header.scales = np.full(3, LAS_SCALE_M)
    # Offset at the (rounded) minimum keeps the int32 range for clouds far from the origin.
    header.offsets = np.floor(pts.min(axis=0)) if len(pts) else np.zeros(3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    if scan_id is not None:
        las.point_source_id = scan_id
    with open(path, "wb") as fh:
        las.write(fh, do_compress=compress, laz_backend=laspy.LazBackend.Lazrs if compress else None)
