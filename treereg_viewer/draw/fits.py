"""The fitted sections as the Fits and Fine stages draw them (a fit per arc, the table of fits, the
"Frame a fit" rows), and the prepared scans the fine stages index into.

The sections are already in the reference frame; the target's slice points are mapped by the pose
they were made at (`rigid.apply_transform`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, cast

import numpy as np
import trimesh
import viser

from treereg_core.fine.arcs import SliceArcs
from treereg_core.fine.pose import FineResult
from treereg_core.fine.sections import SectionsResult
from treereg_core.fine.slicing import SliceResult
from treereg_core.geometry.rigid import apply_transform
from treereg_core.scan import Scan

from ..controller import Snapshot, SnapshotPair
from ..palette import GREY, HIGHLIGHT, scan_color
from ..view_state import ALL_SLICES, ViewState
from ..text import md
from .common import md_table, plural, target_index

#: With every slice shown, the fits table lists at most this many rows (a slice at a time lists all).
MAX_ROWS = 40


def fine_scans(snap: Snapshot, t: int) -> tuple[Scan, Scan]:
    """The prepared reference and target scans of pair `t` (what the fine stages index into). The
    fine stages' items exist only for pairs whose scans were prepared: anything else is a bug."""
    scans = snap.pair(t).prepared()
    if scans is None:
        raise ValueError(f"{snap.pair(t).label}: its scans were not prepared")
    return scans


@dataclass(frozen=True, kw_only=True)
class FitRow:
    """One row of the fits table (and of the "Frame a fit" list): a fitted section worth a look."""

    number: int  # 1-based, as the table shows it
    scan: str
    scan_index: int  # 0 = reference
    section: Any
    slice_box: tuple[tuple[float, float], tuple[float, float]]  # (min x, min y), (max x, max y) of that slice's points

    @property
    def label(self) -> str:
        s = self.section
        return f"#{self.number}: {self.scan}, slice {s.slice_index + 1}, {s.kind}, r = {s.radius_m * 100:.1f} cm"


def _box(points: np.ndarray) -> tuple[tuple[float, float], tuple[float, float]]:
    if not len(points):
        return (0.0, 0.0), (0.0, 0.0)
    lo, hi = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    return (float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1]))


def busiest_slice(snap: Snapshot, t: int) -> int:
    """The slice of pair `t` with the most fitted sections of both scans (the most to look at; the
    arcs' count before the Fits stage has run, else the lowest slice)."""
    pair = snap.pair(t)
    item = pair.item("sections", SectionsResult)
    counts: dict[int, int] = {}
    if item is not None:
        for s in (*item.ref.sections, *item.tgt.sections):
            if s.plausible:
                counts[s.slice_index] = counts.get(s.slice_index, 0) + 1
    a = pair.item("arcs", SliceArcs) if not counts else None
    if a is not None:
        for k, (r, g) in enumerate(zip(a.ref, a.tgt)):
            counts[k] = r.n_arcs + g.n_arcs
    return max(counts, key=lambda k: (counts[k], -k)) if counts else 0


def pinned_slice(snap: Snapshot, view: ViewState) -> int | None:
    """What `ViewState.slice_shown` should hold for the pair in view: the slice already chosen while the
    pair has it (kept across re-runs: the Arcs, Fits and Fine views, the *Slice* list and the framing
    stay on it), else the busiest slice once the arcs or fits are known (None until then); every
    slice (`ALL_SLICES`) stays so."""
    if view.slice_shown == ALL_SLICES or snap.output("slices") is None or snap.n_pairs == 0:
        return view.slice_shown
    t = target_index(snap, "slices", view)
    pair = snap.pair(t)
    sl = pair.item("slices", SliceResult)
    if sl is None or not sl.ok or sl.n_slices == 0:
        return view.slice_shown  # nothing to choose from (yet): as it is
    if view.slice_shown is not None and 0 <= view.slice_shown < sl.n_slices:
        return view.slice_shown
    if pair.item("arcs", SliceArcs) is None and pair.item("sections", SectionsResult) is None:
        return None  # the busiest slice is not known before the arcs are
    return busiest_slice(snap, t)


def slice_shown(snap: Snapshot, t: int, view: ViewState, n_slices: int) -> int | None:
    """The slice the Arcs, Fits and Fine views show for pair `t` (None: every slice)."""
    if view.slice_shown == ALL_SLICES or n_slices == 0:
        return None
    k = busiest_slice(snap, t) if view.slice_shown is None else view.slice_shown
    return int(min(max(k, 0), n_slices - 1))


#: Points of one slice seen close up are drawn this share of the view's point size (at the size that
#: reads over a whole tree they merged into blobs a third of the stem wide, hiding the arcs' colours).
CLOSE_UP_POINTS = 0.5


def slice_point_size(view: ViewState, only: int | None, whole: float = 1.0) -> float:
    """The point size of slice points: `whole` times the view's over every slice, smaller for one slice."""
    return view.point_size * (whole if only is None else CLOSE_UP_POINTS)


def slice_label(k: int, heights_m: Any) -> str:
    """'slice 3 at 2.41 m' (counted from 1, as the tables do)."""
    return f"slice {k + 1} at {float(heights_m[k]):.2f} m" if k < len(heights_m) else f"slice {k + 1}"


def fit_rows(snap: Snapshot, t: int, sl: SliceResult, sec: SectionsResult, ref: Any, tgt: Any,
             show_rejected: bool, only_slice: int | None = None) -> tuple[list[FitRow], int]:
    """The fits worth listing, accepted first (then rejected, when asked), each by slice and radius
    (of slice `only_slice` alone, when given); and how many arcs have no fit to show (too few
    points, failed, or skipped: no NaN rows)."""
    boxes: dict[int, Any] = {}  # per slice: the horizontal extent of both scans' points in it

    def box(k: int) -> Any:
        if k not in boxes:
            parts = [ref.points[sl.ref_indices[k]]] if k < len(sl.ref_indices) else []
            if k < len(sl.tgt_indices) and len(sl.tgt_indices[k]):
                parts.append(apply_transform(sec.T_ref_target, tgt.points[sl.tgt_indices[k]]))
            boxes[k] = _box(np.concatenate(parts)) if parts else _box(np.empty((0, 3)))
        return boxes[k]

    rows: list[FitRow] = []
    hidden = 0
    pair = snap.pair(t)
    for plausible in (True, False):
        for secs, i in ((sec.ref.sections, pair.ref), (sec.tgt.sections, pair.tgt)):
            mine = (s for s in secs if s.plausible == plausible and only_slice in (None, s.slice_index))
            for s in sorted(mine, key=lambda s: (s.slice_index, -s.radius_m)):
                if not (s.fit.ok and np.isfinite(s.radius_m) and np.isfinite(s.centre_m).all()):
                    hidden += plausible is False
                    continue
                if not plausible and not show_rejected:
                    continue
                rows.append(FitRow(number=0, scan=snap.scans[i].name, scan_index=i, section=s,
                                   slice_box=box(s.slice_index)))
    rows = [replace(r, number=k + 1) for k, r in enumerate(rows)]
    return rows, hidden


def slice_points(scene: viser.SceneApi, root: str, pair: SnapshotPair, sl: SliceResult, T: np.ndarray | None, ref: Any,
                 tgt: Any, size: float, only_slice: int | None = None) -> list[Any]:
    """Every slice's points of both scans of `pair` (or slice `only_slice`'s) in the reference frame,
    in the scans' colours; the target's mapped by `T` (None: no pose yet, each scan in its own frame)."""
    handles: list[Any] = []
    for k in range(sl.n_slices) if only_slice is None else (only_slice,):
        r_idx, t_idx = sl.ref_indices[k], sl.tgt_indices[k]
        if len(r_idx):
            handles.append(scene.add_point_cloud(f"{root}/ref{k}", ref.points[r_idx], scan_color(pair.ref), point_size=size,
                                                 point_shape="circle", precision="float32"))
        if len(t_idx):
            pts = tgt.points[t_idx] if T is None else apply_transform(T, tgt.points[t_idx])
            handles.append(scene.add_point_cloud(f"{root}/tgt{k}", pts, scan_color(pair.tgt), point_size=size,
                                                 point_shape="circle", precision="float32"))
    return handles


#: A fit is drawn only when its circle stays within its slice's points, give or take this fraction
#: of the slice's extent plus `SLACK_M`: the scans see only part of a stem, so a true section may
#: reach a little beyond its points; a circle of metres fitted to a nearly straight arc does not.
SLACK_FRACTION = 0.1
SLACK_M = 0.05


def within(centre_xy: np.ndarray, radius_m: float, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Whether a circle lies within the box lo..hi widened by the slack."""
    pad = SLACK_FRACTION * float(np.max(hi - lo)) + SLACK_M
    c = np.asarray(centre_xy, dtype=float)
    return bool(radius_m > 0 and np.all(c - radius_m >= lo - pad) and np.all(c + radius_m <= hi + pad))


def drawable(row: FitRow) -> bool:
    """A fit is drawn only when it is no larger than the slice it came from: a circle fitted to an
    almost straight arc can have a radius of kilometres and would hide the tree."""
    lo, hi = (np.asarray(v, dtype=float) for v in row.slice_box)
    return within(row.section.centre_m[:2], row.section.radius_m, lo, hi)


def section_mesh(section: Any, thickness_m: float, grow: float = 1.0) -> trimesh.Trimesh:
    """A circle as a short vertical ring-cylinder at its slice; a cylinder along its axis (no longer
    than a few slice thicknesses: a fit describes its slice, not the whole branch)."""
    centre = np.asarray(section.centre_m, dtype=float)
    axis = np.asarray(section.axis, dtype=float)
    axis = axis / (np.linalg.norm(axis) or 1.0)
    r = float(section.radius_m) * grow
    length = thickness_m if section.kind == "circle" else \
        min(max(float(getattr(section.fit, "length_m", thickness_m)), thickness_m), 3.0 * thickness_m)
    seg = np.stack([centre - axis * length / 2, centre + axis * length / 2])
    mesh: trimesh.Trimesh = trimesh.creation.cylinder(radius=r, segment=seg, sections=32)
    return mesh


def _sections_meshes(scene: viser.SceneApi, name: str, sections: list[Any], color: tuple[int, int, int],
                     thickness_m: float, opacity: float, grow: float = 1.0) -> list[Any]:
    if not sections:
        return []
    mesh = cast(trimesh.Trimesh, trimesh.util.concatenate([section_mesh(s, thickness_m, grow) for s in sections]))
    return [scene.add_mesh_simple(name, mesh.vertices.astype(np.float32), mesh.faces.astype(np.int32),
                                  color=color, opacity=opacity, side="double")]


def draw_sections(scene: viser.SceneApi, root: str, snap: Snapshot, t: int, sl: SliceResult, sec: SectionsResult,
                  ref: Any, tgt: Any, view: ViewState) -> tuple[list[Any], str, list[FitRow]]:
    """The fitted sections of both scans (rejected ones grey, only when asked), the sliced points as
    context and the tie lines between partners; returns the handles, the fits table and its rows."""
    thick = sl.thickness_m
    only = slice_shown(snap, t, view, sl.n_slices)
    # The scans are hidden on these stages (points on a fitted surface would hide it): the fitted
    # slices' points stay as context.
    pair = snap.pair(t)
    handles: list[Any] = slice_points(scene, root, pair, sl, sec.T_ref_target, ref, tgt, slice_point_size(view, only),
                                      only)
    rows, hidden = fit_rows(snap, t, sl, sec, ref, tgt, view.show_rejected, only)
    shown = [r for r in rows if drawable(r)]
    for who, i in (("ref", pair.ref), ("tgt", pair.tgt)):
        good = [r.section for r in shown if r.scan_index == i and r.section.plausible]
        bad = [r.section for r in shown if r.scan_index == i and not r.section.plausible]
        handles += _sections_meshes(scene, f"{root}/{who}_fits", good, scan_color(i), thick, 0.55)
        handles += _sections_meshes(scene, f"{root}/{who}_rejected", bad, GREY, thick, 0.3)
    focus = rows[view.focus_section] if view.focus_section is not None and view.focus_section < len(rows) else None
    if focus is not None and drawable(focus):
        handles += _sections_meshes(scene, f"{root}/focus", [focus.section], HIGHLIGHT, thick, 0.9, grow=1.08)
    ties = tie_mask(sec, sl, only)
    if ties.any():
        segs = np.stack([sec.tie_points_ref[ties], sec.tie_points_tgt[ties]], axis=1).astype(np.float32)
        handles.append(scene.add_line_segments(f"{root}/correspondences", segs, HIGHLIGHT, thickness=3.0,
                                               thickness_units="screen"))
        handles.append(scene.add_point_cloud(f"{root}/ties_ref", np.asarray(sec.tie_points_ref)[ties], scan_color(pair.ref),
                                             point_size=0.05, point_shape="circle", precision="float32"))
        handles.append(scene.add_point_cloud(f"{root}/ties_tgt", np.asarray(sec.tie_points_tgt)[ties], scan_color(pair.tgt),
                                             point_size=0.05, point_shape="circle", precision="float32"))
    # A plausible fit counts only when a section of the other scan corresponds to it.
    pairs = np.asarray(sec.correspondences.pairs, dtype=np.int64).reshape(-1, 2)
    paired = ({id(sec.ref.sections[i]) for i in pairs[:, 0]} | {id(sec.tgt.sections[j]) for j in pairs[:, 1]})
    table_rows = []
    listed = rows if only is not None else rows[:MAX_ROWS]
    for r in listed:
        s, fit = r.section, r.section.fit
        verdict = (("yes" if id(s) in paired else "no partner") if s.plausible else f"no: {md(s.reason)}")
        if not drawable(r):
            verdict += " (larger than its slice: not drawn)"
        mark = "▶ " if focus is r else ""
        where = () if only is not None else (s.slice_index + 1,)  # one slice shown: its number is said above
        table_rows.append((f"{mark}{r.number}", f"scan {r.scan_index + 1}", *where, s.kind, f"{s.radius_m * 100:.1f}",
                           f"{fit.rms_m * 1000:.1f}", f"{fit.arc_deg:.0f}", verdict))
    header = ("#", "scan", *(() if only is not None else ("slice",)), "fit", "r (cm)", "RMS (mm)", "arc (°)", "used")
    table = md_table(header, table_rows)
    n_bad = sum(not r.section.plausible for r in fit_rows(snap, t, sl, sec, ref, tgt, True, only)[0])
    notes = [f"Shown: {slice_label(only, sl.heights_m)} of {sl.n_slices} (pick another under *Slice*, Stage tab)."
             if only is not None else f"Shown: all {sl.n_slices} slices."]
    if len(listed) < len(rows):
        notes.append(f"The first {len(listed)} of {len(rows)} fits are listed: pick a slice under *Slice* to list "
                     "its fits.")
    if not view.show_rejected and n_bad:
        notes.append(f"{plural(n_bad, 'rejected fit')} hidden (tick *Show rejected fits* to list and draw them).")
    if hidden:
        notes.append(f"{plural(hidden, 'arc')} without a usable fit (too few points, or no section of the other "
                     "scan nearby) not listed.")
    if notes:
        table = " ".join(notes) + "\n\n" + table
    return handles, table, rows


def tie_mask(sec: SectionsResult, sl: SliceResult, only_slice: int | None) -> np.ndarray:
    """Which tie points to draw: all, or those of the sections fitted in slice `only_slice` (the
    ties come pair by pair of corresponding sections, in `correspondences.pairs` order: one per
    circle, two per cylinder)."""
    n = len(sec.tie_points_ref)
    if only_slice is None or n == 0:
        return np.ones(n, dtype=bool)
    keep: list[bool] = []
    for i, j in np.asarray(sec.correspondences.pairs, dtype=np.int64).reshape(-1, 2):
        a, b = sec.ref.sections[i], sec.tgt.sections[j]
        k = 1 if "circle" in (a.kind, b.kind) else 2
        keep += [a.slice_index == only_slice] * k
    return np.array(keep, dtype=bool) if len(keep) == n else np.ones(n, dtype=bool)


def focus_rows(snap: Snapshot, stage: str, view: ViewState) -> list[FitRow]:
    """The rows the fits table of stage `stage` ("sections" or "fine") lists for this view."""
    out = snap.output(stage)
    if out is None or not out.items:
        return []
    t = target_index(snap, stage, view)
    pair = snap.pair(t)
    if stage == "sections":
        sl, sec = pair.item("slices", SliceResult), pair.item("sections", SectionsResult)
    else:
        fine = pair.item("fine", FineResult)
        sl, sec = (fine.slices, fine.sections) if fine is not None else (None, None)
    if sl is None or not sl.ok or sec is None:
        return []
    ref, tgt = fine_scans(snap, t)
    return fit_rows(snap, t, sl, sec, ref, tgt, view.show_rejected, slice_shown(snap, t, view, sl.n_slices))[0]
