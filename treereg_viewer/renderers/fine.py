"""Stages 4-6: fine.FineResult — its slices, arcs and fits, drawn in the reference frame.

The fine result carries the slices, arcs and fitted sections of its last iteration, at the pose it
returns (`T_ref_tgt`); the scan layer shows the targets at that pose on these stages, so the
target's slice points are mapped with it (`rigid.apply_transform`) and its sections are already
in the reference frame.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import trimesh
import viser

from treereg_core.rigid import apply_transform

from ..controller import Snapshot
from ..palette import GREY, HIGHLIGHT, categorical, scan_color
from ..view_panel import PanelContent
from ..view_state import ViewState
from .common import md_table, metrics_table, not_ready_text, pair_label


def _fine_context(snap: Snapshot, view: ViewState) -> tuple[int, Any, Any, Any] | None:
    """(target index, FineResult, prepared reference scan, prepared target scan) or None."""
    out, prep = snap.output("fine"), snap.output("prepare")
    if out is None or prep is None or not out.items:
        return None
    t = min(view.target, len(out.items) - 1)
    return t, out.items[t], prep.items[0].scan, prep.items[t + 1].scan


def _status_text(snap: Snapshot, t: int, f: Any) -> str:
    verdict = "the fine update was **kept**" if f.accepted else "the coarse transform **stands**"
    text = f"{pair_label(snap, t)}: {verdict} ({f.iterations} iteration{'s' if f.iterations != 1 else ''})."
    if f.message:
        text += f" {f.message[0].upper()}{f.message[1:]}."
    return text


def _slice_points(scene: viser.SceneApi, root: str, t: int, f: Any, ref: Any, tgt: Any, size: float) -> list[Any]:
    """Every slice's points of both scans in the reference frame, in the scans' colours."""
    handles: list[Any] = []
    sl = f.slices
    if sl is None:
        return handles
    for k in range(sl.n_slices):
        r_idx, t_idx = sl.ref_indices[k], sl.tgt_indices[k]
        if len(r_idx):
            handles.append(scene.add_point_cloud(f"{root}/ref{k}", ref.points[r_idx], scan_color(0), point_size=size,
                                                 point_shape="circle", precision="float32"))
        if len(t_idx):
            pts = apply_transform(f.T_ref_tgt, tgt.points[t_idx])
            handles.append(scene.add_point_cloud(f"{root}/tgt{k}", pts, scan_color(t + 1), point_size=size,
                                                 point_shape="circle", precision="float32"))
    return handles


def render_slices(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> tuple[list[Any], PanelContent]:
    ctx = _fine_context(snap, view)
    if ctx is None:
        return [], PanelContent("4 · Slices", text=not_ready_text(snap, "fine"))
    t, f, ref, tgt = ctx
    sl = f.slices
    handles: list[Any] = []
    rows = []
    if sl is not None:
        handles += _slice_points(scene, root, t, f, ref, tgt, 2.0 * view.point_size)
        for k, h in enumerate(sl.heights_m):
            r_idx, t_idx = sl.ref_indices[k], sl.tgt_indices[k]
            anchor = ref.points[r_idx].mean(axis=0) if len(r_idx) else np.array([0.0, 0.0, h])
            handles.append(scene.add_label(f"{root}/label{k}", f"z = {h:.2f} m", position=(anchor[0], anchor[1], h),
                                           anchor="center-left"))
            rows.append((k + 1, f"{h:.2f}", f"{len(r_idx):,}", f"{len(t_idx):,}"))
    text = _status_text(snap, t, f)
    if sl is not None:
        q = snap.params.slicing.quantiles
        where = (f"quantiles {', '.join(f'{v:g}' for v in q)}" if len(q) <= 5
                 else f"{len(q)} quantiles from {min(q):g} to {max(q):g}")
        text += (f" Slices {sl.thickness_m * 100:.0f} cm thick at {where} of the tree's height "
                 f"({sl.z_extent_m[0]:.2f} to {sl.z_extent_m[1]:.2f} m, reference frame).")
        if not sl.ok:
            text += f"\n\n**Slicing failed:** {sl.message}"
    table = md_table(("slice", "height (m)", f"{snap.scans[0].name} points", f"{snap.scans[t + 1].name} points"), rows)
    if sl is not None and sl.metrics:
        table += "\n\n" + metrics_table({"slices": sl.metrics})
    return handles, PanelContent(f"4 · Slices: {pair_label(snap, t)}", text=text, table=table)


def render_arcs(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> tuple[list[Any], PanelContent]:
    ctx = _fine_context(snap, view)
    if ctx is None:
        return [], PanelContent("5 · Arcs", text=not_ready_text(snap, "fine"))
    t, f, ref, tgt = ctx
    handles: list[Any] = []
    rows = []
    size = 2.0 * view.point_size
    heights = f.slices.heights_m if f.slices is not None else ()
    for k in range(max(len(f.ref_arcs), len(f.tgt_arcs))):
        counts = []
        for who, arcs, scan, T, offset in (("ref", f.ref_arcs, ref, None, 0), ("tgt", f.tgt_arcs, tgt, f.T_ref_tgt, 5)):
            if k >= len(arcs):
                counts.append("")
                continue
            a = arcs[k]
            counts.append(f"{a.n_arcs}" + ("" if a.ok else f" ({a.message})"))
            if len(a.indices) == 0:
                continue
            pts = scan.points[a.indices]
            if T is not None:
                pts = apply_transform(T, pts)
            # Offset the target's palette so its arcs do not look like the reference's.
            labels = np.where(a.labels >= 0, a.labels + offset, -1)
            handles.append(scene.add_point_cloud(f"{root}/{who}{k}", pts, categorical(labels), point_size=size,
                                                 point_shape="circle", precision="float32"))
        h = f"{heights[k]:.2f}" if k < len(heights) else ""
        rows.append((k + 1, h, *counts))
    text = (_status_text(snap, t, f) + " Each colour is one arc (connected component in the scan's own angular grid, "
            f"c = {snap.params.arcs.connectivity:g}); grey points belong to arcs smaller than "
            f"{snap.params.arcs.min_points} points.")
    table = md_table(("slice", "height (m)", f"arcs in {snap.scans[0].name}", f"arcs in {snap.scans[t + 1].name}"), rows)
    return handles, PanelContent(f"5 · Arcs: {pair_label(snap, t)}", text=text, table=table)


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


def render_fits(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> tuple[list[Any], PanelContent]:
    ctx = _fine_context(snap, view)
    if ctx is None:
        return [], PanelContent("6 · Fits", text=not_ready_text(snap, "fine"))
    t, f, ref, tgt = ctx
    thick = f.slices.thickness_m if f.slices is not None else snap.params.slicing.thickness_m
    # The scans are hidden on this stage (points on a fitted surface would hide it): the fitted
    # slices' points stay as context.
    handles: list[Any] = _slice_points(scene, root, t, f, ref, tgt, view.point_size)
    rows = []
    for who, secs, color, name in (("ref", f.ref_sections, scan_color(0), snap.scans[0].name),
                                   ("tgt", f.tgt_sections, scan_color(t + 1), snap.scans[t + 1].name)):
        good = [s for s in secs if s.plausible]
        # Implausible fits are drawn grey, except absurdly large ones that would hide the tree.
        bad = [s for s in secs if not s.plausible and s.radius_m <= snap.params.fitting.max_radius_m]
        handles += _sections_meshes(scene, f"{root}/{who}_fits", good, color, thick, 0.55)
        handles += _sections_meshes(scene, f"{root}/{who}_rejected", bad, GREY, thick, 0.3)
        for s in secs:
            fit = s.fit
            rows.append((name, s.slice_index + 1, s.kind, f"{s.radius_m * 100:.1f}", f"{fit.rms_m * 1000:.1f}",
                         f"{fit.arc_deg:.0f}", "yes" if s.plausible else f"no: {s.reason}"))
    if len(f.tie_points_ref):
        segs = np.stack([f.tie_points_ref, f.tie_points_tgt], axis=1).astype(np.float32)
        handles.append(scene.add_line_segments(f"{root}/correspondences", segs, HIGHLIGHT, thickness=3.0,
                                               thickness_units="screen"))
        handles.append(scene.add_point_cloud(f"{root}/ties_ref", np.asarray(f.tie_points_ref), scan_color(0),
                                             point_size=0.05, point_shape="circle", precision="float32"))
        handles.append(scene.add_point_cloud(f"{root}/ties_tgt", np.asarray(f.tie_points_tgt), scan_color(t + 1),
                                             point_size=0.05, point_shape="circle", precision="float32"))
    n_corr = len(f.correspondences.pairs) if f.correspondences is not None else 0
    text = (_status_text(snap, t, f) + f" {n_corr} corresponding sections give {len(f.tie_points_ref)} tie points "
            "(yellow lines join partners). Grey fits were judged implausible and not used. Only the sliced "
            "points are shown with the fits.")
    table = md_table(("scan", "slice", "fit", "radius (cm)", "RMS (mm)", "arc (°)", "plausible"), rows)
    table += "\n\n" + metrics_table({pair_label(snap, t): f.metrics})
    return handles, PanelContent(f"6 · Fits: {pair_label(snap, t)}", text=text, table=table)
