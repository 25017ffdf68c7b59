"""Which point a click meant: the point nearest a ray from the camera through the clicked pixel."""

from __future__ import annotations

import numpy as np


def nearest_to_ray(points: np.ndarray, origin: np.ndarray, direction: np.ndarray,
                   max_angle_deg: float = 1.0) -> int | None:
    """Index of the point a click along the ray meant, or None when no point is near it.

    Points whose direction from `origin` lies within `max_angle_deg` of the ray are candidates (an
    angle, so far points get the same tolerance on screen as near ones); of those the nearest to
    the camera wins (the one in front).

    Examples
    --------
    >>> pts = np.array([[0.0, 0.0, 5.0], [0.0, 0.02, 10.0], [1.0, 0.0, 3.0]])
    >>> nearest_to_ray(pts, np.zeros(3), np.array([0.0, 0.0, 1.0]))
    0
    >>> nearest_to_ray(pts, np.zeros(3), np.array([0.0, 1.0, 0.0])) is None
    True
    """
    pts = np.asarray(points, dtype=float)
    if len(pts) == 0:
        return None
    d = np.asarray(direction, dtype=float)
    d = d / np.linalg.norm(d)
    rel = pts - np.asarray(origin, dtype=float)
    along = rel @ d
    perp = np.linalg.norm(rel - np.outer(along, d), axis=1)
    ok = (along > 0) & (perp <= along * np.tan(np.radians(max_angle_deg)))
    if not ok.any():
        return None
    cand = np.flatnonzero(ok)
    return int(cand[np.argmin(along[cand])])
