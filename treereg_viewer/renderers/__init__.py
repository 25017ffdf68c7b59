"""One drawing function per stage, found by the stage's name (`RENDERERS`).

Each takes the scene, the stage's layer root, the published `Snapshot` and the `ViewState`, and
returns the scene handles it made (so the drawer can remove them on the next draw) and the
`PanelContent` for the docked panel. The drawer calls it only when the stage has an output and the
chosen pair was not skipped (unless `needs_output` is False). Renderers only draw results: every
coordinate they show comes from a result or from `treereg_core`'s `apply_transform` with a result's
transform.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import viser

from ..controller import Snapshot
from ..view_state import ViewState
from . import coarse, fine, icp, matching, projection, result, scans, verify
from .common import Drawing


class RenderFn(Protocol):
    """A stage's drawing: `(scene, root, snapshot, view) -> (scene handles, panel content)`."""

    def __call__(self, scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState, /) -> Drawing: ...


@dataclass(frozen=True)
class Renderer:
    """How one stage is drawn, and the view choices its drawing depends on."""

    draw: RenderFn
    view_fields: tuple[str, ...] = ()
    needs_output: bool = True


RENDERERS: dict[str, Renderer] = {
    "prepare": Renderer(scans.render, (), scans.NEEDS_OUTPUT),
    "projection": Renderer(projection.render, projection.VIEW_FIELDS),
    "matching": Renderer(matching.render, matching.VIEW_FIELDS),
    "coarse": Renderer(coarse.render, coarse.VIEW_FIELDS),
    "hypotheses": Renderer(verify.render_hypotheses, verify.HYPOTHESES_VIEW_FIELDS),
    "slices": Renderer(fine.render_slices, fine.SLICES_VIEW_FIELDS),
    "arcs": Renderer(fine.render_arcs, fine.ARCS_VIEW_FIELDS),
    "sections": Renderer(fine.render_sections, fine.SECTIONS_VIEW_FIELDS),
    "fine": Renderer(fine.render_fine, fine.FINE_VIEW_FIELDS),
    "verify": Renderer(verify.render_verify, verify.VERIFY_VIEW_FIELDS),
    "graph": Renderer(verify.render_graph, verify.GRAPH_VIEW_FIELDS),
    "icp": Renderer(icp.render, icp.VIEW_FIELDS),
    "evaluation": Renderer(result.render, result.VIEW_FIELDS),
}
