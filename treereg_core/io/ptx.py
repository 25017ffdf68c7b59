"""PTX (Leica's ASCII scan exchange format): one or more scans, each a header and a row/column grid.

Each scan starts with a ten-line header::

    <columns>
    <rows>
    st1 st2 st3        scanner position (after registration)
    sx1 sx2 sx3        scanner axis X
    sy1 sy2 sy3        scanner axis Y
    sz1 sz2 sz3        scanner axis Z
    r11 r12 r13 0      4 x 4 transform, row-vector convention: [x y z 1] @ M maps
    r21 r22 r23 0      a point of the scan into the registered frame
    r31 r32 r33 0
    tr1 tr2 tr3 1

followed by columns x rows lines `x y z intensity [r g b]`, column after column; a cell without a
return is written as 0 0 0. Points are stored in the scanner's own frame. The pose we keep is the
4 x 4 (transposed to our column-vector convention); when that is the identity but the scanner
lines are not, they are the pose (a PTX exported with a UCS at the scanner).
"""

from __future__ import annotations

import gzip
import io as _io
from itertools import islice
from pathlib import Path
from typing import TextIO

import numpy as np

from ..errors import ScanError
from .record import NotRigid, ScanRecord, rigid_pose

_HEADER_LINES = 10


def _numbers(line: str, n: int, what: str, path: Path, lineno: int) -> list[float]:
    parts = line.replace(",", " ").split()
    try:
        values = [float(v) for v in parts[:n]]
    except ValueError:
        values = []
    if len(values) != n:
        raise ScanError(str(path), f"line {lineno}: expected {n} numbers ({what}), got {line.strip()[:60]!r}")
    return values


def _pose(header: list[str], path: Path, first_line: int) -> np.ndarray:
    nums = [_numbers(header[2 + k], 3, "scanner position and axes", path, first_line + 2 + k) for k in range(4)]
    M = np.array([_numbers(header[6 + k], 4, "transformation matrix row", path, first_line + 6 + k)
                  for k in range(4)])
    T = M.T  # PTX multiplies row vectors from the left: [p 1] @ M
    if np.allclose(T, np.eye(4)):
        S = np.eye(4)
        S[:3, :3] = np.array(nums[1:4]).T  # axes X, Y, Z as columns
        S[:3, 3] = nums[0]
        T = S
    try:
        return rigid_pose(T)
    except NotRigid as e:  # refused here, not after a whole run that computed with it
        raise ScanError(str(path), f"lines {first_line + 2}-{first_line + 9}: the pose in the scan's header {e}") from None


def _open(path: Path) -> TextIO:
    if path.suffix.lower() == ".gz":
        return _io.TextIOWrapper(gzip.open(path, "rb"), encoding="utf-8", errors="replace")
    return open(path, encoding="utf-8", errors="replace")


def read_ptx(path: str | Path) -> list[ScanRecord]:
    """Every scan of a PTX file, in its own frame, with its pose and (row, col) grid.

    A single scan is named after the file; several are named `<stem>#1`, `<stem>#2`, ...
    Cells without a return (0 0 0) are dropped; the grid indices of the others are kept.

    Raises
    ------
    ScanError
        A malformed header or point line (the message gives the line number), or a file that ends
        before its grid is complete.
    """
    path = Path(path)
    records: list[tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray], tuple[int, int]]] = []
    lineno = 0
    try:
        with _open(path) as fh:
            while True:
                header = list(islice(fh, _HEADER_LINES))
                if not header or all(not h.strip() for h in header):
                    break
                if records and len(header[0].replace(",", " ").split()) > 1:
                    c, r = records[-1][3]
                    raise ScanError(str(path), f"line {lineno + 1}: a point line where the next scan's header should "
                                               f"start: scan {len(records)} holds more points than its header's "
                                               f"{c} x {r} grid; check the column and row counts in its header")
                if len(header) < _HEADER_LINES:
                    raise ScanError(str(path), f"line {lineno + len(header) + 1}: the file ends inside a scan header")
                cols = _numbers(header[0], 1, "number of columns", path, lineno + 1)[0]
                rows = _numbers(header[1], 1, "number of rows", path, lineno + 2)[0]
                if cols != int(cols) or rows != int(rows) or cols < 1 or rows < 1:
                    raise ScanError(str(path), f"line {lineno + 1}: the grid size must be two positive integers, got {cols:g} x {rows:g}")
                cols, rows = int(cols), int(rows)
                pose = _pose(header, path, lineno + 1)
                n = cols * rows
                lines = list(islice(fh, n))
                if len(lines) < n:
                    raise ScanError(str(path), f"scan {len(records) + 1}: the file ends after {len(lines)} of its "
                                               f"{cols} x {rows} = {n} points")
                try:
                    xyz = np.loadtxt(lines, dtype=np.float64, usecols=(0, 1, 2), ndmin=2)
                except ValueError as e:
                    raise ScanError(str(path), f"scan {len(records) + 1} (from line {lineno + _HEADER_LINES + 1}): "
                                               f"a point line is not x y z numbers ({e})") from None
                k = np.arange(n)
                valid = np.isfinite(xyz).all(axis=1) & np.any(xyz != 0.0, axis=1)  # 0 0 0: no return
                records.append((xyz[valid], pose, (k[valid] % rows, k[valid] // rows), (cols, rows)))
                lineno += _HEADER_LINES + n
    except (OSError, EOFError, gzip.BadGzipFile) as e:
        raise ScanError(str(path), f"cannot read the file ({e})") from None
    if not records:
        raise ScanError(str(path), "the PTX file holds no scans")
    stem = path.name.split(".")[0]
    names = [path.name] if len(records) == 1 else [f"{stem}#{k + 1}" for k in range(len(records))]
    return [ScanRecord(nm, pts, pose, grid) for nm, (pts, pose, grid, _) in zip(names, records)]


def write_ptx(path: str | Path, scans: list[tuple[np.ndarray, np.ndarray, int, int]]) -> Path:
    """Write scans as PTX (for tests and exchange): (grid points rows x cols x 3 with 0 0 0 for no
    return, pose T_file_scan, rows, cols) per scan; the grid is written column after column."""
    from .atomic import write_atomic

    def write(tmp: Path) -> None:
        with open(tmp, "w") as fh:
            for grid, T, rows, cols in scans:
                T = np.asarray(T, dtype=np.float64)
                fh.write(f"{cols}\n{rows}\n")
                fh.write(" ".join(repr(float(v)) for v in T[:3, 3]) + "\n")
                for ax in T[:3, :3].T:
                    fh.write(" ".join(repr(float(v)) for v in ax) + "\n")
                for row in T.T:
                    fh.write(" ".join(repr(float(v)) for v in row) + "\n")
                pts = np.asarray(grid, dtype=np.float64).reshape(rows, cols, 3).transpose(1, 0, 2).reshape(-1, 3)
                np.savetxt(fh, np.column_stack([pts, np.full(len(pts), 0.5)]), fmt="%.6f")

    return write_atomic(Path(path), write)
