"""The matching stage: the most similar image pairs, ORB matches and 3-D tie points."""

from __future__ import annotations

from ..coarse.matching import MatchResult, match_sequences
from ..coarse.sequences import ImageSequence
from ..stage import Stage, StageContext, StageResult
from .common import pair_label, scan_of


def run(ctx: StageContext) -> list[StageResult | None]:
    def one(k: int) -> MatchResult:
        p = ctx.pairs[k]
        return match_sequences(ctx.item("projection", p.ref, ImageSequence), ctx.item("projection", p.tgt, ImageSequence),
                               scan_of(ctx, p.ref), scan_of(ctx, p.tgt), matching=ctx.params.matching)
    return ctx.each(one, lambda k: pair_label(ctx, k))


STAGE = Stage("matching", "Matching", "The most similar image pairs, ORB matches and 3-D tie points (2.1.3-2.1.4, 4.1).",
              "pair", ("matching",), ("projection",), MatchResult, run)
