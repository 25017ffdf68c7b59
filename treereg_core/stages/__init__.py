"""The registry of stages, in the order they run.

Each stage is one module of this package named after it (`stages/arcs.py` for `arcs`), holding
its `STAGE` declaration — name, title, summary, the parameter sections it reads, the stages it
depends on, its result type — and its run function, which unpacks the pipeline's state into the
stage function's own arguments (a stage function never sees the whole parameter tree). What
several run functions share is in `stages/common.py`. Adding a stage: write its module and add it
to `STAGES` below.
"""

from __future__ import annotations

from ..stage import Stage
from . import (arcs, coarse, evaluation, fine, graph, hypotheses, icp, matching, prepare, projection, sections, slices,
               verify)

STAGES: tuple[Stage, ...] = tuple(m.STAGE for m in (
    prepare, projection, matching, coarse, hypotheses, slices, arcs, sections, fine, verify, graph, icp, evaluation))

#: Where a run stops when a user says "--until coarse|fine": fine includes verification and the
#: placement of every scan (the graph stage), so every scan gets its verdict.
UNTIL = {"coarse": "coarse", "fine": "graph"}

#: Stage names in run order.
STAGE_NAMES: tuple[str, ...] = tuple(s.name for s in STAGES)
BY_NAME: dict[str, Stage] = {s.name: s for s in STAGES}


def stage(name: str) -> Stage:
    """The registered stage `name` (KeyError naming the known ones otherwise)."""
    try:
        return BY_NAME[name]
    except KeyError:
        raise KeyError(f"no stage {name!r}; stages are {', '.join(STAGE_NAMES)}") from None


def downstream(name: str) -> tuple[str, ...]:
    """`name` and every stage that depends on it, directly or not, in run order."""
    hit = {name}
    for s in STAGES:
        if any(u in hit for u in s.upstream):
            hit.add(s.name)
    return tuple(s for s in STAGE_NAMES if s in hit)


def affected_by(section: str) -> tuple[str, ...]:
    """The stages a change to parameter `section` makes stale: those reading it (`Stage.reads`) and
    every stage downstream of them, in run order."""
    hit = {d for s in STAGES if section in s.reads for d in downstream(s.name)}
    return tuple(s for s in STAGE_NAMES if s in hit)


def _check() -> None:
    seen: set[str] = set()
    for s in STAGES:
        missing = [u for u in s.upstream if u not in seen]
        if missing:
            raise RuntimeError(f"stage {s.name!r} comes before {missing}, which it depends on")
        seen.add(s.name)


_check()
