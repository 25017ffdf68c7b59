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


#: Largest |R^T R - I| entry accepted in a pose a file's header gives (decimal text keeps about six
#: digits); within it the rotation is snapped to the nearest exact one, beyond it the pose scales or shears.
POSE_TOL = 1e-4


class NotRigid(ValueError):
    """A pose a file gives is not a rigid motion; the message completes "the pose ..."."""


def rigid_pose(T: np.ndarray) -> np.ndarray:
    """`T` (4 x 4 T_file_scan from a file's header) as an exact rigid motion, or `NotRigid` saying why
    not: a pose that scales, shears or mirrors would move the points off their true shape, and every
    transform computed from it would carry that."""
    T = np.asarray(T, dtype=np.float64)
    if not np.isfinite(T).all():
        raise NotRigid("holds NaN or infinite numbers")
    if np.abs(T[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-9:
        raise NotRigid(f"has the last row {' '.join(f'{v:g}' for v in T[3])}, not 0 0 0 1")
    R = T[:3, :3]
    dev = float(np.abs(R.T @ R - np.eye(3)).max())
    if dev > POSE_TOL:
        raise NotRigid(f"is not rigid: its rotation part scales or shears the scan (|R^T R - I| = {dev:.2g}); "
                       "export the scan with a rigid pose (rotation and translation only)")
    if np.linalg.det(R) < 0:
        raise NotRigid("is a mirror (determinant -1), not a rotation; export the scan with a rigid pose")
    if dev <= 1e-12:
        return T
    U, _, Vt = np.linalg.svd(R)
    out = T.copy()
    out[:3, :3] = U @ Vt  # the nearest exact rotation: transforms written from it pass the 1e-6 check
    return out
