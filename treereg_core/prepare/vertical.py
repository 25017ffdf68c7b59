"""Whether a scan's vertical is its z: a scanner tilted, mounted upside down, or a scan exported y-up.

Every stage takes z as up (the ground plane, the stem at breast height, the slices, the projection's
turn about z). The prepare stage levels such a scan when its evidence is clear (`prepare.level`, which
uses this module's ground and stem); one it leaves as given (no stem to tell a slope from a tilt,
levelling turned off) registers as if it showed another tree, and its verdict must say why.

The ground says where up is: a terrestrial scanner stands 0.3-3.5 m above it, so the plane holding
most points within that distance of the scanner (the origin of the scan's frame) is the ground, and
its normal towards the scanner is the scan's up; nothing lies beyond the ground (a plane through the
tree has tree on both sides), and it covers an area, filled (a plane touching a tree's side, in a
cloud that is not a scan, holds a strip of stem and scattered twigs). A steep slope tilts that plane too, but not the
stem, which stands plumb on any slope: under a ground tilted moderately from z the stem's axis is
the vertical (along z: a slope, nothing said); upside down or on its side (past 45 deg) no slope explains.
Without such a plane (a tree cut out of a larger cloud) nothing is said.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Points the search looks at (a strided subset: a plane needs no more).
_SAMPLE = 60_000
#: The scanner stands this far above its ground (m): a plane nearer or farther is not its ground.
_HEIGHT_M = (0.3, 3.5)
#: Points within this distance of a plane lie on it (m), and the ground holds at least this share.
_TOL_M, _MIN_SHARE = 0.05, 0.05
#: At most this share of the points lies more than _BEYOND_M beyond the ground (noise, mixed pixels).
_BEYOND_SHARE, _BEYOND_M = 0.02, 0.3
#: A vertical this far from z (deg) is named; below it a scanner counts as levelled.
_OFF_DEG = 10.0
#: The ground spans at least this much each way (m), its cells of this size filling this share of it.
_SPAN_M, _CELL_M, _FILL = 2.0, 0.25, 0.3
#: The stem, 0.5-3 m above the ground, within this distance of its axis (m).
_STEM_BAND_M, _STEM_RADIUS_M = (0.5, 3.0), 0.6


@dataclass(frozen=True)
class Vertical:
    """A scan's up as its ground (and stem) show it.

    up : unit vector in the scan's frame (the ground's normal towards the scanner), or None (no ground
        found near the scanner).
    off_deg : how far the scan's vertical is from z (deg): the stem's axis where it was traced under a
        ground tilted from z, else `up` (NaN without a ground).
    stem_off_deg : angle between the stem's axis and z, when the stem was traced (else NaN).
    note : the sentence a verdict gives ("the scan's vertical is 25° off z (a scanner not levelled?):
        export it z-up and levelled"), "" when z is up or nothing can be said.
    """

    up: np.ndarray | None
    off_deg: float
    stem_off_deg: float
    note: str


def _ground_plane(pts: np.ndarray, rng: np.random.Generator, iterations: int = 400) -> tuple[np.ndarray, float] | None:
    """The plane (unit normal towards the origin, distance of the origin from it) holding most points
    among planes 0.3-3.5 m from the origin with (almost) nothing beyond them, refitted on its points;
    None without one."""
    if len(pts) < 50:
        return None
    idx = rng.integers(0, len(pts), size=(iterations, 3))
    a, b, c = pts[idx[:, 0]], pts[idx[:, 1]], pts[idx[:, 2]]
    nrm = np.cross(b - a, c - a)
    length = np.linalg.norm(nrm, axis=1)
    good = length > 1e-9
    nrm, a = nrm[good] / length[good, None], a[good]
    d = -(nrm * a).sum(axis=1)  # n.x + d = 0; d is the origin's signed distance
    sign = np.where(d < 0, -1.0, 1.0)
    nrm, d = nrm * sign[:, None], d * sign  # the origin on the positive side
    near = (d >= _HEIGHT_M[0]) & (d <= _HEIGHT_M[1])
    if not near.any():
        return None
    nrm, d = nrm[near], d[near]
    signed = pts @ nrm.T + d
    counts = np.where((signed < -_BEYOND_M).mean(axis=0) <= _BEYOND_SHARE, (np.abs(signed) < _TOL_M).sum(axis=0), 0)
    h = int(np.argmax(counts))
    if counts[h] < max(50, _MIN_SHARE * len(pts)):
        return None
    on = np.abs(signed[:, h]) < _TOL_M
    centre = pts[on].mean(axis=0)
    normal = np.linalg.svd(pts[on] - centre, full_matrices=False)[2][2]
    dist = -float(normal @ centre)
    if dist < 0:  # towards the scanner: the side the scanner stands on is up
        normal, dist = -normal, -dist
    if not _HEIGHT_M[0] <= dist <= _HEIGHT_M[1] or np.mean(pts @ normal + dist < -_BEYOND_M) > _BEYOND_SHARE:
        return None
    return (normal, dist) if _covers(pts[on], normal) else None


def _covers(on: np.ndarray, normal: np.ndarray) -> bool:
    """Whether the points on a plane cover an area as ground does: at least `_SPAN_M` each way (5th to
    95th percentile, in the plane), its `_CELL_M` cells filling `_FILL` of that box."""
    e1 = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    uv = np.c_[on @ e1, on @ np.cross(normal, e1)]
    lo, hi = np.percentile(uv, 5, axis=0), np.percentile(uv, 95, axis=0)
    if (hi - lo).min() < _SPAN_M:
        return False
    inside = uv[((uv >= lo) & (uv <= hi)).all(axis=1)]
    cells = np.unique(np.floor((inside - lo) / _CELL_M).astype(np.int64), axis=0)
    return bool(len(cells) >= _FILL * np.prod(np.ceil((hi - lo) / _CELL_M)))


def _stem_axis(pts: np.ndarray, up: np.ndarray, height: float) -> np.ndarray | None:
    """The axis of the stem standing on the ground (unit, pointing away from it), from the points
    0.5-3 m above the ground near the densest column; None when no slender stem is there."""
    h = pts @ up + height  # height above the ground
    band = pts[(h > _STEM_BAND_M[0]) & (h < _STEM_BAND_M[1])]
    if len(band) < 50:
        return None
    # The densest 0.25 m column across the ground (in the plane's own axes) holds the stem.
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    uv = np.c_[band @ e1, band @ e2]
    ij = np.floor(uv / 0.25).astype(np.int64)
    ij -= ij.min(axis=0)
    key = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    centre = np.median(band[key == np.bincount(key).argmax()], axis=0)
    axis = up
    for _ in range(3):  # a stem leaning from `up` is followed along its own axis
        rel = band - centre
        along = rel @ axis
        off = np.linalg.norm(rel - along[:, None] * axis, axis=1)
        stem = band[off < _STEM_RADIUS_M]
        if len(stem) < 30:
            return None
        centre = stem.mean(axis=0)
        s, v = np.linalg.svd(stem - centre, full_matrices=False)[1:]
        if s[0] < 2.0 * s[1]:  # not slender: a bush or a wall, not a stem
            return None
        axis = v[0] if v[0] @ up > 0 else -v[0]
    return axis


def _deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(float(a @ b), -1.0, 1.0))))


def scan_vertical(points: np.ndarray, seed: int = 0) -> Vertical:
    """The scan's up, from its ground near the scanner and its stem (see the module doc)."""
    pts = np.asarray(points, dtype=float)
    pts = pts[:: max(1, len(pts) // _SAMPLE)]
    z = np.array([0.0, 0.0, 1.0])
    plane = _ground_plane(pts, np.random.default_rng(seed))
    if plane is None:
        return Vertical(None, float("nan"), float("nan"), "")
    up, height = plane
    off = _deg(up, z)
    axis = _stem_axis(pts, up, height) if off >= _OFF_DEG else None
    stem_off = _deg(axis, z) if axis is not None else float("nan")
    if off < _OFF_DEG:
        return Vertical(up, off, stem_off, "")
    if off > 135.0:
        why = "upside down?"
    elif off > 45.0:
        k = int(np.argmax(np.abs(up)))
        why = f"{'xyz'[k]}-up?" if k < 2 and abs(up[k]) > 0.9 else "on its side?"
    elif axis is not None:  # the stem stands plumb on any slope: it is the vertical
        if stem_off < _OFF_DEG:  # steep ground under a levelled scanner
            return Vertical(up, off, stem_off, "")
        why, off = "a scanner not levelled?", stem_off
    else:
        return Vertical(up, off, stem_off, f"the ground under the scanner is tilted {off:.0f}° from z and no stem was "
                        "found to tell a tilted scanner from a slope: if the scanner was not levelled, export the "
                        "scan z-up and levelled")
    return Vertical(up, off, stem_off, f"the scan's vertical is {off:.0f}° off z ({why}): export it z-up and levelled")
