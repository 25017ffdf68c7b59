"""The Placement stage (`graph`): Placement — each scan's verdict and a graph of the stations (edges
coloured by verdict, loop errors on hover). All numbers come from the results; the app only draws them.
"""

from __future__ import annotations

import numpy as np
import plotly.graph_objects as go
import viser

from treereg_core.verify.graph import Edge, Placement

from ..controller import Snapshot
from ..draw.common import Drawing, md_table, title
from ..palette import hex_color, scan_color
from ..view_panel import PanelContent
from ..text import html, md
from ..view_state import ViewState
from .base import AppStage, StageView, TourStep
from ..labels import VERDICT_LEGEND, verdict_badge
from .verify import loosened_note


#: Edge colours of the station graph, by verdict.
EDGE_COLOR = {"verified": "#1e8c3c", "unverified": "#e0a000", "failed": "#c83232"}


def graph_figure(snap: Snapshot) -> go.Figure | None:
    """Stations from above at their placed positions, pairs as edges coloured by verdict."""
    graph = snap.output("graph")
    if graph is None or not graph.items:
        return None
    placements = graph.items_as(Placement)
    pos = {i: np.asarray(pl.T_ref_scan)[:2, 3] for i, pl in enumerate(placements) if pl.T_ref_scan is not None}
    fig = go.Figure()
    for e in placements[0].edges:
        if e.i not in pos or e.j not in pos:
            continue
        a, b = pos[e.i], pos[e.j]
        loop = f", loop error {e.loop_error_m * 1000:.1f} mm" if np.isfinite(e.loop_error_m) else ""
        fig.add_trace(go.Scatter(x=[a[0], b[0]], y=[a[1], b[1]], mode="lines", hoverinfo="text",
                                 line=dict(color=EDGE_COLOR.get(e.verdict, "#888"), width=4 if e.used else 2,
                                           dash="solid" if e.used else "dot"),
                                 text=html(f"{snap.scans[e.j].name} → {snap.scans[e.i].name}: {e.verdict}{loop}"
                                           f"{'' if e.used else ' (not used)'}"), showlegend=False))
    xs = [pos[i][0] for i in pos]
    ys = [pos[i][1] for i in pos]
    fig.add_trace(go.Scatter(
        x=xs, y=ys, mode="markers+text", text=[f"{i + 1}" for i in pos], textposition="top center",
        marker=dict(size=14, color=[hex_color(scan_color(i)) for i in pos], line=dict(width=2, color="white")),
        hovertext=[html(f"{snap.scans[i].name}: {placements[i].verdict}") for i in pos], hoverinfo="text", showlegend=False))
    fig.update_layout(margin=dict(l=40, r=10, t=30, b=40), title=dict(text="Stations (top view) and registered pairs",
                      font=dict(size=12)), xaxis_title="x (m, reference frame)", yaxis_title="y (m)",
                      yaxis=dict(scaleanchor="x", scaleratio=1))
    return fig


def render_graph(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> Drawing:
    graph = snap.output("graph")
    assert graph is not None  # the drawer draws a stage that has an output
    placements = graph.items_as(Placement)
    rows: list[tuple[str, str, str]] = []
    why: list[str] = []
    for i, (s, pl) in enumerate(zip(snap.scans, placements)):
        via = ", ".join(str(v + 1) for v in pl.via) or "–"
        rows.append((f"{i + 1}: {md(s.name)}", verdict_badge(pl.verdict), via))
        if pl.verdict != "verified":
            hint = f" Try: {md(pl.hint)}." if pl.hint else ""
            why.append(f"- **{verdict_badge(pl.verdict)} {md(s.name)}:** " + md("; ".join(pl.reasons)) + "." + hint)
    n_ok = sum(pl.verdict == "verified" for pl in placements)
    text = (f"{n_ok} of {len(placements)} scans verified ({VERDICT_LEGEND}). Verified and unverified scans are drawn "
            "at their placement, an unverified one pale (fewer, lighter points) and labelled a best guess; a failed one is not "
            "drawn. Solid edges: verified pairs used in the joint solve; dotted: pairs left out (unverified, failed, "
            "or dropped because a loop did not close).") + loosened_note(snap, "verified" if n_ok > 1 else "")
    if why:
        text += "\n\n" + "\n".join(why)
    plots: list[tuple[go.Figure, float]] = []
    fig = graph_figure(snap)
    if fig is not None and len(snap.scans) > 2:
        plots.append((fig, 1.3))
    table = md_table(("scan", "verdict", "placed through scans"), rows)
    edges = placements[0].edges if placements else ()
    limit = snap.params.verify.max_loop_m
    if edges:
        def loop(e: Edge) -> str:
            if not np.isfinite(e.loop_error_m):
                return "–"
            ok = e.loop_error_m <= limit
            return f"{'✓' if ok else '✗'} {e.loop_error_m * 1000:.2f}"

        table += "\n\n" + md_table(("pair", "verdict", f"loop error (mm, ≤ {limit * 1000:g}: verify.max_loop_m)",
                                     "used"), [
            (md(f"{snap.scans[e.j].name} → {snap.scans[e.i].name}"), verdict_badge(e.verdict), loop(e),
             "yes" if e.used else "no") for e in edges])
    return [], PanelContent(title("graph"), text=text, plots=tuple(plots), table=table)


STAGE = AppStage(
    "graph",
    StageView(
        "final",
        explanation="With three or more scans every verified pair is an edge of a graph of stations. Around a loop "
            "the transforms must compose to nothing; a pair that keeps a loop open is dropped. All poses are then "
            "solved together, so a station opposite the reference is placed through its neighbours. Each scan ends "
            "verified (with the evidence), unverified (the best guess and why) or failed.",
    ),
    draw=render_graph,
    view_fields=(),
    controls=(),
    tour=(
        TourStep(
            "graph", "Every station placed",
            "With three or more scans each verified pair is an edge between stations; around a loop the transforms must "
            "compose to nothing, and all poses are solved together. Each scan ends verified, unverified (best guess and "
            "why) or failed (not placed): the marks ✓, ⚠ and ✗ in the header.",
            "Look at the station graph: which pairs carry each scan to scan 1?",
            view={"panel": "stage"}),
    ),
)
