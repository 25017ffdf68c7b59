"""Stage 3: coarse.CoarseResult — the target moved by its coarse transform, tie residuals.

The scan layer already shows every target at its coarse pose on this stage. Here: the chosen
target's tie pairs after the transform, inliers green and outliers grey, and a histogram of the
residuals with the inlier distance marked.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import plotly.graph_objects as go
import viser

from treereg_core.rigid import apply_transform

from ..controller import Snapshot
from ..palette import KEPT, REJECTED, hex_color
from ..view_panel import PanelContent
from ..view_state import ViewState
from .common import item_message, metrics_table, not_ready_text, pair_label


def residual_figure(c: Any, inlier_m: float) -> go.Figure:
    res = np.asarray(c.residuals_m, dtype=float)
    inl = np.asarray(c.inliers, dtype=bool)
    fig = go.Figure()
    fin = np.isfinite(res)
    top = float(np.nanpercentile(res[fin], 95)) * 1.2 if fin.any() else 1.0
    bins = dict(start=0.0, end=max(top, 2 * inlier_m), size=max(top, 2 * inlier_m) / 40)
    fig.add_trace(go.Histogram(x=res[fin & inl], name="inliers", marker_color=hex_color(KEPT), xbins=bins))
    fig.add_trace(go.Histogram(x=res[fin & ~inl], name="outliers", marker_color=hex_color(REJECTED), xbins=bins))
    fig.add_vline(x=inlier_m, line_dash="dash", annotation_text="inlier distance")
    fig.update_layout(barmode="stack", margin=dict(l=50, r=10, t=30, b=40),
                      title=dict(text="Tie-point residuals after the coarse transform", font=dict(size=12)),
                      xaxis_title="residual |T·p_target − p_ref| (m)", yaxis_title="tie points",
                      xaxis_range=[0, bins["end"]], legend=dict(x=0.7, y=0.95))
    return fig


def render_coarse(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> tuple[list[Any], PanelContent]:
    out = snap.output("coarse")
    if out is None or not out.items:
        return [], PanelContent("3 · Coarse", text=not_ready_text(snap, "coarse"))
    t = min(view.target, len(out.items) - 1)
    c = out.items[t]
    match = c.match if c.match is not None else (snap.output("matching").items[t] if snap.output("matching") else None)
    handles: list[Any] = []
    plots = []
    text = item_message(c) or (
        f"{pair_label(snap, t)}: {c.n_inliers} of {c.n_ties} tie points agree with the transform "
        f"(green lines in 3-D; outliers grey). Every target is shown at its coarse pose."
    )
    if c.ok and match is not None and match.n_ties and len(c.residuals_m) == match.n_ties:
        ref = np.asarray(match.ref_xyz)
        tgt = apply_transform(np.asarray(c.T_ref_target), np.asarray(match.tgt_xyz))
        inl = np.asarray(c.inliers, dtype=bool)
        segs = np.stack([ref, tgt], axis=1).astype(np.float32)
        colors = np.where(inl[:, None], np.array(KEPT, np.uint8), np.array(REJECTED, np.uint8))
        handles.append(scene.add_line_segments(
            f"{root}/ties", segs, np.repeat(colors[:, None, :], 2, axis=1), thickness=1.5, thickness_units="screen"))
        handles.append(scene.add_point_cloud(f"{root}/inlier_ties", ref[inl], KEPT, point_size=0.05,
                                             point_shape="circle", precision="float32"))
        plots.append((residual_figure(c, snap.params.coarse.inlier_m), 1.6))
    table = metrics_table({pair_label(snap, i): it.metrics for i, it in enumerate(out.items)})
    return handles, PanelContent(f"3 · Coarse: {pair_label(snap, t)}", text=text, plots=tuple(plots), table=table)
