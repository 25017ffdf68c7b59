"""The Coarse stage: CoarseResult — the target moved by its coarse transform, tie residuals.

The scan layer already shows every target at its coarse pose on this stage. Here: the chosen
target's tie pairs after the transform, inliers magenta and outliers grey, and a histogram of the
residuals with the inlier distance marked.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import plotly.graph_objects as go
import viser

from treereg_core.coarse.estimate import CoarseResult
from treereg_core.geometry.rigid import apply_transform

from ..controller import Snapshot
from ..draw.common import Drawing, item_message, metrics_table, pair_label, plural, target_index, title
from ..palette import KEPT, REJECTED, hex_color
from ..view_panel import PanelContent
from ..text import md
from ..view_state import ViewState
from .base import AppStage, StageView, TargetControl, TourStep


def residual_figure(c: CoarseResult) -> go.Figure:
    """Histogram of tie residuals, inliers magenta and outliers grey, around the inlier distance
    the inliers were chosen with (RANSAC's last, `c.inlier_m`).

    The x range is four times the inlier distance: the decision happens there. Farther residuals
    (wrong matches, often metres off) are gathered in the last bar, as the title says.
    """
    res = np.asarray(c.residuals_m, dtype=float)
    inl = np.asarray(c.inliers, dtype=bool)
    fin = np.isfinite(res)
    threshold_m = c.inlier_m
    end = 4.0 * threshold_m
    size = end / 40.0
    shown = np.minimum(res, end - size / 2)  # beyond the range: into the last bar
    n_far = int(np.count_nonzero(fin & (res >= end)))
    bins = dict(start=0.0, end=end, size=size)
    fig = go.Figure()
    fig.add_trace(go.Histogram(x=shown[fin & inl], name="inliers", marker_color=hex_color(KEPT), xbins=bins))
    fig.add_trace(go.Histogram(x=shown[fin & ~inl], name="outliers", marker_color=hex_color(REJECTED), xbins=bins))
    fig.add_vline(x=threshold_m, line_dash="dash", annotation_text=f"inlier distance {threshold_m:g} m")
    far = f"; the last bar holds {n_far} beyond {end:g} m" if n_far else ""
    # The legend at the figure's foot: in the plot's corner it lay over the inlier distance's words.
    fig.update_layout(barmode="stack", margin=dict(l=50, r=10, t=30, b=72),
                      title=dict(text=f"Tie-point residuals after the coarse transform{far}", font=dict(size=12)),
                      xaxis_title="residual |T·p_target − p_ref| (m)", yaxis_title="tie points",
                      xaxis_range=[0, end], legend=dict(orientation="h", x=0.5, xanchor="center", yref="container",
                                                        y=0.0, yanchor="bottom"))
    return fig


def render(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> Drawing:
    out = snap.output("coarse")
    t = target_index(snap, "coarse", view)
    c = snap.pair(t).item("coarse", CoarseResult)
    assert out is not None and c is not None, t  # the drawer draws a pair that was not skipped
    match = c.match
    handles: list[Any] = []
    plots = []
    text = item_message(c) or (
        f"{md(pair_label(snap, t))}: {c.n_inliers} of {c.n_ties} tie points agree with the transform "
        f"(magenta lines in 3-D; outliers grey). Every target is shown at its coarse pose."
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
        plots.append((residual_figure(c), 1.6))
        res = np.asarray(c.residuals_m, dtype=float)
        across = int(np.count_nonzero((res < c.inlier_m) != inl))
        if across:  # say why bars sit on the "wrong" side of the line, before a user has to ask
            text += (f" {plural(across, 'tie point')} {'lies' if across == 1 else 'lie'} on the other side of the inlier "
                     "distance in the histogram: RANSAC chose the inliers, then the transform was refitted on them, "
                     "which moved their residuals a little.")
    table = metrics_table({pair_label(snap, i): it.metrics for i, it in enumerate(out.items)})
    return handles, PanelContent(title("coarse", snap, t), text=text, plots=tuple(plots), table=table)


STAGE = AppStage(
    "coarse",
    StageView(
        "coarse",
        explanation="The rigid transform that best maps the target's tie points onto the reference's, by SVD over all "
            "of them in the paper (2.1.4). Wrong matches cannot be avoided on binary images (4.1), so treereg by "
            "default lets RANSAC keep the consistent ones (magenta lines; outliers grey), solving yaw and "
            "translation for levelled scanners. Projection loses detail, so trunks and branches are close but "
            "not yet aligned (paper Fig. 9). ⚠ marks a transform that cannot be right.",
    ),
    draw=render,
    view_fields=("target",),
    controls=(TargetControl,),
    tour=(
        TourStep(
            "coarse", "The coarse transform",
            "One rigid transform maps the target's tie points onto the reference's; treereg lets RANSAC keep the "
            "consistent ties (magenta) and drop the wrong ones (grey). The trees now overlap, but projection loses "
            "detail: stems are close, not yet aligned (paper Fig. 9).",
            "Zoom onto the trunk: each scan's skin of the stem lies a little apart from the others.",
            view={"panel": "stage"}),
    ),
)
