"""Free-space consistency: does the target, placed by a transform, agree with what the reference
scanner saw?

A TLS station measures, along each ray, the first surface; space in front of it is empty. So a
target point mapped into the reference frame can be checked against the reference's own range
image: at its direction from the reference scanner, the reference saw

* a surface at the same range: the two stations agree there (consistent);
* a surface farther away: the point sits in space the reference saw through — a contradiction
  (a free-space violation, the telltale of a wrong registration or a different tree);
* a surface nearer: the point is hidden from the reference (occluded; says nothing);
* nothing at all: no evidence either way (outside its view, sky, dropouts).

Counting only where both stations could see the same place ("where both stations face it")
makes the measure independent of how much the two views overlap, unlike a nearest-neighbour
fitness. Edges are the weak spot: a ray grazing a stem's edge may return from behind it. The
nearest surface over a 3 x 3 neighbourhood of cells is used, so a point next to an edge finds the
near side and is not called a violation.
"""

from __future__ import annotations

import threading
import weakref
from dataclasses import dataclass, field
from functools import cached_property
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from ..geometry.rigid import apply_transform

#: Cells with a return within this neighbourhood (cells each way) count for a point.
_REACH = 1


@dataclass(frozen=True, eq=False)
class RangeImage:
    """The nearest range per (azimuth, elevation) cell of one station, sparse.

    `keys` are the sorted flat cell indices that hold a return, `ranges_m` their nearest range.
    """

    cell_deg: tuple[float, float]
    alpha0_deg: float
    beta0_deg: float
    n_cols: int
    keys: np.ndarray
    ranges_m: np.ndarray
    #: Sorted flat cells where the prepare stage removed mixed pixels and no other return is left:
    #: the station did return something there, so a point there is no proof of free space. (Only
    #: the cells themselves: with their neighbourhood, every silhouette of a thin crown would go
    #: blind and a wrong heading would look as good as the right one.)
    blind_keys: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def cells(self, alpha_deg: np.ndarray, beta_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        col = np.floor((np.mod(alpha_deg - self.alpha0_deg, 360.0)) / self.cell_deg[0]).astype(np.int64)
        row = np.floor((beta_deg - self.beta0_deg) / self.cell_deg[1]).astype(np.int64)
        return col, row

    @cached_property
    def _reach(self) -> tuple[np.ndarray, np.ndarray]:
        """The image with each cell holding the nearest range within `_REACH` of it (sorted keys,
        ranges): made once, so a query is one lookup instead of one per neighbour (the free-space
        test runs dozens of times per pair)."""
        row, col = np.divmod(self.keys, self.n_cols)
        keys, ranges = [], []
        for dc in range(-_REACH, _REACH + 1):
            for dr in range(-_REACH, _REACH + 1):
                keys.append((row - dr) * self.n_cols + np.mod(col - dc, self.n_cols))
                ranges.append(self.ranges_m)
        key, r = np.concatenate(keys), np.concatenate(ranges)
        order = np.lexsort((r, key))
        key, r = key[order], r[order]
        first = np.r_[True, key[1:] != key[:-1]] if len(key) else np.zeros(0, bool)
        return key[first], r[first]

    def blind(self, col: np.ndarray, row: np.ndarray) -> np.ndarray:
        """True in the cells where only removed mixed pixels were."""
        if not len(self.blind_keys):
            return np.zeros(len(col), dtype=bool)
        key = row * self.n_cols + col
        i = np.minimum(np.searchsorted(self.blind_keys, key), len(self.blind_keys) - 1)
        return self.blind_keys[i] == key

    def nearest(self, col: np.ndarray, row: np.ndarray) -> np.ndarray:
        """Nearest range among the cells within `_REACH` of (col, row); inf where none has a return."""
        keys, ranges = self._reach
        out = np.full(len(col), np.inf)
        if len(keys) == 0:
            return out
        key = row * self.n_cols + col
        i = np.minimum(np.searchsorted(keys, key), len(keys) - 1)
        hit = keys[i] == key
        out[hit] = ranges[i[hit]]
        return out


def _angles(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    h = np.hypot(x, y)
    return np.degrees(np.arctan2(y, x)), np.degrees(np.arctan2(z, h)), np.sqrt(h * h + z * z)


def range_image(points: np.ndarray, cell_deg: tuple[float, float], blind_points: np.ndarray | None = None) -> RangeImage:
    """The range image of a station's points (in its own frame, scanner at the origin); the cells
    of `blind_points` (mixed pixels removed from them) and their neighbours are marked blind."""
    alpha, beta, r = _angles(np.asarray(points, dtype=float))
    beta0 = float(beta.min()) - cell_deg[1]
    n_cols = int(np.ceil(360.0 / cell_deg[0])) + 1
    img = RangeImage(cell_deg, -180.0, beta0, n_cols, np.empty(0, np.int64), np.empty(0))
    col, row = img.cells(alpha, beta)
    key = row * n_cols + col
    order = np.lexsort((r, key))
    key, r = key[order], r[order]
    first = np.r_[True, key[1:] != key[:-1]]
    blind = np.zeros(0, dtype=np.int64)
    if blind_points is not None and len(blind_points):
        ba, bb, _ = _angles(np.asarray(blind_points, dtype=float))
        bc, br = img.cells(ba, bb)
        blind = np.setdiff1d(np.unique(br * n_cols + bc), key[first])
    return RangeImage(cell_deg, -180.0, beta0, n_cols, key[first], r[first], blind)


@dataclass(frozen=True)
class Visibility:
    """How the target's points, placed in the reference frame, fare against the reference's view.

    Counts of consistent, violating (in the reference's free space), occluded and unseen points;
    `consistency` = consistent / (consistent + violations): 1 when the two views agree wherever both
    could see, low when the target sits in space the reference saw through. With wind, `moved`
    counts the points in the reference's free space that lie within the crown's measured motion of
    a surface the reference saw (a twig that moved): neither agreement nor contradiction.
    """

    consistent: int
    violations: int
    occluded: int
    unseen: int
    moved: int = 0

    @property
    def seen_by_both(self) -> int:
        return self.consistent + self.violations

    @property
    def consistency(self) -> float:
        return self.consistent / self.seen_by_both if self.seen_by_both else float("nan")


def _classes(ref_image: RangeImage, p: np.ndarray, tolerance_m: float) -> tuple[np.ndarray, ...]:
    """Masks (consistent, violation, occluded, seen) of points `p` in the reference frame."""
    alpha, beta, r = _angles(p)
    col, row = ref_image.cells(alpha, beta)
    near = ref_image.nearest(col, row)
    tol = tolerance_m + r * np.radians(max(ref_image.cell_deg)) * 2.0
    seen = np.isfinite(near)
    # Where the station's mixed pixels were removed it did return something: blind, not free space.
    violation = seen & (r < near - tol) & ~ref_image.blind(col, row)
    return seen & (np.abs(r - near) <= tol), violation, seen & (r > near + tol), seen


def placed(target_points: np.ndarray, T_ref_target: np.ndarray,
           unbend: Callable[[np.ndarray], np.ndarray] | None = None) -> np.ndarray:
    """Target points (their own frame) in the reference frame: mapped by the transform and, with
    wind, moved back to where the reference's tree stood (`fine.bend.Bend.unbend`)."""
    p = apply_transform(np.asarray(T_ref_target, dtype=float), np.asarray(target_points, dtype=float))
    return p if unbend is None else unbend(p)


def visibility(ref_image: RangeImage, target_points: np.ndarray, T_ref_target: np.ndarray,
               tolerance_m: float, *, unbend: Callable[[np.ndarray], np.ndarray] | None = None,
               surface_tree: cKDTree | None = None,
               motion_m: float | Callable[[np.ndarray], np.ndarray] = 0.0) -> Visibility:
    """Check every target point (its own frame), mapped by `T_ref_target`, against the reference's view.

    The tolerance grows with range as a cell does (a surface oblique to the ray spans a range of
    depths within one cell): `tolerance_m + r * cell size`. With wind, the points are first unbent
    (`unbend`), and a point in the reference's free space within `motion_m` of a surface point the
    reference saw (`surface_tree`) counts as moved, not as a violation. `motion_m` is one distance,
    or a function giving each point's own (of the points placed and unbent, reference frame: the
    motion a model allows at their heights).
    """
    p = placed(target_points, T_ref_target, unbend)
    consistent, violation, occluded, seen = _classes(ref_image, p, tolerance_m)
    moved = 0
    if surface_tree is not None and violation.any() and (callable(motion_m) or motion_m > 0):
        idx = np.flatnonzero(violation)
        allow = (np.asarray(motion_m(p[idx]), dtype=float) if callable(motion_m) else np.full(len(idx), float(motion_m)))
        reach = float(allow.max()) * (1.0 + 1e-9) if len(allow) else 0.0
        d, _ = surface_tree.query(p[idx], distance_upper_bound=reach) if reach > 0 else (np.full(len(idx), np.inf), None)
        near = np.isfinite(d) & (d <= allow)
        violation[idx[near]] = False
        moved = int(near.sum())
    return Visibility(int(consistent.sum()), int(violation.sum()), int(occluded.sum()), int((~seen).sum()), moved)


def violation_distances(ref_image: RangeImage, target_points: np.ndarray, T_ref_target: np.ndarray,
                        tolerance_m: float, unbend: Callable[[np.ndarray], np.ndarray] | None,
                        surface_tree: cKDTree, reach_m: float) -> tuple[np.ndarray, int]:
    """How far each target point in the reference's free space lies from the nearest surface point
    the reference saw (inf beyond `reach_m`), and how many points both stations see: what the
    crown's motion beyond the stem's bend looks like."""
    p = placed(target_points, T_ref_target, unbend)
    consistent, violation, _, _ = _classes(ref_image, p, tolerance_m)
    d, _ = surface_tree.query(p[violation], distance_upper_bound=reach_m)
    return d, int(consistent.sum() + violation.sum())


_images: "weakref.WeakKeyDictionary[object, dict]" = weakref.WeakKeyDictionary()
_images_lock = threading.Lock()


def scan_range_image(scan: object, cell_steps: float, blind_points: np.ndarray | None = None) -> RangeImage:
    """The range image of a scan (all its points as measured, ground included: the ground, too, is
    where rays stopped), cells of `cell_steps` angular steps, blind where `blind_points` (the mixed
    pixels removed from the scan) were; made once per scan and shared."""
    with _images_lock:
        found = _images.get(scan, {}).get(cell_steps)
    if found is None:
        found = range_image(scan.points, tuple(cell_steps * s for s in scan.angular_step_deg), blind_points)
        with _images_lock:
            _images.setdefault(scan, {})[cell_steps] = found
    return found
