"""The guided tour: the stages in order, each with the paper's reasoning in two sentences and one
thing to try, the camera, the panel and a highlight set for it (the steps are written in each
stage's module, `treereg_viewer/stages/<name>.py`).

For teaching: a class follows the steps on its own screens, or follows the teacher's tab ("others
follow me", Teach tab). The steps read only the results (the stage, its panel, a height on the
trunk), so the tour works on any scans, the demo or uploaded ones, offline.
"""

from __future__ import annotations

from typing import Any

import viser

from .stages import STAGES
from .stages.base import TourStep


#: The tour's steps: each stage's own (`treereg_viewer/stages/<name>.py`), in run order.
STEPS: tuple[TourStep, ...] = tuple(step for stage in STAGES.values() for step in stage.tour)


class TourPanel:
    """The tour's card at the top of the control panel: step text and Back / Next / End."""

    def __init__(self, gui: viser.GuiApi, go_to: Any) -> None:
        self._go_to = go_to  # go_to(step index or None)
        self.card = gui.add_markdown("", visible=False)
        self.nav = gui.add_button_group("Tour", ("◀ Back", "Next ▶", "End tour"), visible=False)
        self.nav.on_click(lambda e: self._nav(e.target.value))
        self.step: int | None = None

    def _nav(self, which: str) -> None:
        if self.step is None:
            return
        if which == "End tour" or (which.startswith("Next") and self.step == len(STEPS) - 1):
            self._go_to(None)  # Next on the last step ends the tour (it used to do nothing)
        else:
            self._go_to(max(0, min(len(STEPS) - 1, self.step + (1 if which.startswith("Next") else -1))))

    def step_by(self, delta: int) -> None:
        """The keys' Next (+1) or Back (-1): as the buttons."""
        self._nav("Next ▶" if delta > 0 else "◀ Back")

    def show(self, step: int | None, following: bool = False) -> None:
        """Show step `step` (None hides the card); a tab `following` the presenter reads the card
        without the buttons (the presenter leads the steps)."""
        self.step = None if following else step
        if step is None:
            self.card.visible = False
            self.nav.visible = False
            return
        s = STEPS[step]
        last = "\n\n*The last step: Next ends the tour.*" if step == len(STEPS) - 1 and not following else ""
        self.card.content = (f"#### Tour · step {step + 1} of {len(STEPS)}: {s.title}\n\n{s.why}\n\n"
                             f"**Try:** {s.try_this}{last}")
        self.card.visible = True
        self.nav.visible = not following
