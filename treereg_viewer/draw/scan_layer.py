"""The scan layer, always shown under every stage's own drawing.

Each scan hangs under its own frame node `/scans/s<i>` whose pose is the scan's transform for the
current stage (identity before coarse, then the coarse, fine or ICP `T_ref_scan`): moving a scan is
a pose update of one node, not a resend of its points.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np
import viser

from treereg_core.prepare.ground import PreparedScan
from treereg_core.verify.graph import Placement

from ..controller import Snapshot
from ..palette import GREY, MIXED, MOVED, NO_RESIDUAL, residual_colors, scan_color
from ..stages import POSE_STAGE, registered, view_of
from ..view_state import ViewState
from .common import Handles, display_subset, pose_kwargs, target_pose

#: Points a stage removed (ground, crop) are drawn lighter than kept points.
CROPPED = (205, 205, 205)


def scan_node(i: int) -> str:
    return f"/scans/s{i}"


#: Opacity of a see-through scan's points.
SEE_THROUGH_OPACITY = 0.45
#: Height (m, above its scanner) of a scanner's name.
STATION_LABEL_Z = 1.3


def stage_pose(view: ViewState) -> str | None:
    """The registration the current stage shows the targets at (the Result stage: the view's choice)."""
    if view.stage == "evaluation":
        return view.result_pose
    return view_of(view.stage).pose


def see_through(view: ViewState) -> bool:
    """The Result stage draws the scans see-through (half-transparent splats): where they overlap,
    both colours show, so no scan hides another."""
    return view.stage == "evaluation" and view.result_colour == "seethrough"


def residual_mode(view: ViewState) -> bool:
    """The Result stage colours each point by its distance to the other scans' surface."""
    return view.stage == "evaluation" and view.result_colour == "residual"


def scan_poses(snap: Snapshot, view: ViewState) -> list[np.ndarray]:
    """The pose of every scan on the current stage: its `T_ref_scan` for the stage's pose (see
    `stages.StageView.pose`), or the identity (each scan in its own scanner frame)."""
    pose = stage_pose(view)
    poses = [np.eye(4) for _ in snap.scans]
    for k in range(1, len(snap.scans)):
        pair = snap.reference_pair(k)
        T = target_pose(snap, pose, pair.index) if pair is not None else None
        if T is not None:
            poses[k] = T
    return poses


def context_only(view: ViewState) -> bool:
    """Stages whose own drawings (slices, arcs) matter more than the scans: scans fade to a tint."""
    return view_of(view.stage).scans == "faded"


def scans_shown(view: ViewState) -> bool:
    """Stages that draw fitted surfaces hide the scans: points on a surface would hide it."""
    return view_of(view.stage).scans != "hidden"


def verdict_shown(snap: Snapshot, view: ViewState, i: int) -> str:
    """How scan i is marked in 3-D on this stage: "" (verified, or before registration), "unverified"
    (drawn at its best guess, ghosted and labelled) or "failed" (labelled; not drawn where the scans
    stand at their final placement, ghosted at a pair's own pose for inspection)."""
    # The placement's verdicts only: before it has run a scan has none (not "unverified").
    placement = snap.scan_item("graph", i, Placement)
    if i == 0 or not registered(view.stage) or placement is None:
        return ""
    verdict = placement.verdict
    return verdict if verdict in ("unverified", "failed") else ""


#: An unverified (or inspected failed) scan: every GHOST_STRIDE-th point, lightened by GHOST_LIGHT.
GHOST_STRIDE = 3
GHOST_LIGHT = 0.55


def _verdict_label(snap: Snapshot, view: ViewState, i: int, mark: str,
                   over: np.ndarray) -> tuple[str, tuple[float, float, float]]:
    """The 3-D label of scan i, marked `mark`, and where it goes: above the points `over`."""
    name = snap.scans[i].name
    if mark == "unverified":
        text = f"⚠ {name}: unverified, best guess"
    elif stage_pose(view) == "final":
        text = f"✗ {name}: failed, not placed"
    else:
        text = f"✗ {name}: failed (this stage's pose, for inspection)"
    top = np.array([*np.median(over[:, :2], axis=0), float(np.quantile(over[:, 2], 0.99)) + 0.4 + 0.5 * i])
    return text, (float(top[0]), float(top[1]), float(top[2]))


def scan_layer_key(snap: Snapshot, view: ViewState) -> tuple[Any, ...]:
    """What the scan layer's points depend on (it is redrawn only when this changes)."""
    residual = ((view.result_pose, view.residual_max_m, id(snap.output(POSE_STAGE.get(view.result_pose, view.result_pose))))
                if residual_mode(view) else None)
    return (tuple(id(s) for s in snap.scans), id(snap.output("prepare")), view.stage == "prepare", context_only(view),
            view.point_size, view.max_points, view.show_stations, registered(view.stage), residual, see_through(view),
            view.show_mixed and view.stage == "prepare",
            tuple(verdict_shown(snap, view, i) for i in range(len(snap.scans))), stage_pose(view) == "final")


def draw_scan_layer(scene: viser.SceneApi, snap: Snapshot, view: ViewState,
                    residuals: list[np.ndarray] | None = None, moved: list[np.ndarray] | None = None) -> Handles:
    """Every scan's points in its colour (ground grey on stage 1) or, given `residuals` (per scan,
    the distances of its displayed points to the other scans), coloured by distance, the points that
    `moved` with the wind in their own colour; its station axes and name. On the Scans stage the
    mixed pixels the preparation removed are drawn too, when the view asks."""
    handles: Handles = []
    apart = not registered(view.stage)
    for i, scan in enumerate(snap.scans):
        prep = snap.scan_item("prepare", i, PreparedScan)
        color = np.array(scan_color(i), dtype=np.uint8)
        if context_only(view):  # slices, arcs and fits are the subject: the scans fade to a tint
            color = (0.3 * color + 0.7 * 255).astype(np.uint8)
        mixed = None
        if view.stage == "prepare" or prep is None or not prep.ok:
            # The Scans stage shows the station as the stages take it (at the working resolution),
            # with what preparation removes in grey and, on request, its mixed pixels.
            station = prep.station if prep is not None else None
            pts = station.points if station is not None else scan.points
            idx = display_subset(len(pts), view.max_points, seed=i)
            colors = np.broadcast_to(color, (len(idx), 3)).copy()
            if prep is not None and len(prep.kept_mask) == len(pts):
                colors[~prep.kept_mask[idx]] = CROPPED
                colors[prep.ground_mask[idx]] = GREY
            removed = prep.mixed_points if prep is not None else None
            if view.stage == "prepare" and view.show_mixed and removed is not None and len(removed):
                mixed = removed[display_subset(len(removed), view.max_points // 4, seed=i)]
        else:
            pts = prep.scan.points
            idx = display_subset(len(pts), view.max_points, seed=i)
            colors = color
            if residuals is not None and i < len(residuals) and len(residuals[i]) == len(idx):
                colors = residual_colors(residuals[i], view.residual_max_m)
                if moved is not None and i < len(moved) and len(moved[i]) == len(idx):
                    colors[moved[i]] = MOVED
            elif residuals is not None:
                colors = np.array(NO_RESIDUAL, dtype=np.uint8)  # not registered under this pose
        node = scan_node(i)
        visible = scan.name not in view.hidden_scans
        handles.append(scene.add_frame(node, show_axes=False, visible=visible))
        mark = verdict_shown(snap, view, i)
        if mark == "failed" and stage_pose(view) == "final":
            # Not placed: nothing to draw where the registered scans stand; the label stands above the
            # reference's tree (in the reference frame, not under this scan's node).
            reference = snap.scan_item("prepare", 0, PreparedScan)
            ref_pts = reference.scan.points if reference is not None and reference.ok else pts
            text, where = _verdict_label(snap, view, i, mark, ref_pts[display_subset(len(ref_pts), 5000, seed=1)])
            handles.append(scene.add_label(f"/scans/verdict{i}", text, position=where, anchor="bottom-center"))
            continue
        if mark:
            text, where = _verdict_label(snap, view, i, mark, pts[idx])
            handles.append(scene.add_label(f"{node}/verdict", text, position=where, anchor="bottom-center"))
            # A best guess (or a failed pair at its own pose) is drawn ghosted: fewer, lighter points.
            full = np.broadcast_to(np.asarray(colors, dtype=float).reshape(-1, 3), (len(idx), 3))[::GHOST_STRIDE]
            idx = idx[::GHOST_STRIDE]
            colors = (full * (1 - GHOST_LIGHT) + 255 * GHOST_LIGHT).astype(np.uint8)
        if see_through(view) and prep is not None and prep.ok:
            # Gaussian splats blend: half-transparent discs of about the point size.
            n = len(idx)
            sigma = view.point_size  # world-sized: much smaller and a distant tree renders below a pixel
            rgb = np.broadcast_to(np.asarray(colors, np.float32).reshape(-1, 3) / 255.0, (n, 3))
            handles.append(scene.add_gaussian_splats(
                f"{node}/points", centers=pts[idx].astype(np.float32),
                covariances=np.broadcast_to(np.eye(3, dtype=np.float32) * sigma * sigma, (n, 3, 3)).copy(),
                rgbs=np.ascontiguousarray(rgb), opacities=np.full((n, 1), SEE_THROUGH_OPACITY, np.float32)))
        else:
            handles.append(
                scene.add_point_cloud(
                    f"{node}/points", pts[idx], colors, point_size=view.point_size,
                    point_shape="circle", precision="float32",
                )
            )
        if mixed is not None:
            handles.append(scene.add_point_cloud(f"{node}/mixed", mixed, MIXED, point_size=view.point_size * 1.2,
                                                 point_shape="circle", precision="float32"))
        if view.show_stations:
            handles.append(scene.add_frame(f"{node}/station", axes_length=1.0, axes_radius=0.04))
            # Before registration every scanner sits at the origin of its own frame, i.e. at the same
            # point on screen: one label names them all instead of names printed over each other.
            if not apart:
                handles.append(scene.add_label(f"{node}/station/name", f"scanner {i + 1}: {scan.name}",
                                               position=(0.0, 0.0, STATION_LABEL_Z)))
            elif i == 0:
                n = len(snap.scans)
                who = "scanner 1" if n == 1 else f"scanners 1–{n}" if n > 2 else "scanners 1 and 2"
                handles.append(scene.add_label(f"{node}/station/name", f"{who} (own origins)",
                                               position=(0.0, 0.0, STATION_LABEL_Z)))
    return handles


def apply_poses(handles: Mapping[int, viser.SceneNodeHandle], poses: list[np.ndarray]) -> None:
    """Move the scan frames (cheap: no points are sent)."""
    for i, T in enumerate(poses):
        h = handles.get(i)
        if h is not None:
            kw = pose_kwargs(T)
            h.wxyz, h.position = kw["wxyz"], kw["position"]
