"""What one stage module of the app holds (`AppStage`), and the pieces it is built of: the stage's
view (`StageView`), its drawing (`RenderFn`), its view controls (`StageControls`, behind the narrow
`ControlHost` the Stage tab gives them) and its tour steps (`TourStep`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Protocol

import viser

from ..actions import AppActions
from ..controller import Snapshot
from ..draw.common import Drawing
from ..view_state import ViewState


@dataclass(frozen=True)
class StageView:
    """How the scans are shown on a stage, and what it is about.

    Attributes
    ----------
    pose
        Which transform places the target scans on this stage: None (each in its own scanner frame,
        before registration), "coarse", "hypothesis", "fine", "icp" or "final" (the joint placement).
    scans
        How the scan layer is drawn: "full", "faded" (the stage's own drawing is the subject) or
        "hidden" (points would hide fitted surfaces).
    explanation
        What the stage does and why, in a few sentences (the paper's sections cited).
    """

    pose: str | None = "fine"
    scans: str = "full"
    explanation: str = ""


class RenderFn(Protocol):
    """A stage's drawing: `(scene, root, snapshot, view) -> (scene handles, panel content)`.

    It returns the scene handles it made (so the drawer can remove them on the next draw) and the
    `PanelContent` for the docked panel. The drawer calls it only when the stage has an output and
    the chosen pair was not skipped (unless the stage's `needs_output` is False). Drawings only draw
    results: every coordinate comes from a result or from `treereg_core`'s `apply_transform` with a
    result's transform.
    """

    def __call__(self, scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState, /) -> Drawing: ...


class ControlHost(Protocol):
    """The Stage tab as a stage's view controls see it."""

    app: AppActions

    @property
    def quiet(self) -> bool:
        """True while the panel puts values into its own controls (they must not report them back)."""
        ...

    def set_view(self, **changes: Any) -> None:
        """A person's change of view choices (ignored while quiet)."""
        ...


class StageControls:
    """View controls a stage adds to its folder. Built inside the folder as `Kind(gui, host, stage)`;
    the panel then keeps them showing the view and the results (while quiet)."""

    def show_view(self, view: ViewState, snap: Snapshot) -> None:
        """Put the view's choices into the controls (a followed presenter, the tour)."""

    def show_snapshot(self, snap: Snapshot, view: ViewState) -> None:
        """Follow the results: ranges and options."""

    def refresh_focus(self, snap: Snapshot, view: ViewState) -> None:
        """Follow the fits table's rows (only the fits controls have any)."""


#: A stage's controls are made in its folder: `make(gui, host, stage name)`.
ControlsFactory = Callable[[viser.GuiApi, ControlHost, str], StageControls]


def pair_labels(snap: Snapshot) -> list[str]:
    """What the "Pair" lists offer, in the pipeline's order of pairs (a view's `target`): 'scan2 →
    scan1', 'scan3 → scan1', …, then the pairs between other scans ('scan3 → scan2': with three or
    more stations these are registered too, and may be the one that tells why a scan failed)."""
    return [snap.pair(k).label for k in range(snap.n_pairs)] or ["(no target scan)"]


class TargetControl(StageControls):
    """"Pair": which target scan the stage's panel details (every stage's list shows the one choice)."""

    def __init__(self, gui: viser.GuiApi, host: ControlHost, stage: str) -> None:
        self.host = host
        self.dropdown = gui.add_dropdown("Pair", ["scan2 → scan1"], hint="Which target scan the panel details.")
        self.dropdown.on_update(self._picked)

    def _picked(self, _: Any) -> None:
        if not self.host.quiet:
            self.host.app.select_target(self.dropdown.value)

    def show_choice(self, pair: str) -> None:
        """Another stage's list picked `pair`: show it here too."""
        if self.dropdown.value != pair:
            # viser's dropdown redeclares `value` with a getter only; the base class's setter applies.
            self.dropdown.value = pair  # type: ignore[misc]

    def show_view(self, view: ViewState, snap: Snapshot) -> None:
        pairs = pair_labels(snap)
        if view.target < len(pairs):
            self.show_choice(pairs[view.target])

    def show_snapshot(self, snap: Snapshot, view: ViewState) -> None:
        pairs = pair_labels(snap)
        if tuple(self.dropdown.options) != tuple(pairs):
            self.dropdown.options = pairs


@dataclass(frozen=True)
class TourStep:
    """One step of the guided tour (`treereg_viewer.tour`).

    Attributes
    ----------
    stage
        The pipeline stage shown.
    title
        A short heading.
    why
        The paper's reasoning, two sentences.
    try_this
        One thing to try (controls named as they read in the app).
    view
        View choices set for the step (e.g. the cross-section panel).
    camera
        "frame" (what the stage draws) or "trunk" (a close view of the trunk slice).
    highlight
        What labels in 3-D point at: "trees" (each scan's tree), "trunk" (the cross-section's
        slice) or "" (none).
    """

    stage: str
    title: str
    why: str
    try_this: str
    view: dict[str, Any] = field(default_factory=dict)
    camera: str = "frame"
    highlight: str = ""


@dataclass(frozen=True)
class AppStage:
    """The app's side of one core stage, all in its module `treereg_viewer/stages/<name>.py`.

    Attributes
    ----------
    name
        The core stage's name (`treereg_core.stages.STAGE_NAMES`), which is also the module's.
    view
        Pose, scan layer and explanation.
    draw, view_fields, needs_output
        The stage's drawing; the view choices it depends on (it is redrawn when one changes); whether
        it is drawn only once the stage has an output.
    controls
        The view controls the stage's folder gets, in order.
    tour
        The stage's steps of the guided tour.
    """

    name: str
    view: StageView
    draw: RenderFn
    view_fields: tuple[str, ...] = ()
    needs_output: bool = True
    controls: tuple[ControlsFactory, ...] = ()
    tour: tuple[TourStep, ...] = ()
