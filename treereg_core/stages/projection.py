"""The projection stage: spherical binary images of each scan, rotated in steps about the tree."""

from __future__ import annotations

from ..coarse.sequences import ImageSequence, build_sequence
from ..stage import Stage, StageContext, StageResult
from .common import scan_of


def run(ctx: StageContext) -> list[StageResult | None]:
    n = len(ctx.scans)
    return ctx.each(lambda i: build_sequence(scan_of(ctx, i), projection=ctx.params.projection, n_scans=n),
                    lambda i: ctx.scans[i].name)


STAGE = Stage("projection", "Projection", "Spherical binary images of each scan, rotated in steps about the tree (2.1.1-2.1.2).",
              "scan", ("projection",), ("prepare",), ImageSequence, run, stop_on_failure=True)
