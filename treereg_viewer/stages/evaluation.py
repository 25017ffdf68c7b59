"""The Result stage: PairReport (an EvaluationResult each for coarse, fine and ICP)

The scan layer shows the targets at the registration chosen (coarse, fine or ICP), in the scans'
colours or coloured by each point's distance to the other scans' surface (the residual a person
judges a registration by; computed by treereg_core, see `derived.Derived.residuals`). The panel:
the paper's evaluation (mean branch-centre distance d̄, eq. 8) of coarse, fine and ICP side by
side, with the errors against truth when the case has a truth.json; a plot of the per-branch
errors; the per-branch table. In 3-D: each evaluated branch layer as a ring, with its number.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np
import plotly.graph_objects as go
import trimesh
import viser

from treereg_core.evaluate.branches import BranchError, EvaluationResult
from treereg_core.evaluate.report import PairReport
from treereg_core.fine.pose import FineResult

from ..checks import TRUTH_DISP_M, TRUTH_ROT_DEG, stage_warnings, truth_rows
from ..controller import Snapshot
from ..draw.common import Drawing, Handles, branch_names, md_table, metrics_table, pair_label, target_index, title
from ..draw.motion import motion_sentence, profile_figure
from ..palette import HIGHLIGHT, residual_legend, scan_color
from ..view_panel import PanelContent
from ..text import html, md
from ..view_state import ViewState
from .base import AppStage, ControlHost, StageControls, StageView, TargetControl, TourStep


#: Colours of the three registrations in plots (coarse, fine, ICP).
#: The registrations' bar colours: grey, near black and light blue, none close to a scan's colour (fine
#: and ICP were scan 1's green and scan 3's blue: `palette.distinct_from_scans`).
METHOD_COLORS = {"coarse": "#9e9e9e", "fine": "#282828", "ICP": "#96c8ff"}


def branch_rows(ev: EvaluationResult) -> list[BranchError]:
    """The evaluation's per-branch rows (empty if it has none)."""
    return list(ev.branches)


def _where(name: str, b: BranchError) -> str:
    """'stem at 1.31 m' or 'branch 2 at 3.54 m'."""
    return name if name.startswith("stem") else f"{name} at {b.height_m:.2f} m"


def branch_figure(evs: Mapping[str, EvaluationResult], target: str) -> go.Figure | None:
    """Grouped bars: mean centre distance per branch (the stem's sections first), one colour per
    registration (paper Figs. 13-14)."""
    names = branch_names(b for ev in evs.values() for b in ev.branches)
    fig = go.Figure()
    any_rows = False
    for label, ev in evs.items():
        rows = [b for b in branch_rows(ev) if len(b.distances_m)]
        if not rows:
            continue
        any_rows = True
        fig.add_trace(go.Bar(
            x=[names[b.index].replace(" at ", " ") for b in rows], y=[b.mean_m * 1000.0 for b in rows], name=label,
            marker_color=METHOD_COLORS.get(label),
            hovertext=[f"{_where(names[b.index], b)}, r = {b.radius_m * 100:.1f} cm" for b in rows],
        ))
    if not any_rows:
        return None
    # Legend at the figure's foot, under the axis title (above the plot it printed over the title; a
    # share of the plot's height under the axes, over the axis title in a 310 px panel).
    fig.update_layout(barmode="group", margin=dict(l=50, r=10, t=30, b=120),
                      legend=dict(orientation="h", x=0.5, xanchor="center", yref="container", y=0.0, yanchor="bottom"),
                      title=dict(text=f"{html(target)}: mean centre distance (eq. 8)", font=dict(size=12)),
                      xaxis_title="stem and branches (bottom to top)", yaxis_title="d̄ (mm)", xaxis_type="category")
    return fig


def branch_rings(scene: viser.SceneApi, root: str, ev: EvaluationResult, color: tuple[int, int, int],
                 names: Mapping[int, str]) -> Handles:
    """The evaluated branches, visible: a yellow ring around the branch at each evaluated layer, the
    reference's and the target's layer centres, the segments joining them (the d_i of eq. 8, often
    only millimetres long) and the branch's name (`names`: the stem's sections are named so)."""
    rows = [b for b in branch_rows(ev) if len(b.distances_m)]
    if not rows:
        return []
    verts: list[np.ndarray] = []
    faces: list[np.ndarray] = []
    for b in rows:
        axis = np.asarray(b.axis, dtype=float)
        for c in b.ref_centres_m:
            ring = trimesh.creation.annulus(r_min=b.radius_m * 1.15, r_max=b.radius_m * 1.15 + 0.025, height=0.025,
                                            segment=np.stack([c - axis * 0.0125, c + axis * 0.0125]), sections=40)
            faces.append(ring.faces + sum(len(v) for v in verts))
            verts.append(ring.vertices)
    ref = np.concatenate([b.ref_centres_m for b in rows]).astype(np.float32)
    tgt = np.concatenate([b.tgt_centres_m for b in rows]).astype(np.float32)
    handles: Handles = [
        scene.add_mesh_simple(f"{root}/branches", np.concatenate(verts).astype(np.float32),
                              np.concatenate(faces).astype(np.int32), color=HIGHLIGHT, opacity=0.95, side="double"),
        scene.add_line_segments(f"{root}/d", np.stack([ref, tgt], axis=1), HIGHLIGHT, thickness=3.0,
                                thickness_units="screen"),
        scene.add_point_cloud(f"{root}/ref_centres", ref, scan_color(0), point_size=0.02, point_shape="circle",
                              precision="float32"),
        scene.add_point_cloud(f"{root}/tgt_centres", tgt, color, point_size=0.02, point_shape="circle",
                              precision="float32"),
    ]
    for b in rows:
        x, y, z = (float(v) for v in b.ref_centres_m[-1] + np.array([0.0, 0.0, b.radius_m + 0.08]))
        handles.append(scene.add_label(f"{root}/label{b.index}", f"{names[b.index]}: d̄ {b.mean_m * 1000:.1f} mm",
                                       position=(x, y, z)))
    return handles


#: Registrations as the Result stage names them (pose key -> the evaluation's method name). The
#: branches are evaluated per pair, so the final (joint) placement shows the pair's fine evaluation.
METHOD_OF_POSE = {"coarse": "coarse", "fine": "fine", "final": "fine", "icp": "ICP"}


POSE_NAMES = {"coarse": "coarse", "fine": "pairwise fine", "final": "final (joint placement)", "icp": "ICP"}


def render(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> Drawing:
    t = target_index(snap, "evaluation", view)
    report = snap.pair(t).item("evaluation", PairReport)
    assert report is not None, t  # the drawer draws a pair that was not skipped
    evs = report.by_method()
    method = METHOD_OF_POSE.get(view.result_pose, "fine")
    if method not in evs:
        method = "fine"
    shown_at = POSE_NAMES.get(view.result_pose, view.result_pose)
    text = f"Targets shown at their **{shown_at}** pose. "
    fine = snap.output("fine")
    notes = []
    # Each pair's fine result (None for a skipped pair).
    fines = [snap.pair(k).item("fine", FineResult) for k in range(len(fine.items))] if fine is not None else []
    for k, f in enumerate(fines):
        if f is not None and f.ok and not f.accepted and f.message:
            notes.append(f"{md(pair_label(snap, k))}: {md(f.message)}.")
    if snap.truth:
        text += "Errors against truth come from the case's `truth.json`."
    else:
        text += "No truth is known for these scans: the paper's branch measure d̄ is the yardstick."
    text += (" Yellow rings in 3-D mark the evaluated branch layers, labelled with their mean centre distance d̄; "
             "pick a branch under *Section of* in the cross-section view to see its layers.")
    images: list[tuple[np.ndarray, str]] = []
    if view.result_colour == "residual":
        text += (f"\n\nEach point is coloured by its distance to the other scans' surface (0 to "
                 f"{view.residual_max_m * 1000:.0f} mm and beyond); light grey: no other scan's point within "
                 f"{max(30, 1.5 * view.residual_max_m * 1000):.0f} mm (seen by its own scan only).")
        images.append((residual_legend(view.residual_max_m),
                       f"0 mm — {view.residual_max_m * 1000 / 2:.0f} mm — {view.residual_max_m * 1000:.0f} mm and more"))
        if any(f is not None and f.bend is not None for f in fines):
            text += (f" **Pink: moved with the wind**: farther than {view.residual_max_m * 1000:.0f} mm from the other "
                     "scans as registered, within it once each target's crown motion (its stem's fitted bend) is taken "
                     "out. Red points do not fit even then.")
    truth = truth_rows(snap)
    if truth:  # the analyst's first question, answered above the plot
        text += "\n\n" + md_table(
            # Short headers: the verdict column must fit the panel without scrolling sideways.
            ("target", "regis&shy;tration", f"within {TRUTH_ROT_DEG:g}°, {TRUTH_DISP_M * 100:g} cm", "rotation (°)",
             "mean displace&shy;ment (mm)"),
            [(md(pair), label, "yes" if good else "**no**", f"{rot:.3f}", f"{disp * 1000:.1f}")
             for pair, label, rot, disp, good in truth_rows(snap, names_only=True)])
    if notes:
        text += "\n\n" + "\n\n".join(notes)
    text += "".join(f"\n\n{w}" for w in stage_warnings(snap).get("evaluation", []))
    if not report.ok and report.message:
        text += f"\n\n**Evaluation:** {md(report.message)}"
    plots: list[tuple[go.Figure, float]] = []
    pair = snap.pair(t)
    fine_item = pair.item("fine", FineResult)
    ref_name, tgt_name = pair.ref_scan.name, pair.tgt_scan.name
    tol = snap.params.wind.stable_tolerance_m
    motion = motion_sentence(fine_item, ref_name, tgt_name, tol) if fine_item is not None else ""
    if motion and fine_item is not None and fine_item.bend is not None:
        text += "\n\n" + motion
        prof_fig = profile_figure(fine_item, ref_name, tgt_name, pair.tgt, tol)
        if prof_fig is not None:
            plots.append((prof_fig, 1.2))
    fig = branch_figure(evs, pair_label(snap, t))
    if fig is not None:
        plots.append((fig, 1.6))
    # One row per metric, one column per registration of the chosen target (the paper's Table 2 layout).
    columns = {label: ev.metrics for label, ev in evs.items()}
    table = metrics_table(columns) if report.ok else ""
    names = branch_names(b for ev in evs.values() for b in ev.branches)
    rows: list[tuple[str, str, str, str, str, str]] = []
    for label, ev in evs.items():
        for b in branch_rows(ev):
            d = ", ".join(f"{x * 1000:.1f}" for x in b.distances_m)
            rows.append((label, names[b.index].split(" at ")[0], f"{b.height_m:.2f}", f"{b.radius_m * 100:.1f}", d, f"{b.mean_m * 1000:.1f}"))
    if rows:
        table += "\n\n" + md_table(("regis&shy;tration", "branch", "height (m)", "r (cm)", "d₁…dₙ (mm)", "d̄ (mm)"), rows)
    shown = evs.get(method)
    handles = branch_rings(scene, root, shown, scan_color(pair.tgt), names) if shown is not None else []
    return handles, PanelContent(title("evaluation", snap, t), text=text, images=tuple(images), plots=tuple(plots),
                                 table=table)


#: The Result stage's choices, as people read them.
RESULT_POSES = {"Final": "final", "Pairwise fine": "fine", "Coarse": "coarse", "ICP": "icp"}
RESULT_COLOURS = {"Scan colours": "scan", "Scan colours, see-through": "seethrough",
                  "Distance to the other scans": "residual"}


class ResultControls(StageControls):
    """"Targets at" (which registration), "Colour by" and "Colour map top (mm)"."""

    def __init__(self, gui: viser.GuiApi, host: ControlHost, stage: str) -> None:
        self.pose = gui.add_button_group("Targets at", tuple(RESULT_POSES))
        self.pose.on_click(lambda e: host.set_view(result_pose=RESULT_POSES[e.target.value]))
        self.colour = gui.add_dropdown("Colour by", tuple(RESULT_COLOURS), initial_value="Scan colours",
                                       hint="Scan colours (opaque or see-through where scans overlap), or "
                                       "each point's distance to the other scans' surface.")
        self.colour.on_update(lambda _: host.set_view(result_colour=RESULT_COLOURS[self.colour.value]))
        self.residual_max = gui.add_slider("Colour map top (mm)", 2, 100, 1, 20,
                                           hint="Distances from here on get the top colour (red).")
        self.residual_max.on_update(lambda _: host.set_view(residual_max_m=float(self.residual_max.value) / 1000.0))

    def show_view(self, view: ViewState, snap: Snapshot) -> None:
        # viser's dropdown and slider redeclare `value` with a getter only; the base class's setter applies.
        self.colour.value = next(k for k, v in RESULT_COLOURS.items() if v == view.result_colour)  # type: ignore[misc]
        self.residual_max.value = max(2, min(100, round(view.residual_max_m * 1000)))  # type: ignore[misc]


STAGE = AppStage(
    "evaluation",
    StageView(
        "final",
        explanation="The final overlay. The paper judges a registration by its branches: in three layers of each "
            "corresponding branch, cylinder axes are fitted in both scans and the distances between centre "
            "points at equal height averaged, d̄ (eq. 8, 3.3), here for each pair's own fine transform. The targets "
            "are drawn at their final (joint) placement unless you pick another. ICP from the coarse result is shown beside it, "
            "as the paper compares. When a truth.json comes with the scans (the demo, simulated cases), the "
            "errors against it are listed first; ✗ marks a registration far from the truth. Colour the points by their "
            "distance to the other scans to see where the scans agree.",
    ),
    draw=render,
    view_fields=("target", "result_pose", "result_colour", "residual_max_m"),
    controls=(TargetControl, ResultControls),
    tour=(
        TourStep(
            "evaluation", "Judging the result",
            "The paper judges a registration by its branches: three layers per branch, the distance between the scans' "
            "fitted centres, averaged (eq. 8, Table 2). Here each point is also coloured by its distance to the other "
            "scans' surface: blue where they agree, red where they do not, pink where they moved with the wind (they fit "
            "once the crown's measured motion is taken out).",
            "Switch *Targets at* between Final, Coarse and ICP and watch the colours change.",
            view={"panel": "stage", "result_colour": "residual", "result_pose": "final"}),
    ),
)
