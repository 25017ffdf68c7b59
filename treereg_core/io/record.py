"""`ScanRecord`: one scan as a file holds it, before it becomes a `Scan`.

Single-scan formats (PLY, LAS, XYZ, NPY) give one record with the identity pose; E57 and PTX give
one record per scan in the file, each with the pose the file carries and, where the format has
them, the row/column grid (which gives the exact angular step) and the return numbers (which
let several returns per pulse be kept or dropped).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Keep only the first return of each pulse, or every return.
RETURNS = ("first", "all")


@dataclass(frozen=True, eq=False)
class ScanRecord:
    """One scan of a file.

    name : the scan's name in the file (E57 `name`), or `<file stem>#<k>` (k from 1) when it has
        none, or the file's base name for single-scan formats.
    points : N x 3 float64 metres, as stored: the scan's own frame for E57 and PTX.
    pose : 4 x 4 T_file_scan, the pose the file gives the scan (identity when it gives none).
    grid : (row, col) integer indices per point, or None.
    return_index : 0-based return number per point (0 = first return of its pulse), or None.
    """

    name: str
    points: np.ndarray
    pose: np.ndarray
    grid: tuple[np.ndarray, np.ndarray] | None = None
    return_index: np.ndarray | None = None

    def select(self, keep: np.ndarray) -> "ScanRecord":
        """The same record with only the points where `keep` is True."""
        grid = None if self.grid is None else (self.grid[0][keep], self.grid[1][keep])
        ret = None if self.return_index is None else self.return_index[keep]
        return ScanRecord(self.name, self.points[keep], self.pose, grid, ret)

    def with_returns(self, returns: str) -> "ScanRecord":
        """Keep the first return of each pulse (`returns="first"`) or all of them."""
        if returns not in RETURNS:
            raise ValueError(f"returns must be one of {RETURNS}, got {returns!r}")
        if returns == "all" or self.return_index is None:
            return self
        return self.select(self.return_index == 0)
