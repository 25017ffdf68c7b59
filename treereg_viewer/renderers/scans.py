"""The scan layer (always shown) and stage 0's panel: scans.Scan and ground.PreparedScan.

Each scan hangs under its own frame node `/scans/s<i>` whose pose is the scan's transform for the
current stage (identity before coarse, then the coarse, fine or ICP `T_ref_scan`): moving a scan is
a pose update of one node, not a resend of its points.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import viser

from ..controller import Snapshot
from ..palette import GREY, scan_color
from ..view_panel import PanelContent
from ..view_state import ViewState
from .common import display_subset, md_table, not_ready_text, pose_kwargs

#: Points a stage removed (ground, crop) are drawn lighter than kept points.
CROPPED = (205, 205, 205)


def scan_node(i: int) -> str:
    return f"/scans/s{i}"


def station_label_height(i: int) -> float:
    """Height (m, above its scanner) of scan `i`'s name: one line apart per scan."""
    return 1.3 + 0.5 * i


def scan_poses(snap: Snapshot, view: ViewState) -> list[np.ndarray]:
    """The pose of every scan for the current stage: its `T_ref_scan`, or identity.

    Stages 0-2 show each scan in its own scanner frame (before registration); 3 the coarse result;
    4-6 the pose the fine stage drew its slices, arcs and fits at (its final transform); 7 the
    final transform (or ICP's, when chosen).
    """
    n = len(snap.scans)
    poses = [np.eye(4) for _ in range(n)]
    if view.stage < 3:
        return poses
    coarse, fine, ev = snap.output("coarse"), snap.output("fine"), snap.output("evaluation")
    for k in range(1, n):
        T = None
        if coarse is not None and k - 1 < len(coarse.items) and coarse.items[k - 1].ok:
            T = coarse.items[k - 1].T_ref_target
        if view.stage >= 4:
            if view.stage == 7 and view.show_icp and ev is not None and k - 1 < len(ev.items) and getattr(ev.items[k - 1], "icp", None):
                T = ev.items[k - 1].icp.T
            elif fine is not None and k - 1 < len(fine.items):
                T = fine.items[k - 1].T_ref_tgt
        if T is not None:
            poses[k] = np.asarray(T, dtype=np.float64)
    return poses


def context_only(view: ViewState) -> bool:
    """Stages whose own drawings (slices, arcs) matter more than the scans: scans fade to a tint."""
    return view.stage in (4, 5)


def scans_shown(view: ViewState) -> bool:
    """The Fits stage hides the scans: points on a fitted surface would hide the surface."""
    return view.stage != 6


def draw_scan_layer(scene: viser.SceneApi, snap: Snapshot, view: ViewState) -> list[Any]:
    """Every scan's points in its colour (ground grey on stage 0), its station axes and name."""
    handles: list[Any] = []
    prepared = snap.output("prepare")
    for i, scan in enumerate(snap.scans):
        prep = prepared.items[i] if prepared is not None and i < len(prepared.items) else None
        color = np.array(scan_color(i), dtype=np.uint8)
        if context_only(view):  # slices, arcs and fits are the subject: the scans fade to a tint
            color = (0.3 * color + 0.7 * 255).astype(np.uint8)
        if view.stage == 0 or prep is None or not getattr(prep, "ok", False):
            # Stage 0 shows what was measured, with what preparation removes in grey.
            pts = scan.points
            idx = display_subset(len(pts), view.max_points, seed=i)
            colors = np.broadcast_to(color, (len(idx), 3)).copy()
            if prep is not None and getattr(prep, "kept_mask", None) is not None and len(prep.kept_mask) == len(pts):
                colors[~prep.kept_mask[idx]] = CROPPED
                colors[prep.ground_mask[idx]] = GREY
        else:
            pts = prep.scan.points
            idx = display_subset(len(pts), view.max_points, seed=i)
            colors = color
        node = scan_node(i)
        visible = scan.name not in view.hidden_scans
        handles.append(scene.add_frame(node, show_axes=False, visible=visible))
        handles.append(
            scene.add_point_cloud(
                f"{node}/points", pts[idx], colors, point_size=view.point_size,
                point_shape="circle", precision="float32",
            )
        )
        if view.show_stations:
            handles.append(scene.add_frame(f"{node}/station", axes_length=1.0, axes_radius=0.04))
            # Before registration every scanner sits at the origin of its own frame, i.e. at the same
            # point on screen: stack the names so they do not print over each other.
            handles.append(scene.add_label(f"{node}/station/name", f"{i + 1}: {scan.name}",
                                           position=(0.0, 0.0, station_label_height(i))))
    return handles


def apply_poses(handles: dict[int, Any], poses: list[np.ndarray]) -> None:
    """Move the scan frames (cheap: no points are sent)."""
    for i, T in enumerate(poses):
        h = handles.get(i)
        if h is not None:
            kw = pose_kwargs(T)
            h.wxyz, h.position = kw["wxyz"], kw["position"]


def render_scans_stage(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> tuple[list[Any], PanelContent]:
    """Stage 0's panel: a table of the scans and what preparation kept."""
    prepared = snap.output("prepare")
    rows = []
    for i, scan in enumerate(snap.scans):
        prep = prepared.items[i] if prepared is not None and i < len(prepared.items) else None
        phi, vphi = scan.angular_step_deg
        kept = ground = ""
        if prep is not None:
            kept = f"{prep.scan.n_points:,}" if getattr(prep, "scan", None) is not None else ""
            if getattr(prep, "ground_mask", None) is not None:
                ground = f"{int(np.count_nonzero(prep.ground_mask)):,}"
        rows.append((
            f"{i + 1}{' (reference)' if i == 0 else ''}", scan.name, f"{scan.n_points:,}",
            f"{phi:.3g} / {vphi:.3g}{' (est.)' if scan.step_estimated else ''}", kept, ground,
        ))
    table = md_table(("#", "scan", "points", "φ / ϕ (deg)", "kept", "ground"), rows)
    text = ""
    if prepared is None:
        text = not_ready_text(snap, "prepare") if len(snap.scans) >= 2 else (
            "*Registration needs at least two scans: upload another scan (Scans tab).*")
    else:
        bad = [f"**{snap.scans[i].name}:** {it.message}" for i, it in enumerate(prepared.items) if not it.ok]
        notes = [f"{snap.scans[i].name}: {it.message}" for i, it in enumerate(prepared.items) if it.ok and it.message]
        text = "\n\n".join(bad + notes) or "Grey points were removed as ground; light grey were cropped."
    if snap.truth:
        text += "\n\nTruth is known for this case (`truth.json`): the Result stage reports errors against it."
    return [], PanelContent("0 · Scans", text=text, table=table)
