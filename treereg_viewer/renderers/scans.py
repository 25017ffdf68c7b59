"""The scan layer (always shown) and the Scans stage's panel: Scan and PreparedScan.

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
from ..stages import view_of
from ..view_panel import PanelContent
from ..view_state import ViewState
from .common import display_subset, md_table, not_ready_text, pose_kwargs, title

#: Points a stage removed (ground, crop) are drawn lighter than kept points.
CROPPED = (205, 205, 205)


def scan_node(i: int) -> str:
    return f"/scans/s{i}"


def station_label_height(i: int) -> float:
    """Height (m, above its scanner) of scan `i`'s name: one line apart per scan."""
    return 1.3 + 0.5 * i


def target_pose(snap: Snapshot, pose: str | None, k: int) -> np.ndarray | None:
    """Pair `k`'s transform for a view's `pose` ("coarse", "fine", "icp"), falling back to the
    best earlier one that succeeded; None before registration or when none did."""
    order = {"coarse": ("coarse",), "fine": ("fine", "coarse"), "icp": ("icp", "fine", "coarse")}.get(pose or "", ())
    for name in order:
        out = snap.output(name)
        item = out.items[k] if out is not None and k < len(out.items) else None
        if item is not None and item.ok and getattr(item, "ran", True):
            return np.asarray(item.T_ref_target, dtype=np.float64)
    return None


def scan_poses(snap: Snapshot, view: ViewState) -> list[np.ndarray]:
    """The pose of every scan on the current stage: its `T_ref_scan` for the stage's pose (see
    `stages.StageView.pose`), or the identity (each scan in its own scanner frame)."""
    pose = view_of(view.stage).pose
    if view.stage == "evaluation" and view.show_icp:
        pose = "icp"
    poses = [np.eye(4) for _ in snap.scans]
    for k in range(1, len(snap.scans)):
        T = target_pose(snap, pose, k - 1)
        if T is not None:
            poses[k] = T
    return poses


def context_only(view: ViewState) -> bool:
    """Stages whose own drawings (slices, arcs) matter more than the scans: scans fade to a tint."""
    return view_of(view.stage).scans == "faded"


def scans_shown(view: ViewState) -> bool:
    """Stages that draw fitted surfaces hide the scans: points on a surface would hide it."""
    return view_of(view.stage).scans != "hidden"


def draw_scan_layer(scene: viser.SceneApi, snap: Snapshot, view: ViewState) -> list[Any]:
    """Every scan's points in its colour (ground grey on stage 0), its station axes and name."""
    handles: list[Any] = []
    prepared = snap.output("prepare")
    for i, scan in enumerate(snap.scans):
        prep = prepared.items[i] if prepared is not None and i < len(prepared.items) else None
        color = np.array(scan_color(i), dtype=np.uint8)
        if context_only(view):  # slices, arcs and fits are the subject: the scans fade to a tint
            color = (0.3 * color + 0.7 * 255).astype(np.uint8)
        if view.stage == "prepare" or prep is None or not getattr(prep, "ok", False):
            # The Scans stage shows what was measured, with what preparation removes in grey.
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


def render(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> tuple[list[Any], PanelContent]:
    """The Scans stage's panel: a table of the scans and what preparation kept."""
    prepared = snap.output("prepare")
    rows = []
    for i, scan in enumerate(snap.scans):
        prep = prepared.items[i] if prepared is not None and i < len(prepared.items) else None
        # The steps in force: the prepared scan's (a given step replaces the estimate), else the
        # parameter's when one is set and the stage has not run yet, else the scan's own.
        used = getattr(prep, "scan", None)
        given = snap.params.prepare.angular_step_deg
        phi, vphi = used.angular_step_deg if used is not None else given or scan.angular_step_deg
        estimated = used.step_estimated if used is not None else given is None and scan.step_estimated
        kept = ground = ""
        if prep is not None:
            kept = f"{prep.scan.n_points:,}" if getattr(prep, "scan", None) is not None else ""
            if getattr(prep, "ground_mask", None) is not None:
                ground = f"{int(np.count_nonzero(prep.ground_mask)):,}"
        rows.append((
            f"{i + 1}{' (reference)' if i == 0 else ''}", scan.name, f"{scan.n_points:,}",
            f"{phi:.3g} / {vphi:.3g}{' (est.)' if estimated else ''}", kept, ground,
        ))
    table = md_table(("#", "scan", "points", "φ / ϕ (deg)", "kept", "ground"), rows)
    text = not_ready_text(snap, "prepare")
    if prepared is not None:
        bad = [f"**{snap.scans[i].name}:** {it.message}" for i, it in enumerate(prepared.items) if not it.ok]
        notes = [f"{snap.scans[i].name}: {it.message}" for i, it in enumerate(prepared.items) if it.ok and it.message]
        text = "\n\n".join(bad + notes) or "Grey points were removed as ground; light grey were cropped."
    if snap.truth:
        text += "\n\nTruth is known for this case (`truth.json`): the Result stage reports errors against it."
    return [], PanelContent(title("prepare"), text=text, table=table)


#: Drawn even before the stage has run: the table of scans is the first thing a user needs.
NEEDS_OUTPUT = False
