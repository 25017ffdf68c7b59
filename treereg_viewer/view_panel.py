"""The wide panel docked on the left: images, plots and tables of the current stage.

The control panel is about 345 px wide, too narrow for projection images and plots, so they live
in a panel of their own (viser 1.1 `add_panel` + `dock_left`). A renderer describes what it wants
shown as a `PanelContent`; `ViewPanel.show` puts it there. Elements are made once and updated or
hidden: re-creating GUI elements would make the panel jump.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import viser

#: At most this many images and plots per stage.
MAX_IMAGES = 2
MAX_PLOTS = 2


def plot_aspect(width_over_height: float) -> float:
    """The `aspect` viser 1.1's plotly element wants for a plot `width_over_height` wide.

    viser documents `aspect` as width/height, but its client sizes the plot as
    `height = width * aspect`: passed as documented, a wide plot comes out tall and its lower half
    is scrolled out of the panel.
    """
    return 1.0 / max(float(width_over_height), 1e-3)


@dataclass(frozen=True)
class PanelContent:
    """What one stage shows in the panel: a heading, images with captions, plots, tables."""

    title: str
    text: str = ""
    images: tuple[tuple[np.ndarray, str], ...] = ()
    plots: tuple[tuple[Any, float], ...] = ()  # (plotly figure, width / height)
    table: str = ""


@dataclass
class ViewPanel:
    """The docked panel and its reusable elements."""

    server: viser.ViserServer
    width: int = 560
    _panel: Any = field(init=False)
    _title: Any = field(init=False)
    _text: Any = field(init=False)
    _captions: list[Any] = field(init=False, default_factory=list)
    _images: list[Any] = field(init=False, default_factory=list)
    _plots: list[Any] = field(init=False, default_factory=list)
    _table: Any = field(init=False)

    def __post_init__(self) -> None:
        gui = self.server.gui
        self._panel = gui.add_panel()
        self._tab = self._panel.add_tab("Stage view", viser.Icon.PHOTO)
        with self._tab:
            self._title = gui.add_markdown("### Scans", order=0)
            self._text = gui.add_markdown("", order=1)
            blank = np.full((8, 8, 3), 255, np.uint8)
            for k in range(MAX_IMAGES):
                self._captions.append(gui.add_markdown("", visible=False, order=2 + 2 * k))
                self._images.append(gui.add_image(blank, format="png", visible=False, order=3 + 2 * k))
            self._table = gui.add_markdown("", order=20)
        self._panel.dock_left()
        self._panel.set_width(self.width)

    def _ensure_plots(self) -> None:
        # Made on first use: the first plot sends plotly's 3 MB script to every browser, which
        # would otherwise delay the first view of the scans by about two seconds.
        if self._plots:
            return
        import plotly.graph_objects as go

        with self._tab:
            for k in range(MAX_PLOTS):
                self._plots.append(self.server.gui.add_plotly(go.Figure(), aspect=plot_aspect(1.6), visible=False, order=10 + k))

    def show(self, content: PanelContent) -> None:
        """Replace the panel's content (call inside `server.atomic()` with the scene updates)."""
        self._title.content = f"### {content.title}"
        self._text.content = content.text
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
            self._ensure_plots()
        for k, plot in enumerate(self._plots):
            if k < len(content.plots):
                fig, aspect = content.plots[k]
                plot.figure = fig
                plot.aspect = plot_aspect(aspect)
                plot.visible = True
            else:
                plot.visible = False
        self._table.content = content.table

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
    def table(self) -> str:
        return self._table.content
