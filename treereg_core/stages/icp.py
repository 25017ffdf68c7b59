"""The icp stage: the ICP baseline, started from the coarse transform."""

from __future__ import annotations

from ..coarse.estimate import CoarseResult
from ..evaluate.icp import IcpResult, align_icp, icp_off
from ..stage import Stage, StageContext, StageResult
from .common import pair_label, scan_of


def run(ctx: StageContext) -> list[StageResult | None]:
    def one(k: int) -> IcpResult:
        p, T = ctx.pairs[k], ctx.item("coarse", k, CoarseResult).T_ref_target
        if not ctx.params.icp.enabled:
            return icp_off(T)
        return align_icp(scan_of(ctx, p.ref).points, scan_of(ctx, p.tgt).points, T, icp=ctx.params.icp)
    return ctx.each(one, lambda k: pair_label(ctx, k))


STAGE = Stage("icp", "ICP", "The ICP baseline, started from the coarse transform (3.3).",
              "pair", ("icp",), ("coarse",), IcpResult, run)
