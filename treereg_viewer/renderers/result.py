"""Stage 7: pipeline.PairReport (evaluation.EvaluationResult for coarse, fine and ICP, icp.IcpResult).

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

from ..controller import Snapshot
from ..view_panel import PanelContent
from ..view_state import ViewState
from .common import md_table, metrics_table, not_ready_text, pair_label

#: Colours of the three registrations in plots (coarse, fine, ICP).
METHOD_COLORS = {"coarse": "#9e9e9e", "fine": "#1e8c3c", "ICP": "#3050c8"}


def _evaluations(report: Any) -> dict[str, Any]:
    """{'coarse': ev, 'fine': ev, 'ICP': ev} for what the report holds."""
    out = {"coarse": report.coarse, "fine": report.fine}
    if getattr(report, "icp_eval", None) is not None:
        out["ICP"] = report.icp_eval
    return {k: v for k, v in out.items() if v is not None}


def branch_rows(ev: Any) -> list[Any]:
    """The evaluation's per-branch rows (empty if it has none)."""
    return list(getattr(ev, "branches", ()) or ())


def branch_figure(evs: dict[str, Any], target: str) -> go.Figure | None:
    """Grouped bars: mean centre distance per branch, one colour per registration (paper Figs. 13-14)."""
    fig = go.Figure()
    any_rows = False
    for label, ev in evs.items():
        rows = [b for b in branch_rows(ev) if np.isfinite(getattr(b, "mean_distance_m", np.nan))]
        if not rows:
            continue
        any_rows = True
        fig.add_trace(go.Bar(
            x=[f"{getattr(b, 'name', k + 1)}" for k, b in enumerate(rows)],
            y=[b.mean_distance_m * 100.0 for b in rows], name=label, marker_color=METHOD_COLORS.get(label),
        ))
    if not any_rows:
        return None
    fig.update_layout(barmode="group", margin=dict(l=50, r=10, t=30, b=40), legend=dict(orientation="h", y=1.12),
                      title=dict(text=f"{target}: mean centre distance per branch (eq. 8)", font=dict(size=12)),
                      xaxis_title="branch", yaxis_title="d̄ (cm)")
    return fig


def render_result(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> tuple[list[Any], PanelContent]:
    out = snap.output("evaluation")
    if out is None or not out.items:
        return [], PanelContent("7 · Result", text=not_ready_text(snap, "evaluation"))
    t = min(view.target, len(out.items) - 1)
    report = out.items[t]
    evs = _evaluations(report)
    pose = "ICP" if view.show_icp and getattr(report, "icp", None) is not None else "fine"
    text = f"Targets shown at their **{pose}** pose. "
    fine = snap.output("fine")
    notes = []
    if fine is not None:
        for k, f in enumerate(fine.items):
            if not f.accepted and f.message:
                notes.append(f"{pair_label(snap, k)}: {f.message}.")
    if snap.truth:
        text += "Errors against truth come from the demo's `truth.json`."
    else:
        text += "No truth is known for these scans: the paper's branch measure d̄ is the yardstick."
    if notes:
        text += "\n\n" + "\n\n".join(notes)
    if not report.ok and report.message:
        text += f"\n\n**Evaluation:** {report.message}"
    plots = []
    fig = branch_figure(evs, pair_label(snap, t))
    if fig is not None:
        plots.append((fig, 1.6))
    # One column per registration of each target: the paper's Table 2 layout.
    columns = {}
    for k, rep in enumerate(out.items):
        for label, ev in _evaluations(rep).items():
            columns[f"{rep.target} {label}"] = ev.metrics
    table = metrics_table(columns)
    rows = []
    for label, ev in evs.items():
        for b in branch_rows(ev):
            rows.append((label, getattr(b, "name", ""), *(getattr(b, f, "") for f in ("n_layers",)),
                         f"{getattr(b, 'mean_distance_m', float('nan')) * 100:.2f}"))
    if rows:
        table += "\n\n" + md_table(("registration", "branch", "layers", "d̄ (cm)"), rows)
    return [], PanelContent(f"7 · Result: {pair_label(snap, t)}", text=text, plots=tuple(plots), table=table)
