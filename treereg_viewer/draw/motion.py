"""The crown's motion between two stations (wind), as the Fine and Result stages show it.

The stem profile (`treereg_core.fine.stem.StemProfile`, in the fine result) gives, height by
height, how far the target's stem stands from the reference's at the final pose: a vertical line
at zero where the stem holds, bending off above where the crown moved. The plot shows the measured
offsets, the fitted cantilever bend, the tolerance within which the stems count as agreeing and the
height up to which they do. All numbers come from the result; nothing is computed here but their
drawing.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import plotly.graph_objects as go

from ..palette import hex_color, scan_color
from ..text import html, md


def profile_figure(f: Any, ref_name: str, tgt_name: str, colour_index: int, tolerance_m: float) -> go.Figure | None:
    """Offset of the target's stem from the reference's (mm) against height above the stem's base (m)."""
    prof = getattr(f, "profile", None)
    if prof is None or not prof.n:
        return None
    ref_name, tgt_name = html(ref_name), html(tgt_name)  # plotly renders HTML in its title
    z = prof.heights_m - prof.base_z_m
    off = np.hypot(*prof.offsets_m.T) * 1000.0
    fig = go.Figure()
    fig.add_trace(go.Scatter(
        x=off, y=z, mode="markers", name="measured (one slab of both stems)",
        marker=dict(color=hex_color(scan_color(colour_index)), size=7),
        error_x=dict(type="data", array=3000.0 * prof.std_m, visible=True, thickness=1),
        hovertemplate="%{y:.2f} m: %{x:.1f} mm<extra></extra>"))
    top = max(float(z.max()), 0.1)
    if prof.model is not None:
        zz = np.linspace(0.0, prof.height_m, 120)
        mod = np.hypot(*prof.model.offsets(zz + prof.base_z_m, prof.base_z_m, prof.height_m).T) * 1000.0
        fig.add_trace(go.Scatter(x=mod, y=zz, mode="lines", name="fitted: shift, tilt and cantilever bend",
                                 line=dict(color="#555555", dash="dash")))
        top = prof.height_m
    tol = tolerance_m * 1000.0
    fig.add_trace(go.Scatter(x=[tol, tol], y=[0.0, top], mode="lines", name=f"agreement: within {tol:g} mm",
                             line=dict(color="#1e8c3c", width=1)))
    stable = prof.stable_height_m(tolerance_m)
    if np.isfinite(stable):
        fig.add_trace(go.Scatter(x=[0.0, max(float(off.max()), 2 * tol)], y=[stable, stable], mode="lines",
                                 name=f"the stems agree up to {stable:.1f} m", line=dict(color="#1e8c3c", dash="dot")))
    fig.update_layout(
        # The legend at the figure's foot (not under the axis by a share of the plot's height: in a
        # narrow panel its rows would cover the axis title).
        margin=dict(l=50, r=10, t=30, b=140),
        legend=dict(orientation="h", x=0.5, xanchor="center", yref="container", y=0.0, yanchor="bottom"),
        title=dict(text=f"{tgt_name}'s stem against {ref_name}'s, by height", font=dict(size=12)),
        xaxis_title="horizontal offset of the stem (mm)", yaxis_title="height above the stem's base (m)",
        xaxis=dict(rangemode="tozero"), yaxis=dict(rangemode="tozero"))
    return fig


def motion_sentence(f: Any, ref_name: str, tgt_name: str, tolerance_m: float) -> str:
    """What the wind did between the two stations, in words (or that the stems stand alike)."""
    prof = getattr(f, "profile", None)
    bend = getattr(f, "bend", None)
    stable = prof.stable_height_m(tolerance_m) if prof is not None and prof.n else float("nan")
    ref_name, tgt_name = md(ref_name), md(tgt_name)
    if bend is None:
        if prof is None or not prof.n:
            return ""
        return (f"The stems of {tgt_name} and {ref_name} stand alike at every height traced (within "
                f"{tolerance_m * 1000:g} mm up to {stable:.1f} m): no crown motion between the stations.")
    if prof is not None and not prof.crown:  # a bend fitted to a bare stem: no crown moved
        return (f"**The stem top stands {bend.sway_m:.2f} m off** {ref_name}'s (±{bend.sway_std_m * 100:.1f} cm; "
                f"towards {bend.sway_direction_deg:.0f}° in {ref_name}'s frame), fitted as a bend. The scans hold no "
                "crown: a bare stem cannot tell wind from a pose that is off.")
    return (f"**The crown moved {bend.sway_m:.2f} m** between the stations (the stem top, ±{bend.sway_std_m * 100:.1f} cm; "
            f"towards {bend.sway_direction_deg:.0f}° in {ref_name}'s frame): wind. The stems agree within "
            f"{tolerance_m * 1000:g} mm up to {stable:.1f} m above the base; above, the target's stem bends off as a "
            "cantilever. The pose rests on what did not move (the lower stem, the base, the ground); the bend was "
            "fitted with it as a nuisance, so the crown's motion is not taken for a tilt of the scanner.")
