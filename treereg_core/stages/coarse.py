"""The coarse stage: the rigid transform from the tie points."""

from __future__ import annotations

from ..coarse.estimate import CoarseResult, estimate_coarse
from ..coarse.matching import MatchResult
from ..stage import Stage, StageContext, StageResult
from .common import pair_label


def run(ctx: StageContext) -> list[StageResult | None]:
    return ctx.each(lambda k: estimate_coarse(ctx.item("matching", k, MatchResult), coarse=ctx.params.coarse),
                    lambda k: pair_label(ctx, k))


STAGE = Stage("coarse", "Coarse", "The rigid transform that maps the target's tie points onto the reference's (2.1.4).",
              "pair", ("coarse",), ("matching",), CoarseResult, run)
