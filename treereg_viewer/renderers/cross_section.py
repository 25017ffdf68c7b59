"""The cross-section inspector's drawing: a `CrossSection` (treereg_core.evaluate.cross_section) as
2-D figures for the docked panel.

- Top view (or, for a branch, the view along its axis): every scan's slab points in its colour,
  side by side for the registrations shown (coarse, fine, ICP); each arc's fitted circle in the
  scan's colour and its centre as a cross. Registered well, the scans' arcs close into one ring;
  poorly, they stay separate arcs (paper Figs. 11c/d, 12b, 19).
- Each scan's slab in its own angular grid, one cell per angular step, coloured by arc: how the
  arcs were separated (paper Fig. 6).
- A table per registration and scan: arcs, the main section's radius and fit, the paper's 4.2
  check against the part below, and how far its centre lies from the reference's.

Only drawing: every number comes from the CrossSection.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import plotly.graph_objects as go
from plotly.subplots import make_subplots

from treereg_core.evaluate.cross_section import CrossSection, ScanCut

from ..controller import Snapshot
from ..palette import CATEGORICAL, GREY, hex_color, scan_color
from ..view_panel import PanelContent
from ..view_state import ViewState
from .common import md_table, plural
from .fine import SPAN_FACTOR, SPAN_SLACK_M

#: Registrations as people read them.
POSE_TITLES = {"coarse": "Coarse", "fine": "Fine", "icp": "ICP"}
#: Target centres within this distance of the reference's: the sections make one ring.
RING_M = 0.005


def _circle(cx: float, cy: float, r: float, n: int = 73) -> tuple[np.ndarray, np.ndarray]:
    t = np.linspace(0.0, 2.0 * np.pi, n)
    return cx + r * np.cos(t), cy + r * np.sin(t)


def _extent(cs: CrossSection, layer: int) -> float:
    """Half the side of the square the top view shows (m): the slab's points, with some room."""
    uv = [sc.uv for pc in cs.poses for sc in pc.layers[layer].scans if len(sc.uv)]
    if not uv:
        return 0.5
    allp = np.concatenate(uv)
    lo, hi = np.percentile(allp, 0.5, axis=0), np.percentile(allp, 99.5, axis=0)
    return float(max(hi - lo) / 2.0 * 1.15 + 0.01)


def _centre(cs: CrossSection, layer: int) -> np.ndarray:
    uv = [sc.uv for pc in cs.poses for sc in pc.layers[layer].scans if len(sc.uv)]
    if not uv:
        return np.zeros(2)
    allp = np.concatenate(uv)
    lo, hi = np.percentile(allp, 0.5, axis=0), np.percentile(allp, 99.5, axis=0)
    return (lo + hi) / 2.0


def drawable(sc: ScanCut, k: int) -> bool:
    """A fit is drawn only when it is no larger than the slab it came from (a 3 km circle fitted to
    a straight arc would hide everything)."""
    s = sc.sections[k]
    if not (np.isfinite(s.radius_m) and s.radius_m > 0):
        return False
    span = float(np.ptp(sc.uv, axis=0).max()) if len(sc.uv) else 0.0
    return bool(np.any(sc.labels == k)) and 2.0 * s.radius_m <= SPAN_FACTOR * span + SPAN_SLACK_M


def top_view_figure(cs: CrossSection, snap: Snapshot, layers: list[int], show_rejected: bool) -> go.Figure:
    """Subplots: one column per registration, one row per layer; every scan in its colour."""
    poses = [pc for pc in cs.poses]
    rows, cols = len(layers), len(poses)
    titles = [f"{POSE_TITLES.get(pc.pose, pc.pose)} · z = {cs.heights_m[lay]:.2f} m" for lay in layers for pc in poses]
    fig = make_subplots(rows=rows, cols=cols, subplot_titles=titles, horizontal_spacing=0.08,
                        vertical_spacing=0.12 / max(rows, 1) + 0.04)
    half = max(_extent(cs, lay) for lay in layers)
    cm = half < 0.6  # centimetres read better on a stem; metres across a crown
    unit, f = ("cm", 100.0) if cm else ("m", 1.0)
    shown_names: set[str] = set()
    for r, lay in enumerate(layers, start=1):
        c0 = _centre(cs, lay)
        for c, pc in enumerate(poses, start=1):
            for sc in pc.layers[lay].scans:
                color = hex_color(scan_color(sc.index))
                uv = (sc.uv - c0) * f
                first = sc.scan not in shown_names
                shown_names.add(sc.scan)
                fig.add_trace(go.Scattergl(
                    x=uv[:, 0], y=uv[:, 1], mode="markers", name=f"{sc.index + 1}: {sc.scan}", legendgroup=sc.scan,
                    showlegend=first, marker=dict(size=3, color=color),
                    hovertemplate=f"{sc.scan}<extra></extra>"), row=r, col=c)
                for k, s in enumerate(sc.sections):
                    if not drawable(sc, k) or not (s.plausible or show_rejected):
                        continue
                    cu, cv = (cs.to_uv(s.centre_m)[0] - c0) * f
                    x, y = _circle(cu, cv, s.radius_m * f)
                    fig.add_trace(go.Scatter(
                        x=x, y=y, mode="lines", legendgroup=sc.scan, showlegend=False, hoverinfo="skip",
                        line=dict(color=color if s.plausible else hex_color(GREY), width=2,
                                  dash="solid" if s.plausible else "dot")), row=r, col=c)
                    if s.plausible:
                        fig.add_trace(go.Scatter(
                            x=[cu], y=[cv], mode="markers", legendgroup=sc.scan, showlegend=False,
                            marker=dict(symbol="x-thin", size=11, color=color, line=dict(width=2, color=color)),
                            hovertemplate=f"{sc.scan}: centre, r = {s.radius_m * 100:.1f} cm<extra></extra>"),
                            row=r, col=c)
            ax = (r - 1) * cols + c
            fig.update_xaxes(range=[-half * f, half * f], row=r, col=c, title_text=f"x ({unit})" if r == rows else None,
                             matches="x" if ax > 1 else None, zeroline=False)
            fig.update_yaxes(range=[-half * f, half * f], row=r, col=c, scaleanchor=f"x{'' if ax == 1 else ax}",
                             scaleratio=1, title_text=f"y ({unit})" if c == 1 else None, zeroline=False,
                             matches="y" if ax > 1 else None)
    fig.update_layout(margin=dict(l=45, r=8, t=28, b=62), legend=dict(orientation="h", y=-0.1 if rows == 1 else -0.04,
                      yanchor="top", x=0.5, xanchor="center", font=dict(size=11)), plot_bgcolor="white",
                      font=dict(size=11))
    fig.update_annotations(font_size=12)
    fig.update_xaxes(showgrid=True, gridcolor="#e8e8e8")
    fig.update_yaxes(showgrid=True, gridcolor="#e8e8e8")
    return fig


def ring_figure(cs: CrossSection, layer: int) -> go.Figure | None:
    """Every scan's points unrolled along the reference's main circle, one column per registration:
    angle around its centre across, distance from the circle up (mm). A target off by a few
    millimetres, invisible in the top view, stands out here as a band away from zero."""
    profiles = [(pc.pose, cs.ring(pc.pose, layer)) for pc in cs.poses]
    profiles = [(pose, r) for pose, r in profiles if r is not None]
    if not profiles:
        return None
    fig = make_subplots(rows=1, cols=len(profiles), shared_yaxes=True, horizontal_spacing=0.06,
                        subplot_titles=[POSE_TITLES.get(pose, pose) for pose, _ in profiles])
    top = 0.0
    for c, (pose, ring) in enumerate(profiles, start=1):
        pc = cs.pose(pose)
        for sc in pc.layers[layer].scans:
            a, d = ring.angle_deg.get(sc.scan), ring.offset_m.get(sc.scan)
            if a is None or not len(a):
                continue
            top = max(top, float(np.percentile(np.abs(d), 98)))
            fig.add_trace(go.Scattergl(x=a, y=d * 1000.0, mode="markers", showlegend=False,
                                       marker=dict(size=3, color=hex_color(scan_color(sc.index))),
                                       hovertemplate=f"{sc.scan}: %{{y:.1f}} mm<extra></extra>"), row=1, col=c)
        fig.update_xaxes(range=[-180, 180], tickvals=[-180, -90, 0, 90, 180], row=1, col=c,
                         title_text="angle around scan 1's centre (°)" if c == (len(profiles) + 1) // 2 else None)
    lim = max(10.0, min(top * 1000.0 * 1.2, 100.0))
    fig.update_yaxes(range=[-lim, lim], title_text="off scan 1's circle (mm)", row=1, col=1, zeroline=True,
                     zerolinecolor="#999")
    fig.update_layout(margin=dict(l=50, r=8, t=28, b=40), plot_bgcolor="white", font=dict(size=11))
    fig.update_annotations(font_size=12)
    fig.update_yaxes(showgrid=True, gridcolor="#e8e8e8")
    return fig


def raster_figure(cs: CrossSection, pose: str, layer: int) -> go.Figure | None:
    """Each scan's slab in its own angular grid, one column per scan, coloured by arc (paper Fig. 6)."""
    pc = cs.pose(pose)
    if pc is None:
        return None
    cuts = [sc for sc in pc.layers[layer].scans if len(sc.cells)]
    if not cuts:
        return None
    fig = make_subplots(rows=1, cols=len(cuts), horizontal_spacing=0.05,
                        subplot_titles=[f"{sc.index + 1}: {sc.scan} · {plural(sc.n_arcs, 'arc')}" for sc in cuts])
    for c, sc in enumerate(cuts, start=1):
        labels = np.asarray(sc.labels)
        colors = np.where(labels[:, None] >= 0, CATEGORICAL[np.mod(labels, len(CATEGORICAL))], np.array(GREY))
        fig.add_trace(go.Scattergl(
            x=sc.cells[:, 0], y=sc.cells[:, 1], mode="markers", showlegend=False,
            marker=dict(symbol="square", size=5, color=[hex_color(tuple(int(v) for v in row)) for row in colors]),
            text=[f"arc {lab + 1}" if lab >= 0 else "too small for an arc" for lab in labels],
            hovertemplate="%{text}<extra></extra>"), row=1, col=c)
        fig.update_xaxes(title_text="α (steps)", row=1, col=c, autorange="reversed")  # as seen from the scanner
        fig.update_yaxes(title_text="β (steps)" if c == 1 else None, row=1, col=c,
                         scaleanchor=f"x{'' if c == 1 else c}", scaleratio=1)
    fig.update_layout(margin=dict(l=45, r=8, t=28, b=40), plot_bgcolor="white", font=dict(size=11))
    fig.update_annotations(font_size=12)
    return fig


def _main(sc: ScanCut) -> int | None:
    good = [k for k, s in enumerate(sc.sections) if s.plausible]
    if not good:
        return None
    return max(good, key=lambda k: int(np.count_nonzero(sc.labels == k)))


def check_rows(cs: CrossSection, layer: int) -> list[tuple[str, ...]]:
    """Per registration and scan: arcs, the main (largest plausible) section, its 4.2 check and offset."""
    rows = []
    for pc in cs.poses:
        offsets = pc.offsets_m[layer]
        below_layer = pc.layers[layer - 1] if layer > 0 else None
        for sc in pc.layers[layer].scans:
            k = _main(sc)
            if k is None:
                why = sc.sections[0].reason if sc.sections else "no arc"
                rows.append((POSE_TITLES.get(pc.pose, pc.pose), sc.scan, str(sc.n_arcs), "–", "–", f"no plausible fit ({why})", "–"))
                continue
            s = sc.sections[k]
            check = "no part below found"
            if below_layer is not None:
                below = next((b for b in below_layer.scans if b.index == sc.index), None)
                j = sc.below[k]
                if below is not None and j >= 0:
                    rb = below.sections[j].radius_m
                    check = (f"kept: ≤ {rb * 100:.1f} cm below" if s.plausible else f"**dropped**: > {rb * 100:.1f} cm below")
            off = offsets.get(sc.scan)
            rows.append((POSE_TITLES.get(pc.pose, pc.pose), sc.scan, str(sc.n_arcs), f"{s.radius_m * 100:.1f}",
                         f"{s.fit.rms_m * 1000:.1f}", check,
                         "reference" if sc.index == 0 else ("–" if off is None else f"{off * 1000:.1f}")))
        # The 4.2 verdicts of sections that were dropped (not the main one, which is plausible by choice).
    return rows


def verdict(cs: CrossSection, layer: int) -> str:
    """One sentence per registration: how far the targets' sections lie from the reference's."""
    parts = []
    for pc in cs.poses:
        off = pc.offsets_m[layer]
        name = POSE_TITLES.get(pc.pose, pc.pose)
        if not off:
            parts.append(f"{name}: no target section pairs with the reference's here.")
            continue
        worst = max(off.values())
        shape = "one ring" if worst <= RING_M else "separate arcs"
        listed = ", ".join(f"{v * 1000:.1f} mm ({k})" for k, v in off.items())
        parts.append(f"**{name}: {shape}** — the targets' centres lie {listed} from scan 1's.")
    return " ".join(parts)


def render(snap: Snapshot, view: ViewState, cs: CrossSection | None, branch: Any = None) -> PanelContent:
    """The inspector's panel content for `cs` (None: nothing to cut yet)."""
    if cs is None:
        text = ("*The cross-section needs a registration: run the pipeline up to 4 Coarse at least.*"
                if snap.output("coarse") is None else "*No such branch for this pair: pick the stem or another branch.*")
        return PanelContent("Cross-section", text=text)
    if not cs.ok:
        return PanelContent("Cross-section", text=f"{cs.message[0].upper()}{cs.message[1:]}.")
    if branch is None:
        layers = [1]  # layer 0 is the part below, for the 4.2 check
        head = f"Cross-section at z = {cs.heights_m[1]:.2f} m"
        where = f"A {cs.thickness_m * 100:.0f} cm slab of every scan, seen from above."
    else:
        layers = list(range(len(cs.heights_m)))
        head = f"Branch {branch.index + 1}: its {plural(len(layers), 'evaluation layer')}"
        where = (f"The branch's layers (paper Fig. 12b), each seen along its axis: the points within "
                 f"{branch.radius_m * 100:.0f} cm plus the margin of the axis.")
    mid = layers[-1] if branch is None else len(layers) // 2
    text = where + " " + verdict(cs, mid)
    plots = [(top_view_figure(cs, snap, layers, view.show_rejected), len(cs.poses) / max(len(layers), 1) * 0.85)]
    ring = ring_figure(cs, mid)
    if ring is not None:
        plots.append((ring, 2.6))
    last = cs.poses[-1].pose
    raster = raster_figure(cs, last, mid)
    if raster is not None:
        plots.append((raster, 2.4))
    notes = ("**Reading the plots.** Top: each arc's fitted circle in its scan's colour, its centre a cross. "
             "Middle: the same points unrolled along scan 1's circle, their distance from it against the angle "
             "around its centre: a few millimetres show here. Bottom: each scan's slab at the "
             f"{POSE_TITLES.get(last, last).lower()} pose in its own angular grid (one cell per angular step), "
             "coloured by arc: cells within c steps form one arc (paper Fig. 6).")
    if branch is None:
        notes += (f" The table checks each scan's main section against the part "
                  f"{abs(cs.heights_m[1] - cs.heights_m[0]) * 100:.0f} cm below (paper 4.2: no wider than it).")
    table = md_table(("registration", "scan", "arcs", "radius (cm)", "RMS (mm)", "4.2 check", "offset (mm)"),
                     check_rows(cs, mid))
    return PanelContent(head, text=text, plots=tuple(plots), table=notes + "\n\n" + table)


def draw_marker(scene: Any, root: str, cs: CrossSection | None, branch: Any = None) -> list[Any]:
    """Where the cut lies in 3-D: a yellow band around each shown layer (its slab's thickness, a
    little wider than the section), visible from the side as from above."""
    import trimesh

    from ..palette import HIGHLIGHT

    if cs is None or not cs.ok:
        return []
    layers = [1] if branch is None else list(range(len(cs.heights_m)))
    meshes = []
    for lay in layers:
        h = cs.heights_m[lay]
        at = cs.origin + cs.axis * (h - cs.origin[2]) / cs.axis[2] if abs(cs.axis[2]) > 1e-6 else cs.origin
        ring = cs.ring(cs.poses[0].pose, lay) if cs.poses else None
        if ring is not None and branch is None:
            centre, r = ring.centre_m, ring.radius_m * 1.25 + 0.02
        else:
            c0 = _centre(cs, lay)
            centre, r = at + c0[0] * cs.e1 + c0[1] * cs.e2, _extent(cs, lay)
        half = cs.thickness_m / 2.0
        meshes.append(trimesh.creation.annulus(r_min=r, r_max=r + max(0.01, 0.05 * r), height=2 * half,
                                               segment=np.stack([centre - cs.axis * half, centre + cs.axis * half]),
                                               sections=48))
    mesh = trimesh.util.concatenate(meshes)
    return [scene.add_mesh_simple(f"{root}/cut", mesh.vertices.astype(np.float32), mesh.faces.astype(np.int32),
                                  color=HIGHLIGHT, opacity=0.6, side="double")]
