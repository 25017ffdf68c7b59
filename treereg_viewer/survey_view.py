"""The app's survey view (issue 31): a whole-plot survey's station map, its pairs and its stems.

`treereg view` on a survey (more than 8 stations, or `--survey`) gives every tab a `SurveyViewer`
instead of the stage-by-stage `Viewer`. The registration runs on the controller's worker
(`Controller(..., survey=True)` runs `treereg_core.survey.register_survey` there and publishes it in
`Snapshot.survey`); this tab's `Drawer` thread draws it (`SurveyDrawer.draw`), so the tab stays
responsive while the survey registers. Everything drawn is computed by `treereg_core.survey.inspect`:

* the map: every station's voxel-thinned cloud placed and decimated to the tab's point budget,
  coloured by station; each scanner marked and labelled with its verdict's mark and name; each pair a
  link coloured as the report colours it (used by the placement, verified but dropped by a loop,
  unverified, failed); each plot stem a ring at breast height;
* the docked panel: the stations' table (`survey.summary.station_rows`) and the pairs; a pair chosen
  (the *Pair* list, or a click on its link) shows its verdict, its checks beside their thresholds and
  its numbers, and draws its shared stems' sections from both stations; a stem chosen (the *Stem*
  list, or a click on its ring) shows its sections from every station that sees it, in 3-D and as a
  top view at breast height (plotly).

Every name goes into markdown through `text.md`, into plotly through `text.html`; 3-D labels are text.
"""

from __future__ import annotations

import logging
import threading
import time
from contextlib import AbstractContextManager
from dataclasses import dataclass, replace
from typing import Any, Callable

import numpy as np
import viser

from treereg_core.survey.inspect import (BREAST_HEIGHT_M, DEFAULT_MAP_POINTS, PairInspection, StemInspection,
                                         SurveyMap, inspect_pair, inspect_stem, survey_map)
from treereg_core.survey.register import Survey
from treereg_core.survey.summary import station_rows

from .controller import Controller, Snapshot
from .drawer import Drawer
from .labels import VERDICT_MARKS, verdict_badge
from .palette import GREY, HIGHLIGHT, LINK_COLORS, hex_color, station_color
from .text import html, md
from .view_panel import PanelContent, ViewPanel
from .viewer import narrow_window, pick_clicked

log = logging.getLogger(__name__)

#: The control panel's width and the docked panel's, in a wide window and a narrow one (as `viewer`).
CONTROL_WIDTH_PX = 380
PANEL_WIDTH_PX = 600
NARROW_CONTROL_PX = 300
NARROW_PANEL_PX = 380
#: The map's point budgets a person can choose (all stations together).
POINT_BUDGETS = {"100,000 points": 100_000, "300,000 points": DEFAULT_MAP_POINTS, "1,000,000 points": 1_000_000}
NONE = "(none)"
#: What a link's colour says, in the legend.
LINK_MEANING = {"used": "used by the placement", "dropped": "verified, dropped by a loop",
                "unverified": "unverified", "failed": "failed"}


@dataclass(frozen=True)
class SurveyViewState:
    """What one tab looks at: the pair or stem inspected (indices into the survey's pairs and
    `SurveyMap.stems`; at most one of them), the point budget and the points' size (m)."""

    pair: int | None = None
    stem: int | None = None
    max_points: int = DEFAULT_MAP_POINTS
    point_size: float = 0.05


def mark(verdict: str) -> str:
    return "◆" if verdict == "reference" else VERDICT_MARKS.get(verdict, "?")


def pair_label(survey: Survey, k: int) -> str:
    p = survey.pairs[k]
    return f"{k + 1}. {' → '.join(survey.pair_names(p))}  {mark(p.verdict)}"


def stem_label(m: SurveyMap, k: int) -> str:
    s = m.stems[k]
    n = len(s.views)
    return f"Stem {k + 1}: {n} station{'s' if n != 1 else ''}, r {s.radius_m * 100:.0f} cm"


class SurveyDrawer(Drawer):
    """A survey tab's drawing thread: the `Drawer`'s loop, coalescing and panel handling, drawing the
    survey's map and the pair or stem inspected (`draw`)."""

    def __init__(self, scene: viser.SceneApi, atomic: Callable[[], AbstractContextManager[Any]], panel: ViewPanel,
                 get_snapshot: Callable[[], Snapshot], get_view: Callable[[], Any], derived: Any,
                 on_error: Callable[[str], None], give_way: Callable[[float], None] | None,
                 on_map: Callable[[Survey, SurveyMap], None]) -> None:
        self._maps: dict[tuple[int, int], SurveyMap] = {}
        self._maps_lock = threading.Lock()  # a click (viser's threads) asks for the map too
        self._on_map = on_map
        super().__init__(scene, atomic, panel, get_snapshot, get_view, derived, on_error=on_error, give_way=give_way)

    def survey_map(self, survey: Survey, max_points: int) -> SurveyMap:
        key = (id(survey), max_points)
        with self._maps_lock:
            if key not in self._maps:
                self._maps = {key: survey_map(survey, max_points)}  # the latest survey's only
            return self._maps[key]

    def draw(self, latest: Snapshot, view: Any) -> None:  # the one-tree Drawer's `draw`, for a survey
        survey = latest.survey
        m = self.survey_map(survey, view.max_points) if survey is not None else None
        pair = inspect_pair(survey, view.pair, latest.params.survey) \
            if survey is not None and view.pair is not None and view.pair < len(survey.pairs) else None
        stem = inspect_stem(survey, m.stems[view.stem]) \
            if survey is not None and m is not None and view.stem is not None and view.stem < len(m.stems) else None
        with self._atomic():
            key = (id(m), view.point_size)
            if self._keys.get("map") != key:
                self._replace("map", draw_map(self.scene, m, view.point_size) if m is not None else [])
                self._keys["map"] = key
            inspected = (id(m), view.pair, view.stem)
            if self._keys.get("inspect") != inspected:
                handles = (draw_pair(self.scene, m, pair) if pair is not None and m is not None else
                           draw_stem(self.scene, stem, m) if stem is not None and m is not None else [])
                self._replace("inspect", handles)
                self._keys["inspect"] = inspected
            # Inspecting, the sections are what to see: the stations' points (5 cm dots) would hide them.
            for hd in self._handles.get("map", []):
                if getattr(hd, "name", "") == "/survey/map/points":
                    hd.visible = view.pair is None and view.stem is None
            panel_key = (id(m), view.pair, view.stem, latest.busy, latest.message)
            if self._keys.get("panel") != panel_key:
                content = (pair_content(survey, pair) if pair is not None and survey is not None else
                           stem_content(stem, m) if stem is not None and m is not None else
                           overview_content(latest, m))
                self._plots_pending = bool(content.plots) and not self.panel.plots
                if self._plots_pending:
                    self._asked_at = max(self._asked_at, time.monotonic())
                self.panel.show(replace(content, plots=()) if self._plots_pending else content)
                self._keys["panel"] = panel_key
        if survey is not None and m is not None:
            self._on_map(survey, m)


# ---- the scene ----------------------------------------------------------------------------------------
def _colors(station_of: np.ndarray) -> np.ndarray:
    ks = np.unique(station_of)
    lut = np.zeros((int(ks.max()) + 1 if len(ks) else 1, 3), np.uint8)
    for k in ks:
        lut[k] = station_color(int(k))
    return np.asarray(lut[station_of], dtype=np.uint8)


def _ring(centre: np.ndarray, radius: float, n: int = 32) -> np.ndarray:
    """A horizontal circle as n line segments (n x 2 x 3)."""
    a = np.linspace(0, 2 * np.pi, n + 1)
    p = np.column_stack([centre[0] + radius * np.cos(a), centre[1] + radius * np.sin(a), np.full(n + 1, centre[2])])
    return np.stack([p[:-1], p[1:]], axis=1)


def draw_map(scene: viser.SceneApi, m: SurveyMap, point_size: float) -> list[Any]:
    """The station map under /survey/map: points, scanners and their labels, links, stems."""
    root = "/survey/map"
    h: list[Any] = [scene.add_frame(root, show_axes=False)]
    if len(m.points):
        h.append(scene.add_point_cloud(f"{root}/points", m.points, _colors(m.station_of), point_size=point_size,
                                       precision="float32"))
    for k, (name, verdict, at) in enumerate(zip(m.names, m.verdicts, m.scanners)):
        if not np.all(np.isfinite(at)):
            continue
        h.append(scene.add_icosphere(f"{root}/station{k}", radius=0.3, color=station_color(k), position=tuple(at)))
        h.append(scene.add_label(f"{root}/station{k}/name", f"{mark(verdict)} {name}", position=(0.0, 0.0, 0.45),
                                 anchor="bottom-center"))
    for state in LINK_COLORS:
        links = [ln for ln in m.links if ln.state == state and np.all(np.isfinite(ln.ends))]
        if links:
            segs = np.stack([ln.ends for ln in links]).astype(np.float32)
            h.append(scene.add_line_segments(f"{root}/links_{state}", segs, LINK_COLORS[state],
                                             thickness=5.0 if state == "used" else 3.0, thickness_units="screen"))
    if m.stems:
        rings = np.concatenate([_ring(s.xyz, max(s.radius_m, 0.05) + 0.08) for s in m.stems]).astype(np.float32)
        h.append(scene.add_line_segments(f"{root}/stems", rings, HIGHLIGHT, thickness=3.0, thickness_units="screen"))
    return h


def draw_pair(scene: viser.SceneApi, m: SurveyMap, p: PairInspection) -> list[Any]:
    """A pair inspected under /survey/pair: its link highlighted, its shared stems' sections from
    both stations coloured by station (stems the fit left out grey)."""
    root = "/survey/pair"
    h: list[Any] = [scene.add_frame(root, show_axes=False)]
    ln = m.links[p.index]
    if np.all(np.isfinite(ln.ends)):
        h.append(scene.add_line_segments(f"{root}/link", ln.ends[None].astype(np.float32), HIGHLIGHT, thickness=9.0,
                                         thickness_units="screen"))
    if len(p.points):
        colors = _colors(p.station_of)
        colors[~p.used] = GREY
        h.append(scene.add_point_cloud(f"{root}/sections", p.points.astype(np.float32), colors, point_size=0.03,
                                       precision="float32"))
    for k, (at, used) in enumerate(zip(p.stems_xyz, p.stems_used)):
        h.append(scene.add_label(f"{root}/stem{k}", "used" if used else "left out", position=tuple(at + [0, 0, 2.2]),
                                 anchor="bottom-center", font_screen_scale=0.8))
    return h


def draw_stem(scene: viser.SceneApi, s: StemInspection, m: SurveyMap) -> list[Any]:
    """A stem inspected under /survey/stem: every station's sections coloured by station, with circles."""
    root = "/survey/stem"
    h: list[Any] = [scene.add_frame(root, show_axes=False)]
    for v in s.views:
        if len(v.points):
            h.append(scene.add_point_cloud(f"{root}/s{v.station}/points", v.points.astype(np.float32),
                                           np.tile(np.array(station_color(v.station), np.uint8), (len(v.points), 1)),
                                           point_size=0.01, precision="float32"))
        rings = [_ring(c[:3], c[3]) for c in v.circles if np.all(np.isfinite(c))]
        if rings:
            h.append(scene.add_line_segments(f"{root}/s{v.station}/circles", np.concatenate(rings).astype(np.float32),
                                             station_color(v.station), thickness=2.0, thickness_units="screen"))
    h.append(scene.add_label(f"{root}/name", f"stem {s.index + 1}", position=(*s.xyz[:2], s.heights[1] + 0.3),
                             anchor="bottom-center"))
    return h


# ---- the panel ----------------------------------------------------------------------------------------
def _table(head: list[str], rows: list[list[str]]) -> str:
    """A markdown table; every cell is escaped by the caller."""
    return "\n".join(["| " + " | ".join(head) + " |", "|" + "---|" * len(head),
                      *("| " + " | ".join(r) + " |" for r in rows)])


def _nowrap(cell: str) -> str:
    """A table cell whose words stay whole ("verified": the survey's tables break names anywhere)."""
    return f'<span style="overflow-wrap: normal">{cell}</span>'


def legend() -> str:
    return " · ".join(f'<span style="color:{hex_color(c)}">━</span> {LINK_MEANING[s]}' for s, c in LINK_COLORS.items()) + \
        f' · <span style="color:{hex_color(HIGHLIGHT)}">◯</span> a stem at breast height'


def overview_content(snap: Snapshot, m: SurveyMap | None) -> PanelContent:
    """The survey as a whole: its stations' table and its pairs."""
    survey = snap.survey
    n = len(snap.scans)
    if survey is None or m is None:
        text = (f"{n} stations are registering as a survey (every station on every stem it shares with its "
                "neighbours). The map appears when they are placed." if snap.busy else
                f"{n} stations, not registered yet: press *Run*.")
        return PanelContent(f"Survey of {n} stations", text=text)
    drawn = len(m.points)
    text = (f"{n} stations, {len(survey.pairs)} pairs registered on the stems they share, "
            f"{len(m.stems)} stems. Drawn: {drawn:,} points of the stations' {m.cloud_points:,} voxel-thinned "
            f"points ({m.input_points:,} read), coloured by station.\n\n{legend()}\n\n"
            "Choose a pair or a stem on the right, or click a link's middle or a stem's ring: the stations' "
            "points are hidden while one is inspected.")
    rows = [[md(r[0]), _nowrap(md(f"{mark(r[1])} {r[1]}")), md(r[2]), md(r[3] or "–"), md(r[4] or "–"), md(r[5])]
            for r in station_rows(survey)]
    stations = _table(["station", "verdict", "pairs verified", "loop residual", "placed through", "stems"], rows)
    prow = []
    for ln in m.links:
        p = survey.pairs[ln.index]
        prow.append([str(ln.index + 1), md(" → ".join(survey.pair_names(p))),
                     _nowrap(md(verdict_badge(p.verdict))), md(f"{p.fit.stems_used} of {len(p.fit.stems)}"),
                     md(_mm(p.fit.residual_m)), md(LINK_MEANING[ln.state])])
    pairs = _table(["#", "pair", "verdict", "stems used", "stem residual", "on the map"], prow)
    return PanelContent(f"Survey of {n} stations", text=text, table=f"**Stations**\n\n{stations}\n\n**Pairs**\n\n{pairs}")


def _mm(v: float) -> str:
    return f"{v * 1000:.2f} mm" if np.isfinite(v) else "–"


def pair_content(survey: Survey, p: PairInspection) -> PanelContent:
    """A pair inspected: its verdict and reasons, its checks beside their thresholds, its numbers."""
    tgt, ref = survey.pair_names(survey.pairs[p.index])
    why = "\n".join(f"- {md(r)}" for r in p.reasons)
    text = (f"**{md(verdict_badge(p.verdict))}**" + (f", because\n\n{why}" if why else ": every check passes.") +
            f"\n\n{md(tgt)} (target) onto {md(ref)} (reference). In 3-D: the shared stems' sections, "
            f"{md(ref)} where the placement puts it and {md(tgt)} under this pair's own fit, coloured by station "
            "(stems the fit left out grey).")
    checks = _table(["check", "value", "threshold", ""],
                    [[md(c.what), md(c.value), md(c.threshold), "✓" if c.ok else "✗"] for c in p.checks])
    numbers = _table(["number", "value"], [[md(a), md(b)] for a, b in p.numbers])
    return PanelContent(f"Pair {p.index + 1}: {md(tgt)} → {md(ref)}", text=text,
                        table=f"**Checks**\n\n{checks}\n\n**Numbers**\n\n{numbers}")


def stem_content(s: StemInspection, m: SurveyMap) -> PanelContent:
    """A stem inspected: its sections from every station that sees it (a top view at breast height,
    and each station's section heights)."""
    seen = [v for v in s.views if v.breast >= 0]
    unseen = [v for v in s.views if v.breast < 0]
    text = (f"Seen at breast height by {len(s.views)} station{'s' if len(s.views) != 1 else ''}; "
            f"radius {s.radius_m * 100:.1f} cm. In 3-D: every station's sections placed, with their circles, "
            "coloured by station." +
            (f" Found at breast height but traced no section: {', '.join(md(v.name) for v in unseen)}." if unseen else ""))
    rows = []
    for v in seen:
        good = np.isfinite(v.heights_m) & np.isfinite(v.circles[:, 3])
        hs = ", ".join(f"{h:.2f}" for h in v.heights_m[good])
        c = v.circles[v.breast]
        rows.append([f'<span style="color:{hex_color(station_color(v.station))}">●</span>&nbsp;{md(v.name)}',
                     str(int(good.sum())), hs, f"{c[3] * 100:.1f}&nbsp;cm"])
    table = _table(["station", "sections", "heights above ground (m)", f"r at {BREAST_HEIGHT_M:g} m"], rows)
    plots = (stem_figure(s),) if seen else ()
    return PanelContent(f"Stem {s.index + 1}", text=text, plots=plots, table=table)


def stem_figure(s: StemInspection) -> tuple[Any, float]:
    """Top view of the stem's section nearest breast height from every station, in cm about the stem's
    centre, each station's points and circle in its colour."""
    import plotly.graph_objects as go

    fig = go.Figure()
    cx, cy = float(s.xyz[0]), float(s.xyz[1])
    a = np.linspace(0, 2 * np.pi, 73)
    for v in s.views:
        if v.breast < 0:
            continue
        col = hex_color(station_color(v.station))
        on = v.section == v.breast
        name = html(v.name)
        fig.add_trace(go.Scatter(x=(v.points[on, 0] - cx) * 100, y=(v.points[on, 1] - cy) * 100, mode="markers",
                                 marker=dict(size=4, color=col), name=name, legendgroup=str(v.station),
                                 hovertemplate=f"{name}<br>%{{x:.1f}}, %{{y:.1f}} cm<extra></extra>"))
        c = v.circles[v.breast]
        fig.add_trace(go.Scatter(x=(c[0] - cx + c[3] * np.cos(a)) * 100, y=(c[1] - cy + c[3] * np.sin(a)) * 100,
                                 mode="lines", line=dict(color=col, width=1.5), showlegend=False,
                                 legendgroup=str(v.station), hoverinfo="skip"))
    fig.update_layout(title=dict(text=f"Stem {s.index + 1} at {BREAST_HEIGHT_M:g} m, from each station", font=dict(size=14)),
                      xaxis=dict(title="x (cm)", scaleanchor="y", scaleratio=1), yaxis=dict(title="y (cm)"),
                      margin=dict(l=50, r=10, t=40, b=40), legend=dict(orientation="h", y=-0.2),
                      plot_bgcolor="white", paper_bgcolor="white", font=dict(size=11))
    return fig, 1.0


# ---- one tab ------------------------------------------------------------------------------------------
class SurveyViewer:
    """One tab's survey view (the app's `Viewer` for a survey): control panel on the right (status,
    progress, Run, the pair and stem lists, the point budget), the docked panel on the left, the map
    in 3-D; its own `SurveyDrawer`."""

    following = False

    def __init__(self, host: Any, gui: viser.GuiApi, scene: viser.SceneApi, client: Any | None,
                 atomic: Callable[[], AbstractContextManager[Any]], name: str = "this tab") -> None:
        self.host = host
        self.name = name
        self.controller: Controller = host.controller
        self.client = client
        self.gui = gui
        self.scene = scene
        self._lock = threading.Lock()
        self._view = SurveyViewState()
        self._closed = False
        self._last_progress = 0.0
        self._framed: int | None = None  # id of the survey the camera was framed on
        self._pairs: tuple[str, ...] = ()
        self._stems: tuple[str, ...] = ()
        self._quiet = False
        self._window_px: int | None = None

        self.panel = ViewPanel(gui, lambda **_: None, width=PANEL_WIDTH_PX)
        # A station's name is one long word ("placed through" lists several): the survey's tables break
        # it anywhere rather than grow wider than the panel.
        gui.add_markdown("<style>.treereg-tables td {overflow-wrap: anywhere !important;}</style>")
        gui.main_panel.dock_right()
        gui.main_panel.set_width(CONTROL_WIDTH_PX)
        n = len(self.controller.snapshot.scans)
        gui.add_markdown(f"**treereg** · whole-plot survey of {n} stations: every station registered on every stem "
                         "it shares with its neighbours")
        self.status = gui.add_markdown("")
        self.progress = gui.add_progress_bar(0.0, animated=False)
        self.progress_text = gui.add_markdown("")
        self.run = gui.add_button("Run", icon=viser.Icon.PLAYER_PLAY, color="green",
                                  hint="Register the stations again (as a survey).")
        self.run.on_click(lambda _: self.controller.request_run())
        with gui.add_folder("Inspect"):
            self.pair = gui.add_dropdown("Pair", (NONE,), hint="A registered pair: its verdict, checks and numbers, "
                                         "and its shared stems' sections in 3-D. Or click a link's middle.")
            self.stem = gui.add_dropdown("Stem", (NONE,), hint="A stem of the plot: its sections from every station "
                                         "that sees it. Or click a stem's ring.")
            self.back = gui.add_button("Whole survey", icon=viser.Icon.MAP, hint="Back to the stations' table and map.")
        with gui.add_folder("Display"):
            self.budget = gui.add_dropdown("Points drawn", tuple(POINT_BUDGETS), initial_value="300,000 points",
                                           hint="All stations together; each station's voxel-thinned cloud decimated "
                                           "in proportion.")
            self.size = gui.add_slider("Point size (m)", 0.01, 0.2, 0.01, 0.05)
        self.pair.on_update(lambda _: self._chose("pair"))
        self.stem.on_update(lambda _: self._chose("stem"))
        self.back.on_click(lambda _: self.set_view(pair=None, stem=None))
        self.budget.on_update(lambda _: self.set_view(max_points=POINT_BUDGETS[self.budget.value]))
        self.size.on_update(lambda _: self.set_view(point_size=float(self.size.value)))

        self.drawer = SurveyDrawer(scene, atomic, self.panel, lambda: self.controller.snapshot, lambda: self.view,
                                   host.derived, on_error=lambda msg: self.controller.note(msg, error=True),
                                   give_way=self.controller.give_way if client is not None else None,
                                   on_map=self._on_map)
        scene.on_click()(self._on_scene_click)
        if client is not None:
            client.camera.on_update(self._on_camera)
        self.on_snapshot(self.controller.snapshot)

    # ---- the view ---------------------------------------------------------------------------------
    @property
    def view(self) -> SurveyViewState:
        return self._view

    def set_view(self, **changes: Any) -> None:
        with self._lock:
            new = replace(self._view, **changes)
            changed, self._view = new != self._view, new
        if changed:
            self.drawer.post("lists", self._show_choice)
            self.drawer.request()
            if "pair" in changes or "stem" in changes:
                self.drawer.post("look", self._look)

    def _chose(self, which: str) -> None:
        if self._quiet:
            return
        if which == "pair":
            v = self.pair.value
            k = self._pairs.index(v) if v in self._pairs else None
            self.set_view(pair=k, stem=None if k is not None else self.view.stem)
        else:
            v = self.stem.value
            k = self._stems.index(v) if v in self._stems else None
            self.set_view(stem=k, pair=None if k is not None else self.view.pair)

    def _show_choice(self) -> None:
        """The lists show the view's pair and stem (without reporting back)."""
        self._quiet = True
        try:
            v = self.view
            want = self._pairs[v.pair] if v.pair is not None and v.pair < len(self._pairs) else NONE
            if self.pair.value != want:
                self.pair.value = want  # type: ignore[misc]
            want = self._stems[v.stem] if v.stem is not None and v.stem < len(self._stems) else NONE
            if self.stem.value != want:
                self.stem.value = want  # type: ignore[misc]
        finally:
            self._quiet = False

    def _on_map(self, survey: Survey, m: SurveyMap) -> None:
        """On the drawer's thread, once a survey's map is drawn: the lists offer its pairs and stems; the
        camera frames the plot the first time."""
        pairs = tuple(pair_label(survey, k) for k in range(len(survey.pairs)))
        stems = tuple(stem_label(m, k) for k in range(len(m.stems)))
        if pairs != self._pairs or stems != self._stems:
            self._quiet = True
            try:
                self._pairs, self._stems = pairs, stems
                self.pair.options = (NONE, *pairs)
                self.stem.options = (NONE, *stems)
            finally:
                self._quiet = False
            self._show_choice()
        if self._framed != id(survey):
            self._framed = id(survey)
            at = m.scanners[m.placed]
            if len(at):
                lo, hi = at.min(axis=0), at.max(axis=0)
                centre = (lo + hi) / 2
                span = float(max(hi[0] - lo[0], hi[1] - lo[1], 10.0))
                self._camera(centre + np.array([0.0, -1.0 * span, 0.9 * span]), centre)

    def _look(self) -> None:
        """The camera turns to the pair or stem chosen (from where it stands, nearer)."""
        snap, v = self.controller.snapshot, self.view
        if snap.survey is None:
            return
        m = self.drawer.survey_map(snap.survey, v.max_points)
        if v.pair is not None and v.pair < len(m.links):
            ln = m.links[v.pair]
            if np.all(np.isfinite(ln.ends)):
                d = float(np.linalg.norm(ln.ends[1] - ln.ends[0]))
                self._camera(ln.mid + np.array([0.0, -0.55 * d - 2, 0.45 * d + 3]), ln.mid)
        elif v.stem is not None and v.stem < len(m.stems):
            lo, hi = inspect_stem(snap.survey, m.stems[v.stem]).heights
            at = np.array([*m.stems[v.stem].xyz[:2], (lo + hi) / 2])
            d = max(hi - lo, 1.5) * 0.9 + 1.0  # the whole column in view
            self._camera(at + np.array([0.45 * d, -0.9 * d, 0.25 * d]), at)

    def _camera(self, position: np.ndarray, look_at: np.ndarray) -> None:
        if self.client is None:
            return
        try:
            with self.client.atomic():
                self.client.camera.up_direction = (0.0, 0.0, 1.0)
                self.client.camera.position = tuple(float(x) for x in position)
                self.client.camera.look_at = tuple(float(x) for x in look_at)
        except (AssertionError, AttributeError, ValueError):
            log.debug("camera not ready")

    def _on_camera(self, cam: Any) -> None:
        """A narrow window (a 1280 x 720 laptop screen) gets narrower panels, as the stage view's."""
        if self._window_px is None and (narrow := narrow_window(cam, self.panel.width + CONTROL_WIDTH_PX)) is not None:
            self._window_px = narrow
            self.panel.set_width(NARROW_PANEL_PX)
            self.gui.main_panel.set_width(NARROW_CONTROL_PX)
            self.drawer.request()

    def _on_scene_click(self, event: Any) -> None:
        pick_clicked(self.pick, event)

    def pick(self, origin: np.ndarray, direction: np.ndarray) -> None:
        """A click in 3-D: a link's middle inspects its pair, a stem's ring the stem."""
        snap, v = self.controller.snapshot, self.view
        if snap.survey is None:
            return
        m = self.drawer.survey_map(snap.survey, v.max_points)
        hit = m.pick(origin, direction)
        if hit is None:
            return
        kind, k = hit
        self.set_view(pair=k, stem=None) if kind == "link" else self.set_view(stem=k, pair=None)

    # ---- what the app calls ---------------------------------------------------------------------
    def on_snapshot(self, snap: Snapshot) -> None:
        if not self._closed:
            self.drawer.post("snapshot", lambda: self._show_snapshot(snap))
            self.drawer.request()

    def _show_snapshot(self, snap: Snapshot) -> None:
        self.status.content = (f"**{md(snap.message)}**" if snap.error else md(snap.message)) if snap.message else ""
        self.run.disabled = snap.busy
        if not snap.busy:
            self.progress.value = 100.0 if snap.survey is not None else 0.0  # type: ignore[misc]
            self.progress_text.content = ""

    def on_progress(self, fraction: float, text: str) -> None:
        now = time.perf_counter()
        if fraction < 1.0 and now - self._last_progress < 0.1:
            return
        self._last_progress = now

        def show() -> None:
            self.progress.value = float(min(max(fraction, 0.0), 1.0) * 100.0)  # type: ignore[misc]
            self.progress_text.content = f"*{md(text)}*" if text else ""

        self.drawer.post("progress", show)

    def show_presenter(self, presenter: Any) -> None:
        """A survey tab neither presents nor follows (the stage view's Teach tab), nor takes the
        projector mode (`treereg view --projector` enlarges the stage view's tabs)."""

    def follow(self, presenter: Any) -> None:
        pass

    def offer_tabs(self, names: list[str]) -> None:
        pass

    def show_changed_elsewhere(self, by: str, what: str, undo: Any) -> None:
        """Another tab's change (parameters, a hypothesis) is the stage view's; a survey has none."""

    def follow_camera(self, position: Any, look_at: Any, up: Any) -> None:
        pass

    def close(self) -> None:
        self._closed = True
        self.drawer.close()
