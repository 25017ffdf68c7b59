"""Frames: is a scan in its scanner's frame, and if not, moving it there.

Registration needs each scan in its scanner's own frame: the angular grid is regular only there
(projection, step estimation), and coordinates stay small enough for the float32 steps (a UTM
easting of 500 000 m keeps only ~3 cm in float32). Files often come in a project or map frame
instead. With the scanner's position in that frame (from the user, or the pose an E57/PTX file
carries) we shift the points to a local origin at the scanner, in float64, before anything else,
and keep the shift as the scan's pose `T_user_scan`; transforms are mapped back through it.

Without a position we can only detect the problem and say what to give: a scan whose nearest
points are kilometres from the origin is not in its scanner frame; one whose points all lie on
one side of the origin *and* show no angular grid probably is not either.
"""

from __future__ import annotations

import numpy as np

#: A scanner sees something nearer than this (m): a scan whose 1st-percentile range exceeds it is
#: not in its scanner's frame (georeferenced or project coordinates).
FAR_M = 1000.0
#: Points sampled for the checks.
_SAMPLE = 50_000


def translation(position: np.ndarray | tuple[float, float, float]) -> np.ndarray:
    """4 x 4 translation by `position`."""
    T = np.eye(4)
    T[:3, 3] = np.asarray(position, dtype=np.float64)
    return T


def far_from_origin(points: np.ndarray) -> float | None:
    """The 1st-percentile distance of the points from the origin when it exceeds `FAR_M`, else None."""
    sample = points[:: max(1, len(points) // _SAMPLE)]
    near = float(np.quantile(np.linalg.norm(sample, axis=1), 0.01)) if len(sample) else 0.0
    return near if near > FAR_M else None


def one_sided(points: np.ndarray) -> bool:
    """True when the origin lies outside the points' horizontal bounding box (all on one side).

    A single tree cut out of a station is one-sided too; combined with an angular step that the
    points do not show, it says the origin is not where the scanner stood.
    """
    lo, hi = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    return bool(np.any(lo > 0.0) or np.any(hi < 0.0))


def to_scanner_frame(points: np.ndarray, position: np.ndarray | tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Points moved so the scanner at `position` (in the points' frame) is the origin, and the
    4 x 4 T_user_scan that maps them back. Float64 throughout: millimetres survive UTM sizes."""
    p = np.asarray(position, dtype=np.float64).reshape(3)
    return np.asarray(points, dtype=np.float64) - p, translation(p)


def far_message(distance_m: float) -> str:
    """What to tell the user about a scan whose points lie `distance_m` from the origin."""
    return (f"the points lie {distance_m:,.0f} m or more from the origin, so the scan is not in its scanner's "
            "frame (georeferenced or project coordinates); give the scanner's position in the file's "
            "coordinates with --scanner-position X Y Z (once per scan, in order)")
