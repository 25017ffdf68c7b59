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
from ..palette import GREY, MIXED, MOVED, NO_RESIDUAL, residual_colors, scan_color
from ..stages import POSE_STAGE, registered, view_of
from ..view_panel import PanelContent
from ..view_state import ViewState
from .common import Drawing, display_subset, md_table, not_ready_text, pose_kwargs, title

#: Points a stage removed (ground, crop) are drawn lighter than kept points.
CROPPED = (205, 205, 205)


def scan_node(i: int) -> str:
    return f"/scans/s{i}"


#: Opacity of a see-through scan's points.
SEE_THROUGH_OPACITY = 0.45
#: Height (m, above its scanner) of a scanner's name.
STATION_LABEL_Z = 1.3
#: Where the stem markers start without a ground plane: the scanner's foot, 1.5 m below it.
SCANNER_FOOT_Z = -1.5


def target_pose(snap: Snapshot, pose: str | None, k: int) -> np.ndarray | None:
    """Pair `k`'s transform for a view's `pose` ("coarse", "hypothesis", "fine", "icp", "final"),
    falling back to the best earlier one that succeeded; None before registration or when none did.
    "final" is the joint placement of scan k + 1 (the graph stage), k being its pair with the reference."""
    if pose == "final":
        graph = snap.output("graph")
        item = graph.items[k + 1] if graph is not None and k + 1 < len(graph.items) else None
        if item is not None and item.T_ref_scan is not None:
            return np.asarray(item.T_ref_scan, dtype=np.float64)
    order = {"coarse": ("coarse",), "hypothesis": ("hypotheses", "coarse"), "fine": ("fine", "hypotheses", "coarse"),
             "icp": ("icp", "fine", "coarse"), "final": ("fine", "hypotheses", "coarse")}.get(pose or "", ())
    for name in order:
        out = snap.output(name)
        item = out.items[k] if out is not None and k < len(out.items) else None
        if item is not None and item.ok and getattr(item, "ran", True):
            return np.asarray(item.T_ref_target, dtype=np.float64)
    return None


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


def scan_layer_key(snap: Snapshot, view: ViewState) -> tuple[Any, ...]:
    """What the scan layer's points depend on (it is redrawn only when this changes)."""
    residual = ((view.result_pose, view.residual_max_m, id(snap.output(POSE_STAGE.get(view.result_pose, view.result_pose))))
                if residual_mode(view) else None)
    return (tuple(id(s) for s in snap.scans), id(snap.output("prepare")), view.stage == "prepare", context_only(view),
            view.point_size, view.max_points, view.show_stations, registered(view.stage), residual, see_through(view),
            view.show_mixed and view.stage == "prepare")


def draw_scan_layer(scene: viser.SceneApi, snap: Snapshot, view: ViewState,
                    residuals: list[np.ndarray] | None = None, moved: list[np.ndarray] | None = None) -> list[Any]:
    """Every scan's points in its colour (ground grey on stage 1) or, given `residuals` (per scan,
    the distances of its displayed points to the other scans), coloured by distance, the points that
    `moved` with the wind in their own colour; its station axes and name. On the Scans stage the
    mixed pixels the preparation removed are drawn too, when the view asks."""
    handles: list[Any] = []
    prepared = snap.output("prepare")
    apart = not registered(view.stage)
    for i, scan in enumerate(snap.scans):
        prep = prepared.items[i] if prepared is not None and i < len(prepared.items) else None
        color = np.array(scan_color(i), dtype=np.uint8)
        if context_only(view):  # slices, arcs and fits are the subject: the scans fade to a tint
            color = (0.3 * color + 0.7 * 255).astype(np.uint8)
        mixed = None
        if view.stage == "prepare" or prep is None or not getattr(prep, "ok", False):
            # The Scans stage shows the station as the stages take it (at the working resolution),
            # with what preparation removes in grey and, on request, its mixed pixels.
            station = getattr(prep, "station", None) if prep is not None else None
            pts = station.points if station is not None else scan.points
            idx = display_subset(len(pts), view.max_points, seed=i)
            colors = np.broadcast_to(color, (len(idx), 3)).copy()
            if prep is not None and getattr(prep, "kept_mask", None) is not None and len(prep.kept_mask) == len(pts):
                colors[~prep.kept_mask[idx]] = CROPPED
                colors[prep.ground_mask[idx]] = GREY
            removed = getattr(prep, "mixed_points", None) if prep is not None else None
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
        if see_through(view) and prep is not None and getattr(prep, "ok", False):
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


def apply_poses(handles: dict[int, Any], poses: list[np.ndarray]) -> None:
    """Move the scan frames (cheap: no points are sent)."""
    for i, T in enumerate(poses):
        h = handles.get(i)
        if h is not None:
            kw = pose_kwargs(T)
            h.wxyz, h.position = kw["wxyz"], kw["position"]


def _stem_markers(scene: viser.SceneApi, root: str, snap: Snapshot) -> list[Any]:
    """The target tree of each scan (a tall line at its stem, in the scan's colour, labelled) and the
    other stems found at breast height (short grey lines), in each scan's own frame."""
    prepared = snap.output("prepare")
    handles: list[Any] = []
    if prepared is None:
        return handles
    for i, prep in enumerate(prepared.items):
        stems = getattr(prep, "stems", None)
        if stems is not None and len(stems):
            base = prep.ground_z(stems[:, :2], SCANNER_FOOT_Z)
            segs = np.stack([np.column_stack([stems[:, :2], base]), np.column_stack([stems[:, :2], base + 2.0])], axis=1)
            handles.append(scene.add_line_segments(f"{root}/s{i}/stems", segs, GREY, thickness=2.0, thickness_units="screen"))
        xy = getattr(prep, "stem_xy", None)
        if xy is not None and getattr(prep, "target", ""):
            z = float(prep.ground_z(np.asarray([xy]), SCANNER_FOOT_Z)[0])
            seg = np.array([[[xy[0], xy[1], z], [xy[0], xy[1], z + 12.0]]])
            handles.append(scene.add_line_segments(f"{root}/s{i}/target", seg, scan_color(i), thickness=5.0,
                                                   thickness_units="screen"))
            handles.append(scene.add_label(f"{root}/s{i}/target/name", f"target ({snap.scans[i].name})",
                                           position=(xy[0], xy[1], z + 12.5 + 0.5 * i)))
    return handles


def render(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> Drawing:
    """The Scans stage's panel: a table of the scans, what preparation kept and which tree it took."""
    prepared = snap.output("prepare")
    rows = []
    stood_down: list[str] = []
    for i, scan in enumerate(snap.scans):
        prep = prepared.items[i] if prepared is not None and i < len(prepared.items) else None
        # The instrument's steps in force: the parameter's when one is set (it replaces the
        # estimate in the prepare stage), else the scan's own (read off its grid, or estimated).
        given = snap.params.prepare.angular_step_deg
        phi, vphi = given or scan.angular_step_deg
        kept = ground = target = mixed = ""
        if prep is not None:
            removed = getattr(prep, "mixed_points", None)
            mixed = f"{len(removed):,}" if removed is not None and snap.params.prepare.mixed_pixels else "off"
            # The filter stood down on this scan (no regular grid, a surface rougher than it): say why.
            why = next((m.value for m in getattr(prep, "metrics", ()) if m.description == "mixed pixels removed"
                        and isinstance(m.value, str) and m.value != "off"), None)
            if why is not None:
                mixed = "not filtered"
                stood_down.append(f"{scan.name}: mixed pixels {why}.")
            kept = f"{prep.scan.n_points:,}" if getattr(prep, "scan", None) is not None else ""
            if getattr(prep, "ground_mask", None) is not None:
                ground = f"{int(np.count_nonzero(prep.ground_mask)):,}"
            xy = getattr(prep, "stem_xy", None)
            target = f"{xy[0]:.2f}, {xy[1]:.2f}" if xy is not None and getattr(prep, "target", "") else "all points"
        step = scan.step
        how = "" if given or step is None or step.source == "given" else (" (grid)" if step.source == "grid" else f" (est., {step.confidence:.2f})")
        rows.append((
            f"{i + 1}{' (reference)' if i == 0 else ''}", scan.name, f"{scan.n_points:,}",
            f"{phi:.3g} / {vphi:.3g}{how}", mixed, kept, ground, target,
        ))
    table = md_table(("#", "scan", "points", "φ / ϕ (deg)", "mixed pixels", "kept", "ground",
                      "target stem x, y (m)"), rows)
    text = not_ready_text(snap, "prepare")
    if prepared is not None:
        bad = [f"**{snap.scans[i].name}:** {it.message}" for i, it in enumerate(prepared.items) if not it.ok]
        notes = [f"{snap.scans[i].name}: {it.message}" for i, it in enumerate(prepared.items) if it.ok and it.message]
        notes += stood_down
        text = "\n\n".join(bad + notes) or "Grey points were removed as ground; light grey were cropped."
        if snap.params.prepare.mixed_pixels:
            text += (" Near-black: mixed pixels, returns strung out behind a stem's or branch's edge (the beam "
                     "straddled it), removed before anything else; the free-space test is blind where they were.")
        chosen = getattr(prepared.items[0], "target", "") if prepared.items else ""
        if chosen and getattr(prepared.items[0], "stem_xy", None) is not None:
            text += (f"\n\n**Target tree:** {chosen}. The tall line marks it in every scan, grey lines the other stems; "
                     "to take another tree, type its stem's x, y (reference scan's frame) into *tree at* below.")
    if snap.truth:
        text += "\n\nTruth is known for this case (`truth.json`): the Result stage reports errors against it."
    return _stem_markers(scene, root, snap), PanelContent(title("prepare"), text=text, table=table)


#: Drawn even before the stage has run: the table of scans is the first thing a user needs.
NEEDS_OUTPUT = False
