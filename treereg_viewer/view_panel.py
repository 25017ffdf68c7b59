"""The wide panel docked on the left: the current stage's images, plots and tables, or the
cross-section inspector.

The control panel is about 345 px wide, too narrow for projection images and plots, so they live
in a panel of their own (viser 1.1 `add_panel` + `dock_left`). A renderer describes what it wants
shown as a `PanelContent`; `ViewPanel.show` puts it there. Elements are made once and updated or
hidden: re-creating GUI elements would make the panel jump.

At the top, from the Coarse stage on, a switch between the stage's details and the cross-section
inspector (a slab of every scan at a height, or a branch's evaluation layers; its controls sit
under the switch).
"""

from __future__ import annotations

import re
import threading

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import viser

from .view_state import SECTION_POSES, ViewState

#: At most this many images and plots per stage.
MAX_IMAGES = 2
MAX_PLOTS = 3
#: Tables in the panels: a little room between columns, and cells that wrap (a long word too) so that
#: no table is ever wider than its panel, whatever its width (1280 x 720 included): nothing is
#: clipped and nothing scrolls sideways. The small print under a cell (a parameter's name) is grey.
TABLE_CSS = ("<style>.treereg-tables {max-width: 100%;} .treereg-tables table {width: 100%;} "
             ".treereg-tables td, .treereg-tables th {padding: 2px 8px 2px 0 !important; white-space: normal "
             "!important; overflow-wrap: break-word;} .treereg-tables small {color: #777;}</style>")


def fitted(markdown: str) -> str:
    """Markdown whose tables wrap to the panel's width (see `TABLE_CSS`)."""
    return f'<div class="treereg-tables">\n\n{markdown}\n\n</div>' if "|" in markdown else markdown


#: The switch's two faces.
MODES = {"Stage details": "stage", "Cross-section": "section"}
STEM = "Stem (pick a height)"


def plot_aspect(width_over_height: float) -> float:
    """The `aspect` viser 1.1's plotly element wants for a plot `width_over_height` wide.

    viser documents `aspect` as width/height, but its client sizes the plot as
    `height = width * aspect`: passed as documented, a wide plot comes out tall and its lower half
    is scrolled out of the panel.
    """
    return 1.0 / max(float(width_over_height), 1e-3)


#: Plot text widths, estimated: a character is about this share of its font size wide (plotly's
#: default sans serif); a line is this many times its font size tall.
CHAR_EM = 0.58
LINE_EM = 1.3
#: The plot is this much narrower than its panel (the panel's padding and scrollbar).
PLOT_INSET_PX = 20
#: plotly's default margins, where a figure sets none.
DEFAULT_MARGIN = {"l": 80, "r": 80, "t": 100, "b": 80}


def _chars(text: str) -> int:
    """Characters a piece of plotly text shows (its tags dropped, an entity one character)."""
    return len(re.sub(r"&#?\w+;", "x", re.sub(r"<[^>]+>", "", text)))


def wrapped(text: str, width_px: float, font_px: float) -> list[str]:
    """`text` in lines of at most `width_px` (estimated), broken between words; lines it already has kept."""
    per = max(6, int(width_px / (CHAR_EM * font_px)))
    lines: list[str] = []
    for part in re.split(r"<br\s*/?>", text):
        line = ""
        words: list[str] = []
        for word in part.split(" "):  # a word of one or two characters stays with the one before ("0.92 m", "z =")
            if words and _chars(word) <= 2:
                words[-1] += f" {word}"
            else:
                words.append(word)
        for word in words:
            if line and _chars(f"{line} {word}") > per:
                lines.append(line)
                line = word
            else:
                line = f"{line} {word}" if line else word
        lines.append(line)
    return lines


#: A plot keeps at least this much height for its axes, whatever its margins (titles, legend) take.
MIN_AREA_PX = 150


def fit_figure(fig: Any, width_px: float, width_over_height: float) -> float:
    """Fit a figure's words to the size it is shown at (in place): its title, its subplots' titles
    and its axis titles broken into lines that fit (at 1280 x 720 a plot is 310 px wide: titles ran
    past its edges and into each other), the top and left margins grown for the lines added; returns
    the width / height to show it at, taller than asked where its margins left its axes less than
    `MIN_AREA_PX`."""
    layout = fig.layout
    base = float(layout.font.size or 12)
    margin = {k: float(getattr(layout.margin, k) if getattr(layout.margin, k) is not None else v)
              for k, v in DEFAULT_MARGIN.items()}
    height_px = width_px / max(width_over_height, 1e-3)
    top = 0.0  # extra lines over the plot area, in px
    title = layout.title.text
    title_lines, size = 0, base
    if title:
        size = float(layout.title.font.size or round(base * 1.4))
        lines = wrapped(title, width_px - 10, size)
        title_lines = len(lines)
        if title_lines > 1:
            layout.title.text = "<br>".join(lines)
            top = max(top, title_lines * size * LINE_EM + 16 - margin["t"])
    area = max(width_px - margin["l"] - margin["r"], 1.0)
    paper = [a for a in layout.annotations if a.xref == "paper" and a.yref == "paper" and a.text and a.yanchor == "bottom"]
    for a in paper:  # subplot titles: as wide as the gap to the next one on their row
        others = [abs(float(b.x) - float(a.x)) for b in paper if b is not a and abs(float(b.y) - float(a.y)) < 1e-6]
        room = (min(others) if others else 1.0) * area - 6
        size = float(a.font.size or base)
        lines = wrapped(a.text, room, size)
        if len(lines) > 1:
            a.text = "<br>".join(lines)
            if float(a.y) >= 0.99:
                top = max(top, (len(lines) - 1) * size * LINE_EM)
    left = 0.0
    height_px = max(height_px, margin["t"] + top + margin["b"] + MIN_AREA_PX)
    if title and title_lines > 1:
        # plotly places a title of several lines by its first: that line's foot a line below the top,
        # the others under it, in the top margin that holds them.
        layout.title.update(yref="container", y=1.0 - (size + 6) / height_px, yanchor="bottom")
    plot_h = height_px - margin["t"] - top - margin["b"]
    for name in [k for k in layout if k.startswith("yaxis")]:
        axis = layout[name]
        text = axis.title.text
        if not text:
            continue
        lo, hi = axis.domain if axis.domain else (0.0, 1.0)
        size = float(axis.title.font.size or base)
        lines = wrapped(text, (hi - lo) * plot_h, size)
        if len(lines) > 1:
            axis.title.text = "<br>".join(lines)
            left = max(left, (len(lines) - 1) * size * LINE_EM)
    for name in [k for k in layout if k.startswith("xaxis")]:
        axis = layout[name]
        text = axis.title.text
        if text:
            lo, hi = axis.domain if axis.domain else (0.0, 1.0)
            axis.title.text = "<br>".join(wrapped(text, (hi - lo) * (area - left), float(axis.title.font.size or base)))
    if top or left:
        layout.margin.update(t=margin["t"] + top, l=margin["l"] + left)
    return width_px / height_px


@dataclass(frozen=True)
class PanelContent:
    """What one stage shows in the panel: a heading, images with captions, plots, tables."""

    title: str
    text: str = ""
    images: tuple[tuple[np.ndarray, str], ...] = ()
    plots: tuple[tuple[Any, float], ...] = ()  # (plotly figure, width / height)
    table: str = ""


class ViewPanel:
    """The docked panel of one viewer and its reusable elements.

    `set_view(**changes)` records the inspector's control changes in the viewer's ViewState.
    """

    def __init__(self, gui: viser.GuiApi, set_view: Callable[..., None], width: int = 560) -> None:
        self.gui = gui
        self.width = width
        self._set_view = set_view
        # Set while this panel puts values into its own controls (on the thread doing so only: a
        # person's change arriving meanwhile on another thread is not swallowed).
        self._local = threading.local()
        self._panel = gui.add_panel()
        self._tab = self._panel.add_tab("View", viser.Icon.PHOTO)
        self._captions: list[Any] = []
        self._images: list[Any] = []
        self._plots: list[Any] = []
        with self._tab:
            self.mode = gui.add_dropdown("Show", tuple(MODES), initial_value="Stage details", order=0, visible=False,
                                         hint="The current stage's details, or a cross-section of the registered scans.")
            self.section_of = gui.add_dropdown("Section of", (STEM,), order=0.1, visible=False,
                                               hint="The stem at a height, or a branch the Result stage evaluated.")
            self.height = gui.add_slider("Height (m)", -1.0, 10.0, 0.01, 0.0, order=0.2, visible=False,
                                         hint="Height of the slab (reference frame). Or click the tree in 3-D.")
            self.poses = gui.add_dropdown("Registration", tuple(SECTION_POSES), initial_value="Coarse and fine",
                                          order=0.3, visible=False, hint="Which registrations to cut, side by side.")
            gui.add_markdown(TABLE_CSS, order=0.05)
            self._title = gui.add_markdown("### Scans", order=1)
            self._text = gui.add_markdown("", order=2)
            blank = np.full((8, 8, 3), 255, np.uint8)
            for k in range(MAX_IMAGES):
                self._captions.append(gui.add_markdown("", visible=False, order=3 + 2 * k))
                self._images.append(gui.add_image(blank, format="png", visible=False, order=4 + 2 * k))
            self._table = gui.add_markdown("", order=20)
        self._panel.dock_left()
        self._panel.set_width(width)
        self.mode.on_update(lambda _: self._changed(panel=MODES[self.mode.value]))
        self.section_of.on_update(lambda _: self._changed(branch=self._branch_choice()))
        self.height.on_update(lambda _: self._changed(section_height=float(self.height.value), branch=None))
        self.poses.on_update(lambda _: self._changed(section_poses=self.poses.value))
        self._branch_options: tuple[str, ...] = (STEM,)

    @property
    def _quiet(self) -> bool:
        return getattr(self._local, "quiet", False)

    def _changed(self, **changes: Any) -> None:
        if not self._quiet:
            self._set_view(**changes)

    def _branch_choice(self) -> int | None:
        v = self.section_of.value
        return None if v == STEM or v not in self._branch_options else self._branch_options.index(v) - 1

    def set_width(self, width: int) -> None:
        if width != self.width:
            self.width = width
            self._panel.set_width(width)

    def prepare_plots(self) -> None:
        # Made on first use: the first plot sends plotly's 3 MB script to the browser, which would
        # otherwise delay the first view of the scans by about two seconds.
        if self._plots:
            return
        import plotly.graph_objects as go

        with self._tab:
            for k in range(MAX_PLOTS):
                self._plots.append(self.gui.add_plotly(go.Figure(), aspect=plot_aspect(1.6), visible=False, order=10 + k))

    # ---- the inspector's controls -----------------------------------------------------------------
    def show_controls(self, view: ViewState, available: bool, height_range: tuple[float, float] | None,
                      height: float | None, branches: list[str]) -> None:
        """Show the switch (when a cross-section can be cut) and, in section mode, its controls at
        the view's values (without reporting them back as changes)."""
        self._local.quiet = True
        try:
            self.mode.visible = available
            want_mode = next(k for k, v in MODES.items() if v == view.panel)
            if self.mode.value != want_mode:
                self.mode.value = want_mode
            section = available and view.panel == "section"
            options = (STEM, *branches)
            if options != self._branch_options:
                self._branch_options = options
                self.section_of.options = options
            want = STEM if view.branch is None or view.branch + 1 >= len(options) else options[view.branch + 1]
            if self.section_of.value != want:
                self.section_of.value = want
            self.section_of.visible = section
            self.poses.visible = section
            if self.poses.value != view.section_poses:
                self.poses.value = view.section_poses
            self.height.visible = section and view.branch is None
            if height_range is not None:
                lo, hi = round(height_range[0], 2), round(height_range[1], 2)
                if (self.height.min, self.height.max) != (lo, hi):
                    self.height.min, self.height.max = lo, hi
                if height is not None:
                    v = float(np.clip(round(height, 2), lo, hi))
                    if abs(self.height.value - v) > 1e-9:
                        self.height.value = v
        finally:
            self._local.quiet = False

    # ---- content ----------------------------------------------------------------------------------
    def show(self, content: PanelContent) -> None:
        """Replace the panel's content (call inside the viewer's `atomic()` with the scene updates)."""
        self._title.content = f"### {content.title}"
        self._text.content = fitted(content.text)
        for k, (cap, img) in enumerate(zip(self._captions, self._images)):
            if k < len(content.images):
                arr, caption = content.images[k]
                cap.content = caption
                cap.visible = bool(caption)
                img.image = arr
                img.visible = True
            else:
                cap.visible = False
                img.visible = False
        if content.plots:
            self.prepare_plots()
        for k, plot in enumerate(self._plots):
            if k < len(content.plots):
                fig, aspect = content.plots[k]
                fitted_at = getattr(fig, "_treereg_fitted", None)  # a figure shown again is fitted already
                if fitted_at is None or fitted_at[0] != self.width:
                    fitted_at = (self.width, fit_figure(fig, self.width - PLOT_INSET_PX, aspect))
                    fig._treereg_fitted = fitted_at
                plot.figure = fig
                plot.aspect = plot_aspect(fitted_at[1])
                plot.visible = True
            else:
                plot.visible = False
        self._table.content = fitted(content.table)

    @property
    def images(self) -> list[Any]:
        """The image handles (tests read what is shown)."""
        return self._images

    @property
    def plots(self) -> list[Any]:
        return self._plots

    @property
    def title(self) -> str:
        return self._title.content

    @property
    def text(self) -> str:
        return self._text.content

    @property
    def table(self) -> str:
        return self._table.content
