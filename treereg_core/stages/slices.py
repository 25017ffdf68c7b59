"""The slices stage: both scans cut into thin horizontal slices at the start pose (the first step
of `fine.sections.fit_at_pose`)."""

from __future__ import annotations

from ..fine.slicing import SliceResult
from ..stage import Stage, StageContext, StageResult
from .common import pair_label, pose_fit


def run(ctx: StageContext) -> list[StageResult | None]:
    return ctx.each(lambda k: pose_fit(ctx, k, until="slices").slices, lambda k: pair_label(ctx, k))


STAGE = Stage("slices", "Slices", "Both scans cut into thin horizontal slices at the coarse pose (2.2.1).",
              "pair", ("slices",), ("hypotheses",), SliceResult, run)
