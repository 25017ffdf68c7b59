"""The Slices, Arcs, Fits and Fine stages: SliceResult, SliceArcs, SectionsResult and FineResult.

Slices, arcs and fits are drawn as their stages made them, at the coarse pose (the paper slices the
coarsely aligned scans); the Fine stage draws the same three at the final pose, where the sections
of both scans should coincide. The target's slice points are mapped by the pose they were made at
(`rigid.apply_transform`); the sections are already in the reference frame.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import trimesh
import viser

from treereg_core.fine.arcs import SliceArcs
from treereg_core.fine.sections import SectionsResult
from treereg_core.fine.slicing import SliceResult
from treereg_core.geometry.rigid import apply_transform

from ..controller import Snapshot
from ..palette import GREY, HIGHLIGHT, categorical, scan_color
from ..view_panel import PanelContent
from ..view_state import ViewState
from .common import md_table, metrics_table, pair_label, target_index, title
from .scans import target_pose


def _scans(snap: Snapshot, t: int) -> tuple[Any, Any]:
    """The prepared reference and target scans of pair `t` (what the fine stages index into)."""
    prep = snap.output("prepare")
    return prep.items[0].scan, prep.items[t + 1].scan


def _slice_points(scene: viser.SceneApi, root: str, t: int, sl: SliceResult, T: np.ndarray, ref: Any, tgt: Any,
                  size: float) -> list[Any]:
    """Every slice's points of both scans in the reference frame, in the scans' colours."""
    handles: list[Any] = []
    for k in range(sl.n_slices):
        r_idx, t_idx = sl.ref_indices[k], sl.tgt_indices[k]
        if len(r_idx):
            handles.append(scene.add_point_cloud(f"{root}/ref{k}", ref.points[r_idx], scan_color(0), point_size=size,
                                                 point_shape="circle", precision="float32"))
        if len(t_idx):
            handles.append(scene.add_point_cloud(f"{root}/tgt{k}", apply_transform(T, tgt.points[t_idx]),
                                                 scan_color(t + 1), point_size=size, point_shape="circle",
                                                 precision="float32"))
    return handles


def _slice_text(snap: Snapshot, sl: SliceResult) -> str:
    q = snap.params.slicing.quantiles
    where = (f"quantiles {', '.join(f'{v:g}' for v in q)}" if len(q) <= 5
             else f"{len(q)} quantiles from {min(q):g} to {max(q):g}")
    text = (f"Slices {sl.thickness_m * 100:.0f} cm thick at {where} of the tree's height "
            f"({sl.z_extent_m[0]:.2f} to {sl.z_extent_m[1]:.2f} m, reference frame), the target at its coarse pose.")
    if not sl.ok:
        text += f"\n\n**Slicing failed:** {sl.message}"
    return text


def render_slices(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> tuple[list[Any], PanelContent]:
    t = target_index(snap, "slices", view)
    sl: SliceResult = snap.output("slices").items[t]
    ref, tgt = _scans(snap, t)
    T = target_pose(snap, "hypothesis", t)
    handles = _slice_points(scene, root, t, sl, T, ref, tgt, 2.0 * view.point_size)
    rows = []
    for k, h in enumerate(sl.heights_m):
        r_idx, t_idx = sl.ref_indices[k], sl.tgt_indices[k]
        anchor = ref.points[r_idx].mean(axis=0) if len(r_idx) else np.array([0.0, 0.0, h])
        handles.append(scene.add_label(f"{root}/label{k}", f"z = {h:.2f} m", position=(anchor[0], anchor[1], h),
                                       anchor="center-left"))
        rows.append((k + 1, f"{h:.2f}", f"{len(r_idx):,}", f"{len(t_idx):,}"))
    table = md_table(("slice", "height (m)", f"{snap.scans[0].name} points", f"{snap.scans[t + 1].name} points"), rows)
    table += "\n\n" + metrics_table({"slices": sl.metrics})
    return handles, PanelContent(title("slices", snap, t), text=_slice_text(snap, sl), table=table)


def _arc_points(scene: viser.SceneApi, root: str, ar: SliceArcs, T: np.ndarray, ref: Any, tgt: Any,
                size: float) -> tuple[list[Any], list[tuple[str, str]]]:
    """Both scans' arcs coloured one per arc; per slice the arc counts."""
    handles: list[Any] = []
    counts: list[tuple[str, str]] = []
    for k in range(max(len(ar.ref), len(ar.tgt))):
        row = []
        for who, arcs, scan, M, offset in (("ref", ar.ref, ref, None, 0), ("tgt", ar.tgt, tgt, T, 5)):
            if k >= len(arcs):
                row.append("")
                continue
            a = arcs[k]
            row.append(f"{a.n_arcs}" + ("" if a.ok else f" ({a.message})"))
            if len(a.indices) == 0:
                continue
            pts = scan.points[a.indices]
            if M is not None:
                pts = apply_transform(M, pts)
            # Offset the target's palette so its arcs do not look like the reference's.
            labels = np.where(a.labels >= 0, a.labels + offset, -1)
            handles.append(scene.add_point_cloud(f"{root}/{who}{k}", pts, categorical(labels), point_size=size,
                                                 point_shape="circle", precision="float32"))
        counts.append((row[0], row[1]))
    return handles, counts


def render_arcs(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> tuple[list[Any], PanelContent]:
    t = target_index(snap, "arcs", view)
    ar: SliceArcs = snap.output("arcs").items[t]
    sl: SliceResult = snap.output("slices").items[t]
    ref, tgt = _scans(snap, t)
    handles, counts = _arc_points(scene, root, ar, target_pose(snap, "hypothesis", t), ref, tgt, 2.0 * view.point_size)
    rows = [(k + 1, f"{sl.heights_m[k]:.2f}" if k < len(sl.heights_m) else "", *c) for k, c in enumerate(counts)]
    text = ("Each colour is one arc (connected component in the scan's own angular grid, "
            f"c = {snap.params.arcs.connectivity:g}); grey points belong to arcs smaller than "
            f"{snap.params.arcs.min_points} points. The target is at its coarse pose.")
    table = md_table(("slice", "height (m)", f"arcs in {snap.scans[0].name}", f"arcs in {snap.scans[t + 1].name}"), rows)
    table += "\n\n" + metrics_table({pair_label(snap, t): ar.metrics})
    return handles, PanelContent(title("arcs", snap, t), text=text, table=table)


def section_mesh(section: Any, thickness_m: float) -> trimesh.Trimesh:
    """A circle as a short vertical ring-cylinder at its slice; a cylinder along its axis."""
    centre = np.asarray(section.centre_m, dtype=float)
    axis = np.asarray(section.axis, dtype=float)
    axis = axis / (np.linalg.norm(axis) or 1.0)
    r = float(section.radius_m)
    length = thickness_m if section.kind == "circle" else max(float(getattr(section.fit, "length_m", thickness_m)), thickness_m)
    seg = np.stack([centre - axis * length / 2, centre + axis * length / 2])
    return trimesh.creation.cylinder(radius=r, segment=seg, sections=32)


def _sections_meshes(scene: viser.SceneApi, name: str, sections: list[Any], color: tuple[int, int, int],
                     thickness_m: float, opacity: float) -> list[Any]:
    ok = [s for s in sections if np.isfinite(s.radius_m) and s.radius_m > 0 and np.isfinite(s.centre_m).all()]
    if not ok:
        return []
    mesh = trimesh.util.concatenate([section_mesh(s, thickness_m) for s in ok])
    return [scene.add_mesh_simple(name, mesh.vertices.astype(np.float32), mesh.faces.astype(np.int32),
                                  color=color, opacity=opacity, side="double")]


def draw_sections(scene: viser.SceneApi, root: str, snap: Snapshot, t: int, sl: SliceResult, sec: SectionsResult,
                  ref: Any, tgt: Any, size: float) -> tuple[list[Any], str]:
    """The fitted sections of both scans (rejected ones grey), the sliced points as context and the
    tie lines between partners; returns the handles and the table of fits."""
    thick = sl.thickness_m
    # The scans are hidden on these stages (points on a fitted surface would hide it): the fitted
    # slices' points stay as context.
    handles: list[Any] = _slice_points(scene, root, t, sl, sec.T_ref_target, ref, tgt, size)
    rows = []
    for who, secs, color, name in (("ref", sec.ref.sections, scan_color(0), snap.scans[0].name),
                                   ("tgt", sec.tgt.sections, scan_color(t + 1), snap.scans[t + 1].name)):
        good = [s for s in secs if s.plausible]
        # Implausible fits are drawn grey, except absurdly large ones that would hide the tree.
        bad = [s for s in secs if not s.plausible and s.radius_m <= snap.params.fitting.max_radius_m]
        handles += _sections_meshes(scene, f"{root}/{who}_fits", good, color, thick, 0.55)
        handles += _sections_meshes(scene, f"{root}/{who}_rejected", bad, GREY, thick, 0.3)
        for s in secs:
            fit = s.fit
            rows.append((name, s.slice_index + 1, s.kind, f"{s.radius_m * 100:.1f}", f"{fit.rms_m * 1000:.1f}",
                         f"{fit.arc_deg:.0f}", "yes" if s.plausible else f"no: {s.reason}"))
    if len(sec.tie_points_ref):
        segs = np.stack([sec.tie_points_ref, sec.tie_points_tgt], axis=1).astype(np.float32)
        handles.append(scene.add_line_segments(f"{root}/correspondences", segs, HIGHLIGHT, thickness=3.0,
                                               thickness_units="screen"))
        handles.append(scene.add_point_cloud(f"{root}/ties_ref", np.asarray(sec.tie_points_ref), scan_color(0),
                                             point_size=0.05, point_shape="circle", precision="float32"))
        handles.append(scene.add_point_cloud(f"{root}/ties_tgt", np.asarray(sec.tie_points_tgt), scan_color(t + 1),
                                             point_size=0.05, point_shape="circle", precision="float32"))
    table = md_table(("scan", "slice", "fit", "radius (cm)", "RMS (mm)", "arc (°)", "plausible"), rows)
    return handles, table


def render_sections(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> tuple[list[Any], PanelContent]:
    t = target_index(snap, "sections", view)
    sec: SectionsResult = snap.output("sections").items[t]
    sl: SliceResult = snap.output("slices").items[t]
    ref, tgt = _scans(snap, t)
    handles, table = draw_sections(scene, root, snap, t, sl, sec, ref, tgt, view.point_size)
    n = sec.n_pairs
    text = (f"At the coarse pose, {n} corresponding section{'s' if n != 1 else ''} give {len(sec.tie_points_ref)} "
            "tie points (yellow lines join partners). Grey fits were judged implausible and are not used. Only "
            "the sliced points are shown with the fits.")
    if sec.message:
        text += f"\n\n{sec.message[0].upper()}{sec.message[1:]}."
    table += "\n\n" + metrics_table({pair_label(snap, t): sec.metrics})
    return handles, PanelContent(title("sections", snap, t), text=text, table=table)


def fine_status(snap: Snapshot, t: int, f: Any) -> str:
    """One sentence: was the fine update kept, after how many iterations, and why not."""
    verdict = "the fine update was **kept**" if f.accepted else "the coarse transform **stands**"
    text = f"{pair_label(snap, t)}: {verdict} ({f.iterations} iteration{'s' if f.iterations != 1 else ''})."
    if f.message:
        text += f" {f.message[0].upper()}{f.message[1:]}."
    return text


def render_fine(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> tuple[list[Any], PanelContent]:
    t = target_index(snap, "fine", view)
    f = snap.output("fine").items[t]
    text = fine_status(snap, t, f)
    handles: list[Any] = []
    table = ""
    if f.slices is not None and f.sections is not None:
        ref, tgt = _scans(snap, t)
        handles, table = draw_sections(scene, root, snap, t, f.slices, f.sections, ref, tgt, view.point_size)
        text += (f" Shown: the sections at the final pose ({f.sections.n_pairs} corresponding); partners should "
                 "now coincide.")
    table = metrics_table({pair_label(snap, t): f.metrics}) + ("\n\n" + table if table else "")
    return handles, PanelContent(title("fine", snap, t), text=text, table=table)


SLICES_VIEW_FIELDS = ("target", "point_size")
ARCS_VIEW_FIELDS = ("target", "point_size")
SECTIONS_VIEW_FIELDS = ("target", "point_size")
FINE_VIEW_FIELDS = ("target", "point_size")
