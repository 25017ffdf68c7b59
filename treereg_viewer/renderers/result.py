"""The Result stage: PairReport (an EvaluationResult each for coarse, fine and ICP)

The scan layer shows the final overlay (fine, or ICP when chosen). The panel: per target, the
paper's evaluation (mean branch-centre distance d̄, eq. 8) for coarse, fine and ICP side by side,
with the errors against truth when the case has a truth.json; a plot of the per-branch errors; the
per-branch table.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import plotly.graph_objects as go
import viser

from ..checks import TRUTH_DISP_M, TRUTH_ROT_DEG, truth_rows, truth_warnings
from ..controller import Snapshot
from ..palette import scan_color
from ..view_panel import PanelContent
from ..view_state import ViewState
from .common import md_table, metrics_table, pair_label, target_index, title

#: Colours of the three registrations in plots (coarse, fine, ICP).
METHOD_COLORS = {"coarse": "#9e9e9e", "fine": "#1e8c3c", "ICP": "#3050c8"}


def branch_rows(ev: Any) -> list[Any]:
    """The evaluation's per-branch rows (empty if it has none)."""
    return list(getattr(ev, "branches", ()) or ())


def branch_figure(evs: dict[str, Any], target: str) -> go.Figure | None:
    """Grouped bars: mean centre distance per branch, one colour per registration (paper Figs. 13-14)."""
    fig = go.Figure()
    any_rows = False
    for label, ev in evs.items():
        rows = [b for b in branch_rows(ev) if len(b.distances_m)]
        if not rows:
            continue
        any_rows = True
        fig.add_trace(go.Bar(
            x=[f"{b.index + 1}" for b in rows], y=[b.mean_m * 100.0 for b in rows], name=label,
            marker_color=METHOD_COLORS.get(label),
            hovertext=[f"branch {b.index + 1} at {b.height_m:.2f} m, r = {b.radius_m * 100:.1f} cm" for b in rows],
        ))
    if not any_rows:
        return None
    # Legend under the axis title: above the plot it printed over the title.
    fig.update_layout(barmode="group", margin=dict(l=50, r=10, t=30, b=70),
                      legend=dict(orientation="h", x=0.5, xanchor="center", y=-0.3, yanchor="top"),
                      title=dict(text=f"{target}: mean centre distance per branch (eq. 8)", font=dict(size=12)),
                      xaxis_title="branch (bottom to top)", yaxis_title="d̄ (cm)", xaxis_type="category")
    return fig


def _branch_lines(scene: viser.SceneApi, root: str, ev: Any, color: tuple[int, int, int]) -> list[Any]:
    """The evaluated layer centres of each branch in both scans, joined (the d_i of eq. 8)."""
    rows = [b for b in branch_rows(ev) if len(b.distances_m)]
    if not rows:
        return []
    ref = np.concatenate([b.ref_centres_m for b in rows]).astype(np.float32)
    tgt = np.concatenate([b.tgt_centres_m for b in rows]).astype(np.float32)
    return [
        scene.add_line_segments(f"{root}/d", np.stack([ref, tgt], axis=1), (250, 200, 0), thickness=3.0,
                                thickness_units="screen"),
        scene.add_point_cloud(f"{root}/ref_centres", ref, scan_color(0), point_size=0.06, point_shape="circle",
                              precision="float32"),
        scene.add_point_cloud(f"{root}/tgt_centres", tgt, color, point_size=0.06, point_shape="circle",
                              precision="float32"),
    ]


def render(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> tuple[list[Any], PanelContent]:
    out = snap.output("evaluation")
    t = target_index(snap, "evaluation", view)
    report = out.items[t]
    evs = report.by_method()
    pose = "ICP" if view.show_icp and report.icp is not None else "fine"
    shown_at = "ICP" if pose == "ICP" else "final (joint placement)"
    text = f"Targets shown at their **{shown_at}** pose. "
    fine = snap.output("fine")
    notes = []
    if fine is not None:
        for k, f in enumerate(fine.items):
            if f.ok and not f.accepted and f.message:
                notes.append(f"{pair_label(snap, k)}: {f.message}.")
    if snap.truth:
        text += "Errors against truth come from the case's `truth.json`."
    else:
        text += "No truth is known for these scans: the paper's branch measure d̄ is the yardstick."
    text += " Yellow segments in 3-D join the centre points of the evaluated branch layers (the dᵢ of eq. 8)."
    truth = truth_rows(snap)
    if truth:  # the analyst's first question, answered above the plot
        text += "\n\n" + md_table(
            ("target", "registration", "rotation error (°)", "mean displacement (mm)",
             f"within {TRUTH_ROT_DEG:g}° and {TRUTH_DISP_M * 100:g} cm"),
            [(pair, label, f"{rot:.3f}", f"{disp * 1000:.1f}", "yes" if good else "**no**")
             for pair, label, rot, disp, good in truth_rows(snap, names_only=True)])
    if notes:
        text += "\n\n" + "\n\n".join(notes)
    text += "".join(f"\n\n**⚠** {w}" for w in truth_warnings(snap))
    if not report.ok and report.message:
        text += f"\n\n**Evaluation:** {report.message}"
    plots = []
    fig = branch_figure(evs, pair_label(snap, t))
    if fig is not None:
        plots.append((fig, 1.6))
    # One column per registration of each target: the paper's Table 2 layout.
    columns = {}
    for k, rep in enumerate(out.items):
        if not rep.ok:
            continue
        for label, ev in rep.by_method().items():
            columns[f"{rep.target} {label}"] = ev.metrics
    table = metrics_table(columns)
    rows = []
    for label, ev in evs.items():
        for b in branch_rows(ev):
            d = ", ".join(f"{x * 100:.1f}" for x in b.distances_m)
            rows.append((label, b.index + 1, f"{b.height_m:.2f}", f"{b.radius_m * 100:.1f}", d, f"{b.mean_m * 100:.2f}"))
    if rows:
        table += "\n\n" + md_table(("registration", "branch", "height (m)", "radius (cm)", "d₁…dₙ (cm)", "d̄ (cm)"), rows)
    shown = report.icp if pose == "ICP" else report.fine
    handles = _branch_lines(scene, root, shown, scan_color(t + 1)) if shown is not None else []
    return handles, PanelContent(title("evaluation", snap, t), text=text, plots=tuple(plots), table=table)


VIEW_FIELDS = ("target", "show_icp")
