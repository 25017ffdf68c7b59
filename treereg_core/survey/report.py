"""The survey report (HTML, `register --report`): the map of stations and stems with every registered
pair drawn as a link coloured by its verdict, then a row per station and a row per pair (the loop
closures: each pair's residual in the joint placement, and whether it was used).

The map is an inline SVG in the reference station's (levelled) frame, north-free: x right, y up. A
station is placed where its placement puts its scanner; a stem where the stations that see it put
it (merged within `_SAME_STEM_M`). Every name in it is escaped; nothing is fetched from elsewhere.
"""

from __future__ import annotations

import html

import numpy as np

from ..batch.report import STYLE
from ..geometry.rigid import apply_transform
from .register import Survey
from .summary import station_rows

#: Stems of two stations nearer than this (m) are drawn as one.
_SAME_STEM_M = 0.3
_SIZE_PX = 640
_MARGIN_PX = 30
#: Link colours by verdict (used in the placement, verified and dropped by a loop, unverified, failed).
_LINK = {"used": "#1a7f37", "dropped": "#8e44ad", "unverified": "#b35900", "failed": "#c62828"}
_EXTRA_STYLE = ".map{border:1px solid #ddd;background:#fcfcf8}.legend span{margin-right:14px}h2{margin-top:28px}"


def survey_report_html(survey: Survey, title: str = "treereg survey") -> str:
    """The whole report as one HTML document."""
    e = html.escape
    verdicts = [pl.verdict for pl in survey.placements]
    counts = ", ".join(f"{verdicts.count(v)} {v}" for v in ("verified", "unverified", "failed") if verdicts.count(v))
    head = (f"<h1>{e(title)}</h1><p>{len(survey.scans)} stations ({e(counts)}), {len(survey.pairs)} pairs registered "
            f"on the stems they share; times: {e(', '.join(f'{k} {v:.1f} s' for k, v in survey.seconds.items()))}</p>")
    legend = ('<p class="legend">' + "".join(
        f'<span style="color:{c}">&#9473; {e(t)}</span>' for t, c in (
            ("pair used in the placement", _LINK["used"]), ("verified, dropped by a loop", _LINK["dropped"]),
            ("unverified", _LINK["unverified"]), ("failed", _LINK["failed"]))) + "</p>")
    st_head = "".join(f"<th>{h}</th>" for h in ("station", "verdict", "pairs verified", "loop residual", "placed through", "stems"))
    st_rows = "".join("<tr>" + "".join(f'<td class="{e(r[1])}">{e(c)}</td>' if j == 1 else f"<td>{e(c)}</td>"
                                       for j, c in enumerate(r)) + "</tr>" for r in station_rows(survey))
    why = "".join(f"<li><b>{e(s.name)}</b>: {e('; '.join(pl.reasons))}</li>"
                  for s, pl in zip(survey.scans, survey.placements) if pl.reasons)
    return (f"<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>{e(title)}</title>"
            f"<style>{STYLE}{_EXTRA_STYLE}</style></head><body>{head}<h2>Map</h2>{legend}{_map_svg(survey)}"
            f"<h2>Stations</h2><table><tr>{st_head}</tr>{st_rows}</table>"
            + (f"<ul>{why}</ul>" if why else "")
            + f"<h2>Pairs and loop closures</h2>{_pairs_table(survey)}</body></html>\n")


def _edge_state(survey: Survey) -> dict[tuple[int, int], tuple[str, float]]:
    """Per pair: how it is drawn, and its residual in the joint placement (NaN when not in it)."""
    edges = survey.placed_edges()
    out = {}
    for p in survey.pairs:
        ed = edges.get((p.i, p.j))
        loop = ed.loop_error_m if ed is not None else float("nan")
        if p.verdict == "verified":
            out[(p.i, p.j)] = ("used" if ed is not None and ed.used else "dropped", loop)
        else:
            out[(p.i, p.j)] = (p.verdict, loop)
    return out


def _pairs_table(survey: Survey) -> str:
    e = html.escape
    state = _edge_state(survey)
    rows = []
    for p in survey.pairs:
        f = p.fit
        how, loop = state[(p.i, p.j)]
        cells = [" → ".join(survey.pair_names(p)), p.verdict, f"{f.stems_used} of {p.shared_stems}",
                 _mm(f.residual_m), _mm(f.pose_sd_m), _mm(loop), "yes" if how == "used" else "no", "; ".join(p.reasons)]
        rows.append("<tr>" + "".join(f'<td class="{e(p.verdict)}">{e(c)}</td>' if j == 1 else f"<td>{e(c)}</td>"
                                     for j, c in enumerate(cells)) + "</tr>")
    heads = ("pair", "verdict", "stems used", "stem residual", "pose uncertainty 20 m out", "loop residual", "used", "why not verified")
    return "<table><tr>" + "".join(f"<th>{h}</th>" for h in heads) + "</tr>" + "".join(rows) + "</table>"


def _mm(v: float) -> str:
    return f"{v * 1000:.2f} mm" if np.isfinite(v) else "–"


def _map_svg(survey: Survey) -> str:
    """Stations, stems and links in one SVG (see the module doc)."""
    e = html.escape
    placed = {k: pl.T_ref_scan for k, pl in enumerate(survey.placements) if pl.T_ref_scan is not None}
    stations = {k: T[:2, 3] for k, T in placed.items()}
    stems = _merged_stems(survey, placed)
    pts = np.array(list(stations.values()) + [s[:2] for s in stems]) if stations else np.zeros((1, 2))
    lo, hi = pts.min(axis=0) - 1.0, pts.max(axis=0) + 1.0
    scale = (_SIZE_PX - 2 * _MARGIN_PX) / max(float((hi - lo).max()), 1e-6)

    def xy(p: np.ndarray) -> tuple[float, float]:
        return _MARGIN_PX + (p[0] - lo[0]) * scale, _SIZE_PX - _MARGIN_PX - (p[1] - lo[1]) * scale

    parts = [f'<svg class="map" xmlns="http://www.w3.org/2000/svg" width="{_SIZE_PX}" height="{_SIZE_PX}" '
             f'viewBox="0 0 {_SIZE_PX} {_SIZE_PX}" role="img" aria-label="map of stations, stems and pairs">']
    for x, y, r, seen in stems:
        cx, cy = xy(np.array([x, y]))
        parts.append(f'<circle cx="{cx:.1f}" cy="{cy:.1f}" r="{max(r * scale, 2.0):.1f}" fill="#8d6e63" opacity="0.7">'
                     f"<title>stem, radius {r * 100:.0f} cm, seen by {seen} station{'s' if seen != 1 else ''}</title></circle>")
    state = _edge_state(survey)
    for p in survey.pairs:
        if p.i not in stations or p.j not in stations:
            continue
        how, loop = state[(p.i, p.j)]
        (x1, y1), (x2, y2) = xy(stations[p.i]), xy(stations[p.j])
        dash = "" if how == "used" else ' stroke-dasharray="6 4"'
        tip = (f"{' → '.join(survey.pair_names(p))}: {p.verdict}, {p.fit.stems_used} stems, "
               f"residual {_mm(p.fit.residual_m)}, loop {_mm(loop)}" + (f" ({'; '.join(p.reasons)})" if p.reasons else ""))
        parts.append(f'<line x1="{x1:.1f}" y1="{y1:.1f}" x2="{x2:.1f}" y2="{y2:.1f}" stroke="{_LINK[how]}" '
                     f'stroke-width="2.5"{dash}><title>{e(tip)}</title></line>')
    for k, at in stations.items():
        x, y = xy(at)
        pl = survey.placements[k]
        colour = {"verified": "#1a7f37", "unverified": "#b35900"}.get(pl.verdict, "#c62828")
        parts.append(f'<rect x="{x - 6:.1f}" y="{y - 6:.1f}" width="12" height="12" fill="{colour}">'
                     f"<title>{e(survey.scans[k].name)}: {e(pl.verdict)}</title></rect>"
                     f'<text x="{x + 9:.1f}" y="{y - 8:.1f}" font-size="12">{e(survey.scans[k].name)}</text>')
    parts.append("</svg>")
    return "".join(parts)


def _merged_stems(survey: Survey, placed: dict[int, np.ndarray]) -> list[tuple[float, float, float, int]]:
    """Every placed station's stems in the reference frame, those within `_SAME_STEM_M` merged:
    (x, y, radius, stations that see it)."""
    found: list[list[float]] = []
    for k, T in placed.items():
        st = survey.stations[k].stems
        if not len(st):
            continue
        xy = apply_transform(T, np.column_stack([st.xy, np.zeros(len(st))]))[:, :2]
        for (x, y), r in zip(xy, st.radius_m):
            near = next((f for f in found if np.hypot(f[0] - x, f[1] - y) < _SAME_STEM_M), None)
            if near is None:
                found.append([float(x), float(y), float(r), 1])
            else:
                near[3] += 1
    return [(f[0], f[1], f[2], int(f[3])) for f in found]
