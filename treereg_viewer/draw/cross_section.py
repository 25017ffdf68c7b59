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

from typing import Any, Sequence, cast

import numpy as np
import plotly.graph_objects as go
import viser

from treereg_core.evaluate.branches import BranchError
from treereg_core.evaluate.cross_section import CrossSection, ScanCut

from ..controller import Snapshot
from ..palette import CATEGORICAL, GREY, hex_color, scan_color
from ..view_panel import PanelContent
from ..text import html, md, md_sentence
from ..view_state import ViewState
from .common import Handles, evaluated_branch_names, md_table, plural
from .fits import within

#: A plotly figure's layout, trace or axis as plain JSON-like data (see `_grid`).
Plain = dict[str, Any]

#: Registrations as people read them.
POSE_TITLES = {"coarse": "Coarse", "fine": "Fine", "icp": "ICP"}
#: Categorical colours (palette indices) for arcs other than a slab's largest: none of the scans' colours.
OTHER_ARCS = (1, 4, 5, 6, 7, 8, 9)
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
    return np.asarray((lo + hi) / 2.0)


def drawable(cs: CrossSection, box: tuple[np.ndarray, np.ndarray], sc: ScanCut, k: int) -> bool:
    """A fit is drawn only when it stays within the slab it came from (`box`: the slab's points of
    every scan, section-plane coordinates): a 3 km circle fitted to a straight arc would hide everything."""
    s = sc.sections[k]
    if not (np.isfinite(s.radius_m) and s.radius_m > 0 and np.any(sc.labels == k)):
        return False
    return within(cs.to_uv(s.centre_m)[0], s.radius_m, *box)


def _box(layer_scans: Sequence[ScanCut]) -> tuple[np.ndarray, np.ndarray]:
    uv = [sc.uv for sc in layer_scans if len(sc.uv)]
    if not uv:
        return np.zeros(2), np.zeros(2)
    allp = np.concatenate(uv)
    return allp.min(axis=0), allp.max(axis=0)


def _grid(rows: int, cols: int, titles: list[str], hgap: float = 0.08, vgap: float = 0.12) -> tuple[Plain, list[tuple[str, str]]]:
    """A plotly layout with a rows x cols grid of axes and a title over each cell; returns the layout
    and each cell's (x axis, y axis) names, row by row. Plain dicts: plotly's `make_subplots` and
    validated figures cost ten times more, and the inspector redraws as its slider moves."""
    layout: Plain = {"annotations": []}
    w = (1.0 - hgap * (cols - 1)) / cols
    h = (1.0 - vgap * (rows - 1)) / rows
    cells = []
    for r in range(rows):
        for c in range(cols):
            k = r * cols + c + 1
            x, y = ("x", "y") if k == 1 else (f"x{k}", f"y{k}")
            x0, y1 = c * (w + hgap), 1.0 - r * (h + vgap)
            layout["xaxis" if k == 1 else f"xaxis{k}"] = {"domain": [x0, x0 + w], "anchor": y}
            layout["yaxis" if k == 1 else f"yaxis{k}"] = {"domain": [y1 - h, y1], "anchor": x}
            cells.append((x, y))
            if titles:
                layout["annotations"].append({"text": titles[k - 1], "x": x0 + w / 2, "y": y1, "xref": "paper",
                                              "yref": "paper", "xanchor": "center", "yanchor": "bottom",
                                              "showarrow": False, "font": {"size": 12}})
    return layout, cells


def _axis(layout: Plain, name: str) -> Plain:
    axis = layout["xaxis" if name == "x" else f"xaxis{name[1:]}"] if name.startswith("x") else \
        layout["yaxis" if name == "y" else f"yaxis{name[1:]}"]
    assert isinstance(axis, dict)  # `_grid` made it
    return axis


def _figure(traces: list[Plain], layout: Plain) -> go.Figure:
    return go.Figure({"data": traces, "layout": layout}, _validate=False)


def top_view_figure(cs: CrossSection, snap: Snapshot, layers: list[int], show_rejected: bool) -> go.Figure:
    """Subplots: one column per registration, one row per layer; every scan in its colour."""
    poses = list(cs.poses)
    rows, cols = len(layers), len(poses)
    titles = [f"{POSE_TITLES.get(pc.pose, pc.pose)} · z = {cs.heights_m[lay]:.2f} m" for lay in layers for pc in poses]
    layout, cells = _grid(rows, cols, titles, hgap=0.1, vgap=0.14 / max(rows, 1) + 0.04)
    half = max(_extent(cs, lay) for lay in layers)
    cm = half < 0.6  # centimetres read better on a stem; metres across a crown
    unit, f = ("cm", 100.0) if cm else ("m", 1.0)
    traces: list[Plain] = []
    shown_names: set[str] = set()
    for r, lay in enumerate(layers):
        c0 = _centre(cs, lay)
        for c, pc in enumerate(poses):
            xa, ya = cells[r * cols + c]
            box = _box(pc.layers[lay].scans)
            for sc in pc.layers[lay].scans:
                color = hex_color(scan_color(sc.index))
                uv = (sc.uv - c0) * f
                first = sc.scan not in shown_names
                shown_names.add(sc.scan)
                traces.append(dict(type="scattergl", x=uv[:, 0], y=uv[:, 1], mode="markers", xaxis=xa, yaxis=ya,
                                   name=html(f"{sc.index + 1}: {sc.scan}"), legendgroup=sc.scan, showlegend=first,
                                   marker=dict(size=3, color=color), hovertemplate=f"{html(sc.scan)}<extra></extra>"))
                for k, s in enumerate(sc.sections):
                    if not drawable(cs, box, sc, k) or not (s.plausible or show_rejected):
                        continue
                    cu, cv = (cs.to_uv(s.centre_m)[0] - c0) * f
                    x, y = _circle(cu, cv, s.radius_m * f)
                    traces.append(dict(type="scatter", x=x, y=y, mode="lines", xaxis=xa, yaxis=ya, legendgroup=sc.scan,
                                       showlegend=False, hoverinfo="skip",
                                       line=dict(color=color if s.plausible else hex_color(GREY), width=2,
                                                 dash="solid" if s.plausible else "dot")))
                    if s.plausible:
                        traces.append(dict(type="scatter", x=[cu], y=[cv], mode="markers", xaxis=xa, yaxis=ya,
                                           legendgroup=sc.scan, showlegend=False,
                                           marker=dict(symbol="x-thin", size=11, color=color, line=dict(width=2, color=color)),
                                           hovertemplate=f"{html(sc.scan)}: centre, r = {s.radius_m * 100:.1f} cm<extra></extra>"))
            ax, ay = _axis(layout, xa), _axis(layout, ya)
            ax.update(range=[-half * f, half * f], zeroline=False, showgrid=True, gridcolor="#e8e8e8",
                      title=dict(text=f"x ({unit})") if r == rows - 1 else None)
            ay.update(range=[-half * f, half * f], zeroline=False, showgrid=True, gridcolor="#e8e8e8",
                      scaleanchor=xa, scaleratio=1, title=dict(text=f"y ({unit})") if c == 0 else None)
            if (xa, ya) != ("x", "y"):
                ax["matches"], ay["matches"] = "x", "y"
    # The legend at the figure's foot, under the axis titles (placed a share of the plot's height under
    # the axes, it lay over the x axis' title in a 310 px panel).
    layout.update(margin=dict(l=45, r=8, t=28, b=100), plot_bgcolor="white", font=dict(size=11),
                  legend=dict(orientation="h", x=0.5, xanchor="center", yref="container", y=0.0, yanchor="bottom",
                              font=dict(size=11)))
    return _figure(traces, layout)


def ring_figure(cs: CrossSection, layer: int) -> go.Figure | None:
    """Every scan's points unrolled along the reference's main circle, one column per registration:
    angle around its centre across, distance from the circle up (mm). A target off by a few
    millimetres, invisible in the top view, stands out here as a band away from zero."""
    profiles = [(pc, ring) for pc in cs.poses if (ring := cs.ring(pc.pose, layer)) is not None]
    if not profiles:
        return None
    layout, cells = _grid(1, len(profiles), [POSE_TITLES.get(pc.pose, pc.pose) for pc, _ in profiles], hgap=0.06)
    traces: list[Plain] = []
    top = 0.0
    for c, (pc, ring) in enumerate(profiles):
        xa, ya = cells[c]
        for sc in pc.layers[layer].scans:
            a, d = ring.angle_deg.get(sc.scan), ring.offset_m.get(sc.scan)
            if a is None or d is None or not len(a):
                continue
            top = max(top, float(np.percentile(np.abs(d), 98)))
            traces.append(dict(type="scattergl", x=a, y=d * 1000.0, mode="markers", xaxis=xa, yaxis=ya, showlegend=False,
                               marker=dict(size=3, color=hex_color(scan_color(sc.index))),
                               hovertemplate=f"{html(sc.scan)}: %{{y:.1f}} mm<extra></extra>"))
        _axis(layout, xa).update(range=[-180, 180], tickvals=[-180, -90, 0, 90, 180],
                                 title=dict(text="angle around scan 1's centre (°)") if c == (len(profiles) - 1) // 2 else None)
    lim = max(10.0, min(top * 1000.0 * 1.2, 100.0))
    for c in range(len(profiles)):
        ay = _axis(layout, cells[c][1])
        ay.update(range=[-lim, lim], zeroline=True, zerolinecolor="#999", showgrid=True, gridcolor="#e8e8e8",
                  showticklabels=c == 0, title=dict(text="off scan 1's circle (mm)") if c == 0 else None)
        if c:
            ay["matches"] = "y"
    layout.update(margin=dict(l=50, r=8, t=28, b=40), plot_bgcolor="white", font=dict(size=11), showlegend=False)
    return _figure(traces, layout)


def raster_figure(cs: CrossSection, pose: str, layer: int) -> go.Figure | None:
    """Each scan's slab in its own angular grid, one column per scan, coloured by arc (paper Fig. 6)."""
    pc = cs.pose(pose)
    if pc is None:
        return None
    cuts = [sc for sc in pc.layers[layer].scans if len(sc.cells)]
    if not cuts:
        return None
    layout, cells = _grid(1, len(cuts), [html(f"{sc.index + 1}: {sc.scan} · {plural(sc.n_arcs, 'arc')}") for sc in cuts],
                          hgap=0.05)
    traces: list[Plain] = []
    for c, sc in enumerate(cuts):
        xa, ya = cells[c]
        labels = np.asarray(sc.labels)
        # The largest arc (the stem, usually) in its scan's colour; the others in colours no scan has.
        others = CATEGORICAL[list(OTHER_ARCS)]
        colors = np.where(labels[:, None] > 0, others[np.mod(labels - 1, len(others))], np.array(GREY))
        colors[labels == 0] = scan_color(sc.index)
        traces.append(dict(type="scattergl", x=sc.cells[:, 0], y=sc.cells[:, 1], mode="markers", xaxis=xa, yaxis=ya,
                           showlegend=False,
                           marker=dict(symbol="square", size=5, color=[hex_color((int(r), int(g), int(b))) for r, g, b in colors]),
                           text=[f"arc {lab + 1}" if lab >= 0 else "too small for an arc" for lab in labels],
                           hovertemplate="%{text}<extra></extra>"))
        _axis(layout, xa).update(title=dict(text="α (steps)"), autorange="reversed")  # as seen from the scanner
        _axis(layout, ya).update(title=dict(text="β (steps)") if c == 0 else None, scaleanchor=xa, scaleratio=1)
    layout.update(margin=dict(l=45, r=8, t=28, b=40), plot_bgcolor="white", font=dict(size=11), showlegend=False)
    return _figure(traces, layout)


def _main(sc: ScanCut) -> int | None:
    good = [k for k, s in enumerate(sc.sections) if s.plausible]
    if not good:
        return None
    return max(good, key=lambda k: int(np.count_nonzero(sc.labels == k)))


def check_rows(cs: CrossSection, layer: int) -> list[tuple[str, ...]]:
    """Per registration and scan: arcs, the main (largest plausible) section, its 4.2 check and offset."""
    rows: list[tuple[str, ...]] = []
    for pc in cs.poses:
        offsets = pc.offsets_m[layer]
        below_layer = pc.layers[layer - 1] if layer > 0 else None
        for sc in pc.layers[layer].scans:
            k = _main(sc)
            if k is None:
                why = sc.sections[0].reason if sc.sections else "no arc"
                rows.append((POSE_TITLES.get(pc.pose, pc.pose), md(sc.scan), str(sc.n_arcs), "–", "–",
                             f"no plausible fit ({md(why)})", "–"))
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
            rows.append((POSE_TITLES.get(pc.pose, pc.pose), md(sc.scan), str(sc.n_arcs), f"{s.radius_m * 100:.1f}",
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
        listed = ", ".join(f"{v * 1000:.1f} mm ({md(k)})" for k, v in off.items())
        parts.append(f"**{name}: {shape}** — the targets' centres lie {listed} from scan 1's.")
    return " ".join(parts)


def render(snap: Snapshot, view: ViewState, cs: CrossSection | None, branch: BranchError | None = None) -> PanelContent:
    """The inspector's panel content for `cs` (None: nothing to cut yet)."""
    if cs is None:
        text = ("*The cross-section needs a registration: run the pipeline up to 4 Coarse at least.*"
                if snap.output("coarse") is None else "*No such branch for this pair: pick the stem or another branch.*")
        return PanelContent("Cross-section", text=text)
    if not cs.ok:
        return PanelContent("Cross-section", text=md_sentence(cs.message))
    if branch is None:
        layers = [1]  # layer 0 is the part below, for the 4.2 check
        head = f"Cross-section at z = {cs.heights_m[1]:.2f} m"
        where = f"A {cs.thickness_m * 100:.0f} cm slab of every scan, seen from above."
    else:
        layers = list(range(len(cs.heights_m)))
        name = evaluated_branch_names(snap, view.target).get(branch.index, f"branch {branch.index + 1}")
        head = f"{name[:1].upper()}{name[1:]}: its {plural(len(layers), 'evaluation layer')}"
        where = (f"Its layers (paper Fig. 12b), each seen along its axis: the points within "
                 f"{branch.radius_m * 100:.0f} cm plus the margin of the axis.")
    mid = layers[-1] if branch is None else len(layers) // 2
    text = where + " " + verdict(cs, mid)
    plots: list[tuple[go.Figure, float]] = [(top_view_figure(cs, snap, layers, view.show_rejected), len(cs.poses) / max(len(layers), 1) * 0.85)]
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
             "coloured by arc (the largest in its scan's colour, grey: too small for an arc): cells within c steps "
             "form one arc (paper Fig. 6).")
    if branch is None:
        notes += (f" The table checks each scan's main section against the part "
                  f"{abs(cs.heights_m[1] - cs.heights_m[0]) * 100:.0f} cm below (paper 4.2: no wider than it).")
    # One table per registration, named above it: a column of the registration's name made the table
    # wider than a 310 px panel (1280 x 720).
    rows = check_rows(cs, mid)
    tables = []
    for pose in dict.fromkeys(r[0] for r in rows):
        tables.append(f"**{pose}**\n\n" + md_table(("scan", "arcs", "radius (cm)", "RMS (mm)", "4.2 check", "offset (mm)"),
                                                     [r[1:] for r in rows if r[0] == pose]))
    return PanelContent(head, text=text, plots=tuple(plots), table=notes + "\n\n" + "\n\n".join(tables))


def draw_marker(scene: viser.SceneApi, root: str, cs: CrossSection | None, branch: BranchError | None = None) -> Handles:
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
    # trimesh's stubs type concatenate's result as any Geometry; of Trimeshes it is a Trimesh.
    mesh = cast(trimesh.Trimesh, trimesh.util.concatenate(meshes))
    return [scene.add_mesh_simple(f"{root}/cut", mesh.vertices.astype(np.float32), mesh.faces.astype(np.int32),
                                  color=HIGHLIGHT, opacity=0.6, side="double")]
