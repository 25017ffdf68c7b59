"""The Matching stage: MatchResult — similarity matrix, ORB matches of a chosen image pair, tie points.

The panel shows the similarity matrix of the reference's and the target's image sequences as a
heatmap with the chosen pairs marked (the current one highlighted), and the current pair's two
images side by side with their matches: kept in magenta, rejected by the β check in grey. In 3-D,
the tie points of each scan (each in its own frame, as the scans are shown on this stage) joined by
lines.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import plotly.graph_objects as go
import viser

from treereg_core.coarse.matching import MatchResult
from treereg_core.coarse.sequences import ImageSequence

from ..controller import Snapshot
from ..draw.common import Drawing, item_message, metrics_table, pair_label, plural, target_index, title
from ..draw.images import binary_to_rgb, display_xy, draw_lines, draw_markers, fit_factor, fit_width, hstack, upscale
from ..palette import HIGHLIGHT, KEPT, REJECTED, scan_color
from ..view_panel import PanelContent
from ..text import html, md
from ..view_state import ViewState
from .base import AppStage, ControlHost, StageControls, StageView, TargetControl, TourStep


def similarity_figure(match: Any, angles_ref: tuple[float, ...], angles_tgt: tuple[float, ...], current: int,
                      ref_name: str, tgt_name: str) -> go.Figure:
    """Heatmap of the similarity matrix (rows: reference images, columns: target images), chosen pairs marked."""
    sim = np.asarray(match.similarity, dtype=float)
    ref_name, tgt_name = html(ref_name), html(tgt_name)  # plotly renders HTML in its texts
    fig = go.Figure(go.Heatmap(
        z=sim, x=list(angles_tgt)[: sim.shape[1]], y=list(angles_ref)[: sim.shape[0]], colorscale="Viridis",
        colorbar=dict(title=match.measure, thickness=12),
        hovertemplate=f"{ref_name} θ=%{{y}}°<br>{tgt_name} θ=%{{x}}°<br>{match.measure}=%{{z:.3f}}<extra></extra>",
    ))
    pairs = match.pairs
    if pairs:
        fig.add_trace(go.Scatter(
            x=[p.angle_tgt_deg for p in pairs], y=[p.angle_ref_deg for p in pairs], mode="markers",
            marker=dict(symbol="circle-open", size=11, color="white", line=dict(width=2)),
            name="chosen pairs", text=[f"pair {k + 1}: {int(np.count_nonzero(p.kept))} kept matches" for k, p in enumerate(pairs)],
            hoverinfo="text",
        ))
        c = pairs[min(current, len(pairs) - 1)]
        fig.add_trace(go.Scatter(
            x=[c.angle_tgt_deg], y=[c.angle_ref_deg], mode="markers", name="shown below",
            marker=dict(symbol="square-open", size=15, color="rgb(250,200,0)", line=dict(width=3)), hoverinfo="skip",
        ))
    fig.update_layout(
        margin=dict(l=50, r=10, t=30, b=40), showlegend=False,
        title=dict(text=f"Similarity ({match.measure}) of the two sequences; circles: chosen pairs", font=dict(size=12)),
        xaxis_title=f"{tgt_name} rotation θ (deg)", yaxis_title=f"{ref_name} rotation θ (deg)",
    )
    return fig


def matches_image(pair: Any, img_ref: np.ndarray, img_tgt: np.ndarray, color_ref: tuple[int, int, int],
                  color_tgt: tuple[int, int, int]) -> np.ndarray:
    """The pair's two images side by side (reference left) with kept (magenta) and rejected (grey) matches."""
    k = fit_factor(img_ref.shape[1] + img_tgt.shape[1] + 16)
    a, b = upscale(binary_to_rgb(img_ref, color_ref), k), upscale(binary_to_rgb(img_tgt, color_tgt), k)
    lay = hstack([a, b], gap=16)
    canvas = lay.image
    p0 = display_xy(pair.xy_ref, img_ref.shape, k) + lay.offsets[0]
    p1 = display_xy(pair.xy_tgt, img_tgt.shape, k) + lay.offsets[1]
    kept = np.asarray(pair.kept, dtype=bool)
    colors = np.where(kept[:, None], np.array(KEPT, np.uint8), np.array(REJECTED, np.uint8))
    order = np.argsort(kept, kind="stable")  # rejected first, kept drawn on top
    draw_lines(canvas, p0[order], p1[order], colors[order], thickness=1)
    draw_markers(canvas, np.vstack([p0, p1]), np.vstack([colors, colors]), radius=1 + k // 2)
    return fit_width(canvas)


def render(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> Drawing:
    out = snap.output("matching")
    p = snap.pair(target_index(snap, "matching", view))
    t = p.index
    m, (seq_ref, seq_tgt) = p.item("matching", MatchResult), p.scan_items("projection", ImageSequence)
    # The drawer draws a pair that was not skipped: it was matched, so both scans were projected.
    assert m is not None and seq_ref is not None and seq_tgt is not None and out is not None, p.label
    ref_name, tgt_name = p.ref_scan.name, p.tgt_scan.name
    heading = title("matching", snap, t)
    texts = [item_message(m)] if not m.ok else []
    images, plots = [], []
    if getattr(m, "similarity", None) is not None and np.size(m.similarity):
        plots.append((similarity_figure(m, seq_ref.angles_deg, seq_tgt.angles_deg, view.match_pair, ref_name, tgt_name), 1.25))
    if m.pairs:
        k = min(view.match_pair, len(m.pairs) - 1)
        pair = m.pairs[k]
        img = matches_image(pair, seq_ref.images[pair.i], seq_tgt.images[pair.j], scan_color(p.ref), scan_color(p.tgt))
        n_kept = int(np.count_nonzero(pair.kept))
        if snap.params.matching.beta_check or n_kept < len(pair.kept):
            verdict = (f"{n_kept} of {plural(len(pair.kept), 'match', 'matches')} kept (magenta), "
                       f"{len(pair.kept) - n_kept} rejected by the β check (grey).")
        else:  # nothing is grey: say so, and where wrong matches are caught instead
            verdict = (f"{plural(n_kept, 'match', 'matches')}, all kept (magenta): the β check is off "
                       "(matching.beta_check); 4 Coarse rejects wrong ties by RANSAC instead.")
        images.append((img, (
            f"Image pair {k + 1} of {len(m.pairs)}: {md(ref_name)} at θ = {pair.angle_ref_deg:+.0f}° (left), "
            f"{md(tgt_name)} at θ = {pair.angle_tgt_deg:+.0f}° (right); {verdict}"
        )))
    texts.append(f"{plural(m.n_ties, 'tie point')} from {plural(len(m.pairs), 'image pair')}. In 3-D: the tie points "
                 "of the pair shown below, each in its own scan's frame, joined to its partner (the scans are not "
                 "registered yet).")
    handles: list[Any] = []
    if m.n_ties and m.pairs:
        # The tie points of the image pair shown in the panel (all pairs' ties would hide the trees).
        sel = np.asarray(m.tie_pair) == min(view.match_pair, len(m.pairs) - 1)
        ref_xyz, tgt_xyz = np.asarray(m.ref_xyz)[sel], np.asarray(m.tgt_xyz)[sel]
        if len(ref_xyz):
            segs = np.stack([ref_xyz, tgt_xyz], axis=1).astype(np.float32)
            handles.append(scene.add_line_segments(f"{root}/ties", segs, HIGHLIGHT, thickness=1.5,
                                                   thickness_units="screen"))
            handles.append(scene.add_point_cloud(f"{root}/ties_ref", ref_xyz, scan_color(p.ref), point_size=0.06,
                                                 point_shape="circle", precision="float32"))
            handles.append(scene.add_point_cloud(f"{root}/ties_tgt", tgt_xyz, scan_color(p.tgt), point_size=0.06,
                                                 point_shape="circle", precision="float32"))
    table = metrics_table({pair_label(snap, i): it.metrics for i, it in enumerate(out.items)})
    return handles, PanelContent(heading, text="\n\n".join(x for x in texts if x), images=tuple(images),
                                 plots=tuple(plots), table=table)


class MatchPairControl(StageControls):
    """"Image pair": which chosen image pair's ORB matches are shown (counted from 1)."""

    def __init__(self, gui: viser.GuiApi, host: ControlHost, stage: str) -> None:
        self.slider = gui.add_slider("Image pair", 1, 2, 1, 1, hint="Which chosen image pair's ORB matches to show.")
        self.slider.on_update(lambda _: host.set_view(match_pair=int(self.slider.value) - 1))

    def show_view(self, view: ViewState, snap: Snapshot) -> None:
        if view.match_pair + 1 <= self.slider.max:
            # viser's slider redeclares `value` with a getter only; the base class's setter applies.
            self.slider.value = view.match_pair + 1  # type: ignore[misc]

    def show_snapshot(self, snap: Snapshot, view: ViewState) -> None:
        match = snap.output("matching")
        if match is None or not match.items:
            return
        m = snap.pair(target_index(snap, "matching", view)).item("matching", MatchResult)
        n = len(m.pairs) if m is not None else 0
        if n > 1 and self.slider.max != n:
            self.slider.max = n
        self.slider.disabled = n <= 1


STAGE = AppStage(
    "matching",
    StageView(
        None,
        explanation="The most similar image pairs of two sequences (marked on the similarity matrix) are matched with "
            "ORB, fast and suited to images with little texture (2.1.3; the paper: 3 pairs, the 5 best matches "
            "of each). Each kept match gives a tie point: the centroid of the scan's points in that pixel's "
            "(α, β) cell, rotation undone (2.1.4). The paper's β check (4.1) drops a match whose elevation "
            "difference |β₁ − β₂| lies outside the mean ± one standard deviation of all matches: a crown point "
            "must match a crown point; its rejected matches are drawn in grey. treereg's default leaves the β check "
            "off (matching.beta_check) and lets RANSAC at the coarse stage reject wrong matches instead, so grey "
            "matches appear here only with the check on (e.g. the paper preset, Files tab).",
    ),
    draw=render,
    view_fields=("target", "match_pair"),
    controls=(TargetControl, MatchPairControl),
    tour=(
        TourStep(
            "matching", "Matching the most similar views",
            "The most similar image pairs of two sequences are matched with ORB, and each match becomes a 3-D tie point: "
            "the centroid of the points behind that pixel (2.1.3–2.1.4). Binary images carry little texture, so some "
            "matches are wrong (4.1).",
            "Move *Image pair* and compare the lines between the two images with the tie lines in 3-D.",
            view={"panel": "stage"}),
    ),
)
