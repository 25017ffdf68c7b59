"""The app's stages: for each of the core's stages (`treereg_core.stages.STAGE_NAMES`) its module
`treereg_viewer/stages/<name>.py`, which holds all the app adds to it (`base.AppStage`): the pose
the scans are drawn at and how, the explanation, the drawing and the view choices it depends on,
the view controls and the tour steps.

Every core stage must have its module: a missing one is an ImportError naming the stage, so the app
does not start and every test fails (no stage is drawn by a silent default).
"""

from __future__ import annotations

import importlib
from typing import Any

from ..labels import APP_STAGES, STAGE_NAMES, by_label, label
from .base import AppStage, StageView

__all__ = ["APP_STAGES", "POSE_STAGE", "STAGES", "STAGE_NAMES", "by_label", "label", "registered",
           "section_available", "stage_of", "view_of"]


def _load(name: str) -> AppStage:
    try:
        module = importlib.import_module(f"{__name__}.{name}")
    except ModuleNotFoundError as e:
        if e.name != f"{__name__}.{name}":
            raise
        raise ImportError(f"the core's stage {name!r} has no module treereg_viewer/stages/{name}.py") from e
    stage: AppStage = module.STAGE
    if stage.name != name or any(step.stage != name for step in stage.tour):
        raise ImportError(f"treereg_viewer/stages/{name}.py describes stage {stage.name!r} (or tours another)")
    return stage


#: The app's side of every core stage, in run order.
STAGES: dict[str, AppStage] = {name: _load(name) for name in STAGE_NAMES}

#: The stage whose output holds each pose's transforms.
POSE_STAGE = {"coarse": "coarse", "hypothesis": "hypotheses", "fine": "fine", "icp": "icp", "final": "graph"}


def stage_of(name: str) -> AppStage:
    """The app's side of stage `name` (KeyError for a name the core does not have)."""
    return STAGES[name]


def view_of(name: str) -> StageView:
    """The pose, scan layer and explanation of stage `name`."""
    return STAGES[name].view


def registered(name: str) -> bool:
    """Whether the scans are drawn over the reference (a pose exists) rather than scattered in their frames."""
    return view_of(name).pose is not None


def section_available(snap: Any, name: str) -> bool:
    """Whether the cross-section inspector can be shown on stage `name`: the scans are registered
    there and a coarse registration exists to cut."""
    return registered(name) and snap.output("coarse") is not None and len(snap.scans) >= 2
