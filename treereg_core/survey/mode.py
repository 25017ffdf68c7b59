"""Whether a registration is a survey (every station on every stem it shares) or of one tree.

`survey.mode` says so, or "auto": a survey when there are more than 8 stations (a tree is scanned
from 2-8 stations round it; a plot from a grid of 9 and more) and no target tree was given
(`target.tree_at` keeps the one-tree registration). Fewer stations in a grid: `--survey`.
"""

from __future__ import annotations

from ..params import Params

#: More stations than this stand round a plot, not round one tree.
ONE_TREE_MAX_STATIONS = 8


def is_survey(n_scans: int, params: Params) -> bool:
    """True when `n_scans` stations are registered as a survey under `params` (see the module doc)."""
    mode = params.survey.mode
    if mode != "auto":
        return mode == "survey"
    return n_scans > ONE_TREE_MAX_STATIONS and params.target.tree_at is None
