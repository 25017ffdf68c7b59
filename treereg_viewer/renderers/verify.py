"""The Hypotheses, Verify and Placement stages: HypothesesResult, PairVerification, Placement.

Hypotheses: the target drawn at every competing pose (rivals grey, the chosen one in its colour)
over the reference, and the table of their scores. Verify: each pair's evidence and verdict.
Placement: each scan's verdict and a graph of the stations (edges coloured by verdict, loop
errors on hover). All numbers come from the results; the app only draws them.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import plotly.graph_objects as go
import viser

from treereg_core.geometry.rigid import apply_transform
from treereg_core.verify.report import verdict_text

from ..controller import Snapshot
from ..palette import GREY, hex_color, scan_color
from ..view_panel import PanelContent
from ..view_state import ViewState
from .common import Drawing, display_subset, md_table, metrics_table, pair_label, plural, target_index, title

#: How each verdict reads in the app.
BADGE = {"verified": "✓ verified", "unverified": "⚠ unverified", "failed": "✗ failed"}
#: Edge colours of the station graph, by verdict.
EDGE_COLOR = {"verified": "#1e8c3c", "unverified": "#e0a000", "failed": "#c83232"}


def render_hypotheses(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> Drawing:
    t = target_index(snap, "hypotheses", view)
    h = snap.output("hypotheses").items[t]
    tgt = snap.output("prepare").items[t + 1].scan
    idx = display_subset(tgt.n_points, min(view.max_points, 15_000), seed=t)
    handles: list[Any] = []
    rows = []
    for n, c in enumerate(h.candidates):
        chosen = c.label == h.chosen
        colour = scan_color(t + 1) if chosen else GREY
        if not chosen:  # the chosen pose is where the scan layer already draws the target
            handles.append(scene.add_point_cloud(f"{root}/candidate{n}", apply_transform(c.T_ref_target, tgt.points[idx]),
                                                 colour, point_size=view.point_size * 0.7, point_shape="circle",
                                                 precision="float32"))
        v = c.visibility
        rows.append((("**" + c.label + "**") if chosen else c.label, c.support or "", f"{v.consistency:.3f}",
                     f"{v.seen_by_both:,}", f"{v.violations:,}"))
    if not h.candidates:
        text = f"{pair_label(snap, t)}: {h.message[0].upper()}{h.message[1:]}."
    else:
        hand = " (chosen by hand)" if h.chosen_by_hand else ""
        text = (f"{pair_label(snap, t)}: **{h.chosen}**{hand} is the most consistent pose; the best distinct rival, "
                f"{h.runner_up or 'none'}, is {h.margin:.3f} less consistent. Grey: the rivals at their polished "
                "poses. Consistency: the share of the points both stations see that lie where the reference saw a "
                "surface, not in space its laser passed through.")
        if h.unscored_modes:  # the coarse stage counts every mode: say where the missing ones went
            text += (f" Not scored: {plural(h.unscored_modes, 'further RANSAC mode')} with fewer than "
                     f"{snap.params.hypotheses.min_mode_support} agreeing ties (hypotheses.min_mode_support).")
    table = md_table(("hypothesis", "tie support", "consistency", "seen by both", "in free space"), rows)
    return handles, PanelContent(title("hypotheses", snap, t), text=text, table=table)


def render_verify(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> Drawing:
    out = snap.output("verify")
    t = target_index(snap, "verify", view)
    v = out.items[t]
    text = f"{pair_label(snap, t)}: **{BADGE.get(v.verdict, v.verdict)}**.{_loosened_note(snap, v.verdict)}"
    e = getattr(v, "evidence", None)
    if e is not None and e.sway_m > 0:
        stable = f"; the stems agree up to {e.stable_height_m:.1f} m above the base" if np.isfinite(e.stable_height_m) else ""
        text += (f" The crown moved {e.sway_m:.2f} m between the stations (the stem top){stable}. The evidence is "
                 f"measured with the target unbent by that motion; {e.moved:,} of its points the reference saw "
                 f"through lie within {e.motion_m * 100:.0f} cm of a surface the reference saw and count as moved "
                 "(small branches in the wind), not against the pose.")
    if v.reasons:
        text += "\n\n" + "\n\n".join(f"- {r[0].upper()}{r[1:]}." for r in v.reasons)
        if v.hint:
            text += f"\n\nTry: {v.hint}."
    labels = [f"{snap.scans[p.tgt].name} → {snap.scans[p.ref].name}" for p in snap.pairs] or \
        [pair_label(snap, k) for k in range(len(out.items))]
    table = metrics_table({lab: it.metrics for lab, it in zip(labels, out.items)})
    return [], PanelContent(title("verify", snap, t), text=text, table=table)


def _loosened_note(snap: Snapshot, verdict: str) -> str:
    """" ⚠ Verified under loosened thresholds (…)." when a verified verdict rests on a threshold set looser
    than its default; the same words as transforms.json and the command line."""
    text = verdict_text(verdict, snap.params) if verdict == "verified" else ""
    return f" ⚠ {text[0].upper()}{text[1:]}." if text and text != "verified" else ""


def graph_figure(snap: Snapshot) -> go.Figure | None:
    """Stations from above at their placed positions, pairs as edges coloured by verdict."""
    graph = snap.output("graph")
    if graph is None or not graph.items:
        return None
    pos = {i: np.asarray(pl.T_ref_scan)[:2, 3] for i, pl in enumerate(graph.items) if pl.T_ref_scan is not None}
    fig = go.Figure()
    for e in graph.items[0].edges:
        if e.i not in pos or e.j not in pos:
            continue
        a, b = pos[e.i], pos[e.j]
        loop = f", loop error {e.loop_error_m * 1000:.1f} mm" if np.isfinite(e.loop_error_m) else ""
        fig.add_trace(go.Scatter(x=[a[0], b[0]], y=[a[1], b[1]], mode="lines", hoverinfo="text",
                                 line=dict(color=EDGE_COLOR.get(e.verdict, "#888"), width=4 if e.used else 2,
                                           dash="solid" if e.used else "dot"),
                                 text=f"{snap.scans[e.j].name} → {snap.scans[e.i].name}: {e.verdict}{loop}"
                                      f"{'' if e.used else ' (not used)'}", showlegend=False))
    xs = [pos[i][0] for i in pos]
    ys = [pos[i][1] for i in pos]
    fig.add_trace(go.Scatter(
        x=xs, y=ys, mode="markers+text", text=[f"{i + 1}" for i in pos], textposition="top center",
        marker=dict(size=14, color=[hex_color(scan_color(i)) for i in pos], line=dict(width=2, color="white")),
        hovertext=[f"{snap.scans[i].name}: {graph.items[i].verdict}" for i in pos], hoverinfo="text", showlegend=False))
    fig.update_layout(margin=dict(l=40, r=10, t=30, b=40), title=dict(text="Stations (top view) and registered pairs",
                      font=dict(size=12)), xaxis_title="x (m, reference frame)", yaxis_title="y (m)",
                      yaxis=dict(scaleanchor="x", scaleratio=1))
    return fig


def render_graph(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> Drawing:
    graph = snap.output("graph")
    rows = []
    for i, (s, pl) in enumerate(zip(snap.scans, graph.items)):
        via = ", ".join(str(v + 1) for v in pl.via)
        rows.append((f"{i + 1}: {s.name}", BADGE.get(pl.verdict, pl.verdict), via, "; ".join(pl.reasons)))
    n_ok = sum(pl.verdict == "verified" for pl in graph.items)
    text = (f"{n_ok} of {len(graph.items)} scans verified. Every scan is shown at its joint placement. Solid edges: "
            "verified pairs used in the joint solve; dotted: pairs left out (unverified, failed, or dropped because "
            "a loop did not close).") + _loosened_note(snap, "verified" if n_ok > 1 else "")
    plots = []
    fig = graph_figure(snap)
    if fig is not None and len(snap.scans) > 2:
        plots.append((fig, 1.3))
    table = md_table(("scan", "verdict", "placed through scans", "why not verified"), rows)
    edges = graph.items[0].edges if graph.items else ()
    if edges:
        table += "\n\n" + md_table(("pair", "verdict", "loop error (mm)", "used"), [
            (f"{snap.scans[e.j].name} → {snap.scans[e.i].name}", e.verdict,
             f"{e.loop_error_m * 1000:.2f}" if np.isfinite(e.loop_error_m) else "", "yes" if e.used else "no")
            for e in edges])
    return [], PanelContent(title("graph"), text=text, plots=tuple(plots), table=table)


HYPOTHESES_VIEW_FIELDS = ("target", "point_size", "max_points")
VERIFY_VIEW_FIELDS = ("target",)
GRAPH_VIEW_FIELDS: tuple[str, ...] = ()
