"""Where the camera should stand to show a stage: a view choice, not registration geometry.

Before registration (Scans, Projection, Matching) every scan stands in its own scanner frame, so
the trees are scattered around the common origin and the view frames them all; from Coarse on
every scan is drawn over the reference tree, and the view frames that tree without its ground. The camera looks
from behind the reference scanner towards its tree, slightly from above, far enough that the
whole extent fits the vertical field of view and the narrower horizontal one between the panels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from treereg_core.fine.sections import SectionsResult
from treereg_core.fine.slicing import SliceResult
from treereg_core.geometry.rigid import apply_transform

from .controller import Snapshot
from .draw.common import display_subset
from .stages import registered
from .view_state import ViewState

#: viser's vertical field of view (75 deg) and the scene's width/height between the two docked
#: panels at a common 1700 x 1000 window: the horizontal half-angle is the tighter one.
FOV_Y_RAD = np.radians(75.0)
SCENE_ASPECT = 0.75
#: Spare room around the framed points (the half-angle is divided by this).
MARGIN = 1.1
#: The camera looks down on the tree by this much.
ELEVATION_DEG = 15.0


@dataclass(frozen=True)
class CameraPose:
    position: tuple[float, float, float]
    look_at: tuple[float, float, float]


def _points_to_frame(snap: Snapshot, stage: str) -> list[np.ndarray]:
    prep = snap.output("prepare")
    if registered(stage):
        if prep is not None and prep.items and getattr(prep.items[0], "scan", None) is not None:
            return [prep.items[0].scan.points]
        return [snap.scans[0].points]
    return [s.points for s in snap.scans]


#: Stages that show one slice at a time (`ViewState.slice_shown`): the camera frames that slice.
SLICE_STAGES = ("arcs", "sections", "fine")


def _slice_points(snap: Snapshot, view: ViewState) -> np.ndarray | None:
    """What to frame of the slice the view shows: its fitted sections (centres and rims) once the
    Fits stage has them, else the reference's points in it (None: every slice, or none yet); where
    they are shown, i.e. moved with the pair's reference scan (the drawer's `pair_reference`)."""
    from .draw.before import drawn
    from .draw.common import target_index
    from .draw.fits import slice_shown
    from .draw.scan_layer import scan_poses

    snap = drawn(snap, view)[0]  # the run the view draws (the last one, while its stage is stale)
    if snap.output("slices") is None:
        return None
    t = target_index(snap, "slices", view)
    pair = snap.pair(t)
    sl, scans = pair.item("slices", SliceResult), pair.prepared()
    if sl is None or not sl.ok or scans is None:
        return None
    k = slice_shown(snap, t, view, sl.n_slices)
    if k is None or not len(sl.ref_indices[k]):
        return None
    sec = pair.item("sections", SectionsResult) if view.stage != "arcs" else None
    fits = [s for s in (sec.ref.sections if sec is not None else ()) if s.slice_index == k and s.plausible
            and np.isfinite(s.radius_m) and s.radius_m < 2.0]
    if fits:
        rim = np.array([[np.cos(a), np.sin(a), 0.0] for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)])
        pts = np.concatenate([np.asarray(s.centre_m) + 2.0 * s.radius_m * rim for s in fits])
    else:
        pts = np.asarray(scans[0].points[sl.ref_indices[k]])
    return apply_transform(scan_poses(snap, view)[pair.ref], pts)


#: A slice fills its view to this share of the half-width and half-height (the larger of the two).
SLICE_FILL = 0.9


def frame(snap: Snapshot, stage: str, view: ViewState | None = None,
          aspect: float | None = None, fov_y_rad: float = FOV_Y_RAD) -> CameraPose | None:
    """A camera pose showing what stage `stage` draws (None when there are no scans): on the Arcs,
    Fits and Fine stages the one slice the view shows, from a little more above, filling the view
    (`aspect`: the tab's 3-D view's width / height, as its camera reports it; `SCENE_ASPECT` unknown)."""
    if not snap.scans:
        return None
    one = _slice_points(snap, view) if view is not None and stage in SLICE_STAGES else None
    if one is not None:
        return _fill(snap, one[display_subset(len(one), 5000, seed=7)], 3 * ELEVATION_DEG,
                     aspect or SCENE_ASPECT, fov_y_rad)
    parts = [p[display_subset(len(p), 5000, seed=7)] for p in _points_to_frame(snap, stage)]
    return _frame_points(snap, np.concatenate(parts))


def _frame_points(snap: Snapshot, pts: np.ndarray, elevation_deg: float = ELEVATION_DEG,
                  percentile: float = 0.5) -> CameraPose:
    # Far strays don't count (a slice's few fitted rims all do).
    lo, hi = np.percentile(pts, percentile, axis=0), np.percentile(pts, 100.0 - percentile, axis=0)
    look = (lo + hi) / 2.0
    # From the reference scanner (its origin) towards its tree, i.e. the reference scan's view,
    # from a little above (elevation ELEVATION_DEG).
    tree = snap.scans[0].points.mean(axis=0)
    d = tree[:2] / (np.linalg.norm(tree[:2]) or 1.0)
    e = np.radians(elevation_deg)
    back = np.array([-d[0] * np.cos(e), -d[1] * np.cos(e), np.sin(e)])
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    # The farthest corner must fit the narrower (horizontal) half-angle, with some room to spare.
    half = np.arctan(np.tan(FOV_Y_RAD / 2.0) * SCENE_ASPECT) / MARGIN
    dist = float(np.linalg.norm(hi - lo)) / 2.0 or 1.0
    for _ in range(60):  # grow until everything fits; a few steps of 10 %
        pos = look + back * dist
        rays = corners - pos
        cos = rays @ (look - pos) / (np.linalg.norm(rays, axis=1) * dist)
        if np.all(np.arccos(np.clip(cos, -1.0, 1.0)) < half):
            break
        dist *= 1.1
    return CameraPose(tuple(float(v) for v in pos), tuple(float(v) for v in look))


def _fill(snap: Snapshot, pts: np.ndarray, elevation_deg: float, aspect: float, fov_y_rad: float) -> CameraPose:
    """Points seen from the reference scanner's side, `elevation_deg` above, as close as lets every one
    of them fall within `SLICE_FILL` of the view's half-width and half-height: the nearest distance
    along the viewing direction at which each point's sideways and upward offsets fit the
    field of view's tangents (the slice fills the view, instead of a box's corners around it)."""
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    look = (lo + hi) / 2.0
    tree = snap.scans[0].points.mean(axis=0)
    d = tree[:2] / (np.linalg.norm(tree[:2]) or 1.0)
    e = np.radians(elevation_deg)
    back = np.array([-d[0] * np.cos(e), -d[1] * np.cos(e), np.sin(e)])  # from the look-at point to the camera
    forward = -back
    up = np.array([0.0, 0.0, 1.0]) - forward[2] * forward
    up /= np.linalg.norm(up)
    right = np.cross(forward, up)
    tan_v = np.tan(fov_y_rad / 2.0) * SLICE_FILL
    tan_h = tan_v * float(aspect)
    r = pts - look
    # A point at offset r is at depth dist - r.back from a camera `dist` behind the look-at point.
    need = np.maximum(np.abs(r @ right) / tan_h, np.abs(r @ up) / tan_v) + r @ back
    dist = max(float(need.max()), 0.3)
    return CameraPose(tuple(float(v) for v in look + back * dist), tuple(float(v) for v in look))


def frame_point(snap: Snapshot, centre: np.ndarray, radius_m: float) -> CameraPose:
    """A close view of one spot (a fitted section): from the reference scanner's side, slightly from
    above, far enough to see the spot and a little around it."""
    centre = np.asarray(centre, dtype=float)
    tree = snap.scans[0].points.mean(axis=0) if snap.scans else np.array([1.0, 0.0, 0.0])
    d = tree[:2] / (np.linalg.norm(tree[:2]) or 1.0)
    e = np.radians(ELEVATION_DEG * 2)
    back = np.array([-d[0] * np.cos(e), -d[1] * np.cos(e), np.sin(e)])
    dist = max(1.0, 10.0 * float(radius_m))
    return CameraPose(tuple(float(v) for v in centre + back * dist), tuple(float(v) for v in centre))


def trunk_anchor(snap: Snapshot, height_m: float | None) -> np.ndarray | None:
    """A point on the reference's stem at `height_m` (where the tour points and looks): the middle of
    the reference's points within 10 cm of that height. None without prepared scans."""
    prep = snap.output("prepare")
    if height_m is None or prep is None or not prep.items or getattr(prep.items[0], "scan", None) is None:
        return None
    pts = prep.items[0].scan.points
    near = pts[np.abs(pts[:, 2] - height_m) <= 0.1]
    if len(near) == 0:
        return None
    xy = np.median(near[:, :2], axis=0)
    return np.array([xy[0], xy[1], float(height_m)])
