"""The stages' names and labels as people read them: exactly the core's stages (`treereg_core.stages`),
in run order, numbered from 1. A leaf module: the controller, the drawings and the stage registry
(`treereg_viewer.stages`) all read it.
"""

from __future__ import annotations

from treereg_core.stages import STAGES, Stage

#: The app's stages: exactly the pipeline's, in run order.
APP_STAGES: tuple[Stage, ...] = STAGES
STAGE_NAMES: tuple[str, ...] = tuple(s.name for s in STAGES)


def label(name: str) -> str:
    """What a person reads for a stage, numbered from 1: '4 Coarse'."""
    i = STAGE_NAMES.index(name)
    return f"{i + 1} {APP_STAGES[i].title}"


def by_label(text: str) -> str:
    """The stage name behind a selector label."""
    for name in STAGE_NAMES:
        if label(name) == text:
            return name
    raise KeyError(text)


#: One mark per verdict, the same in every header, panel, help text and 3-D label.
VERDICT_MARKS = {"verified": "✓", "unverified": "⚠", "failed": "✗"}


def verdict_badge(verdict: str) -> str:
    """'✓ verified', '⚠ unverified', '✗ failed'."""
    return f"{VERDICT_MARKS.get(verdict, '?')} {verdict}"


#: The marks as a legend sentence, for help texts.
VERDICT_LEGEND = "✓ verified, ⚠ unverified (a best guess, with the reasons), ✗ failed (not placed)"
