"""The merged registered cloud: every registered scan's points in the reference frame, each point
tagged with the number of the scan it came from (1 = the reference, in the order the scans were
given: the numbers people read in the app and the CLI's output).

PLY carries the number as a `scan_id` vertex property, LAS/LAZ as the standard `point_source_id`,
so CloudCompare, PDAL or lidR can colour or split the merged cloud by scan; each number's scan name
is in the PLY header's comments and a LAS/LAZ VLR.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from ..geometry.rigid import apply_transform
from ..scan import Scan
from .scans import write_scan


#: Beyond this coordinate (m) a float32 PLY would round points by more than ~0.1 mm: georeferenced
#: clouds are written in float64.
FLOAT32_LIMIT_M = 1000.0


def merged_cloud(scans: Sequence[Scan], transforms: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(N x 3 points in the reference's frame, N scan numbers) of the scans that have a transform.

    `transforms` are a transform file's matrices (`TransformFile.transforms`): each maps the scan's
    points as its file gives them (its pose applied to the scanner-frame points) onto the
    reference's points as its file gives them, so the merged cloud lies in the reference file's
    frame (georeferenced when that is). Scans without a transform (not registered, or not
    verified) are left out; their numbers are skipped, not reused.
    """
    parts, ids = [], []
    for i, scan in enumerate(scans):
        if scan.name not in transforms:
            continue
        T = np.asarray(transforms[scan.name], dtype=float) @ np.asarray(scan.pose, dtype=float)
        parts.append(apply_transform(T, scan.points))
        ids.append(np.full(scan.n_points, i + 1, dtype=np.uint16))
    if not parts:
        return np.empty((0, 3)), np.empty(0, dtype=np.uint16)
    return np.concatenate(parts, axis=0), np.concatenate(ids)


def write_merged(path: str | Path, scans: Sequence[Scan], transforms: Mapping[str, np.ndarray],
                 dtype: str = "float32") -> Path:
    """Write the merged cloud (PLY, LAS or LAZ by extension), atomically, with each point's scan
    number and the name of each number (`write_scan`'s `scan_names`). PLY coordinates are float32 by default (half the size, about a micrometre at tree
    distances), float64 when the cloud lies far from the origin (georeferenced)."""
    points, ids = merged_cloud(scans, transforms)
    if len(points) and np.abs(points).max() > FLOAT32_LIMIT_M:
        dtype = "float64"
    names = {i + 1: s.name for i, s in enumerate(scans) if s.name in transforms}
    return write_scan(path, points, dtype=dtype, scan_id=ids, scan_names=names)
