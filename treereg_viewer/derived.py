"""Results the app asks treereg_core for on demand, computed once and shared by every tab.

A viewer's cross-section (at the height it picked) and the overlap residuals of a registration
(the Result stage's colour map) are not pipeline stages: they depend on a view choice. The drawing
threads of all tabs ask here; each result is computed by treereg_core (`evaluate.cross_section`,
`evaluate.residuals`) from the published snapshot and kept, keyed by the outputs it came from, so
a second tab looking at the same thing gets it at once. The app itself computes no geometry.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any, Callable, Hashable

import numpy as np

from treereg_core.evaluate.cross_section import CrossSection, branch_section, stem_section
from treereg_core.evaluate.residuals import overlap_residuals
from treereg_core.evaluate.report import PairReport
from treereg_core.fine.pose import FineResult
from treereg_core.fine.slicing import SliceResult
from treereg_core.geometry.rigid import apply_transform

from .controller import Snapshot
from .draw.common import display_subset
from .stages import POSE_STAGE
from .view_state import SECTION_POSES, ViewState

#: How far below the chosen height the 4.2 check's "part below" is cut (m).
BELOW_M = 0.3
#: A point farther than this from every other scan's point was seen by its scan alone (no residual):
#: the colour map's top times this factor, at least `MIN_REACH_M`. Much farther and a point on one
#: side of a stem would be measured against the other scan's points round the curve.
REACH_FACTOR = 1.5
MIN_REACH_M = 0.03


def prepared_scans(snap: Snapshot) -> list[Any] | None:
    """The scans as every stage after preparation uses them (ground removed, cropped)."""
    prep = snap.output("prepare")
    if prep is None or len(prep.items) != len(snap.scans) or not all(getattr(it, "ok", False) for it in prep.items):
        return None
    return [it.scan for it in prep.items]


def pose_output(snap: Snapshot, pose: str) -> Any:
    """The stage output holding a pose's transforms ("final": the graph stage's placements)."""
    return snap.output(POSE_STAGE.get(pose, pose))


def pose_transforms(snap: Snapshot, pose: str) -> list[np.ndarray | None]:
    """`T_ref_scan` of every scan under one registration ("coarse", "fine", "icp", or "final", the
    joint placement): the identity for the reference, None for a target whose item did not succeed
    (it is then left out, not shown at another registration's pose)."""
    out = pose_output(snap, pose)
    if pose == "final":
        n = len(snap.scans)
        items = list(out.items) if out is not None and len(out.items) == n else [None] * n
        return [np.eye(4)] + [np.asarray(it.T_ref_scan, dtype=float) if it is not None and it.T_ref_scan is not None
                              else None for it in items[1:]]
    Ts: list[np.ndarray | None] = [np.eye(4)]
    for k in range(1, len(snap.scans)):
        pair = snap.reference_pair(k)
        item = out.items[pair.index] if out is not None and pair is not None and pair.index < len(out.items) else None
        ok = item is not None and getattr(item, "ok", False) and getattr(item, "ran", True)
        Ts.append(np.asarray(item.T_ref_target, dtype=float) if ok else None)
    return Ts


def default_height(snap: Snapshot, target: int = 0) -> float | None:
    """The trunk: the lowest slice of the slices stage, else a little above the reference's lowest point."""
    sl = snap.pair(target).item("slices", SliceResult) if target < snap.n_pairs else None
    if sl is not None and sl.ok:
        return float(sl.heights_m[0])
    scans = prepared_scans(snap)
    if scans is None:
        return None
    return float(np.quantile(scans[0].points[:, 2], 0.001) + 0.5)


def height_range(snap: Snapshot) -> tuple[float, float] | None:
    """The reference tree's vertical extent (m), for the height slider."""
    scans = prepared_scans(snap)
    if scans is None:
        return None
    lo, hi = np.quantile(scans[0].points[:, 2], [0.001, 0.999])
    return float(lo), float(hi)


def target_bends(snap: Snapshot) -> list[Any]:
    """Per scan, the bend of its stem against the reference's that the fine stage fitted (its pair
    with the reference; wind between the stations), None for the reference and where none was."""
    fine = snap.output("fine")
    out: list[Any] = [None] * len(snap.scans)
    if fine is None:
        return out
    for i in range(1, len(snap.scans)):
        pair = snap.reference_pair(i)
        item = pair.item("fine", FineResult) if pair is not None else None
        out[i] = item.bend if item is not None else None
    return out


def evaluated_branches(snap: Snapshot, target: int) -> list[Any]:
    """The branches the Result stage evaluated for a target (its fine evaluation's, bottom to top)."""
    report = snap.pair(target).item("evaluation", PairReport) if target < snap.n_pairs else None
    if report is None or not report.ok:
        return []
    return list(report.fine.branches)


class Derived:
    """A small shared cache of on-demand results (thread-safe; drawing threads of all tabs call it)."""

    def __init__(self, size: int = 48) -> None:
        self._lock = threading.Lock()
        self._items: OrderedDict[Hashable, Any] = OrderedDict()
        self._size = size
        self.computed = 0  # how many results were computed (tests: a second tab computes nothing)

    def _get(self, key: Hashable, make: Callable[[], Any]) -> Any:
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
        value = make()
        with self._lock:
            self._items[key] = value
            self.computed += 1
            while len(self._items) > self._size:
                self._items.popitem(last=False)
        return value

    # ---- cross-sections ---------------------------------------------------------------------------
    def cross_section(self, snap: Snapshot, view: ViewState) -> CrossSection | None:
        """The cross-section a view asks for: the stem at its height, or an evaluated branch's
        layers; every registration the view shows that has run. None before coarse has run."""
        scans = prepared_scans(snap)
        if scans is None or snap.output("coarse") is None:
            return None
        wanted = [p for p in SECTION_POSES.get(view.section_poses, ("coarse", "fine")) if snap.output(p) is not None]
        if not wanted:
            wanted = ["coarse"]
        poses = {p: pose_transforms(snap, p) for p in wanted}
        params = snap.params
        thickness = view.section_thickness or params.slices.thickness_m
        ids = (id(snap.output("prepare")), *(id(snap.output(p)) for p in wanted), params.arcs, params.sections)
        if view.branch is not None:
            branches = evaluated_branches(snap, view.target)
            if not 0 <= view.branch < len(branches):
                return None
            b = branches[view.branch]
            ev = params.evaluation
            key = ("branch", *ids, id(snap.output("evaluation")), view.target, view.branch, tuple(wanted))
            return self._get(key, lambda: branch_section(
                scans, poses, point_m=b.point_m, axis=b.axis, radius_m=b.radius_m, layer_z_m=b.layer_z_m,
                thickness_m=ev.layer_thickness_m, margin_m=ev.margin_m, arcs=params.arcs, sections=params.sections))
        h = view.section_height if view.section_height is not None else default_height(snap, view.target)
        if h is None:
            return None
        h = round(float(h), 3)  # millimetres: a slider's float noise must not miss the cache
        key = ("stem", *ids, h, round(thickness, 4), tuple(wanted))
        return self._get(key, lambda: stem_section(scans, poses, h, thickness_m=thickness, below_m=BELOW_M,
                                                   arcs=params.arcs, sections=params.sections))

    # ---- residuals -----------------------------------------------------------------------------------
    def residuals(self, snap: Snapshot, pose: str, max_points: int, top_m: float = 0.02) -> list[np.ndarray] | None:
        """Per scan, the distance of its displayed points (`display_subset`, as the scan layer draws
        them) to the other scans' surface under registration `pose` (NaN: not seen by the others
        within reach of the colour map's top `top_m`); None when it has not run."""
        scans = prepared_scans(snap)
        if scans is None or pose_output(snap, pose) is None:
            return None
        Ts = pose_transforms(snap, pose)
        reach = max(MIN_REACH_M, REACH_FACTOR * top_m)
        key = ("residuals", id(snap.output("prepare")), id(pose_output(snap, pose)), pose, max_points, round(reach, 4))

        def make() -> list[np.ndarray]:
            clouds = [apply_transform(T, s.points) if T is not None else np.empty((0, 3)) for T, s in zip(Ts, scans)]
            samples = [display_subset(len(s.points), max_points, seed=i) if T is not None else np.empty(0, dtype=int)
                       for i, (T, s) in enumerate(zip(Ts, scans))]
            return overlap_residuals(clouds, samples, reach_m=reach)

        return self._get(key, make)

    def wind_moved(self, snap: Snapshot, pose: str, max_points: int, top_m: float = 0.02) -> list[np.ndarray] | None:
        """Per scan, which of its displayed points moved with the wind: beyond the colour map's top
        from the other scans' surface as registered, within it once every target is unbent by its
        crown's measured motion (`fine.bend`); None when no target's crown moved."""
        scans = prepared_scans(snap)
        bends = target_bends(snap)
        raw = self.residuals(snap, pose, max_points, top_m)
        if scans is None or raw is None or not any(b is not None for b in bends):
            return None
        Ts = pose_transforms(snap, pose)
        reach = max(MIN_REACH_M, REACH_FACTOR * top_m)
        key = ("moved", id(snap.output("prepare")), id(pose_output(snap, pose)), id(snap.output("fine")), pose,
               max_points, round(reach, 4), round(top_m, 5))

        def make() -> list[np.ndarray]:
            clouds = []
            for T, s, b in zip(Ts, scans, bends):
                pts = apply_transform(T, s.points) if T is not None else np.empty((0, 3))
                clouds.append(b.unbend(pts) if b is not None and len(pts) else pts)
            samples = [display_subset(len(s.points), max_points, seed=i) if T is not None else np.empty(0, dtype=int)
                       for i, (T, s) in enumerate(zip(Ts, scans))]
            unbent = overlap_residuals(clouds, samples, reach_m=reach)
            return [(~(r <= top_m)) & (u <= top_m) for r, u in zip(raw, unbent)]

        return self._get(key, make)
