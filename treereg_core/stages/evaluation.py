"""The evaluation stage: the paper's branch-centre error of coarse, fine and ICP, and errors against truth."""

from __future__ import annotations

from ..coarse.estimate import CoarseResult
from ..evaluate.branches import find_branches
from ..evaluate.icp import IcpResult
from ..evaluate.report import PairReport, evaluate_registration
from ..fine.fitting import CylinderFit
from ..fine.pose import FineResult
from ..geometry.rigid import invert
from ..prepare.level import as_levelled
from ..stage import Stage, StageContext, StageResult
from .common import pair_label, prepared, scan_of


def run(ctx: StageContext) -> list[StageResult | None]:
    branches: dict[int, list[CylinderFit]] = {}  # a reference's branches: found once for all its pairs and transforms

    def one(k: int) -> PairReport:
        p = ctx.pairs[k]
        ref, tgt = scan_of(ctx, p.ref), scan_of(ctx, p.tgt)
        if p.ref not in branches:
            branches[p.ref] = find_branches(ref, evaluation=ctx.params.evaluation)
        T_true = None
        if ctx.truth and tgt.name in ctx.truth and ref.name in ctx.truth:
            # The truth is of the scans as given; every stage's transform of the levelled ones.
            T_true = as_levelled(invert(ctx.truth[ref.name]) @ ctx.truth[tgt.name], prepared(ctx, p.ref).T_level,
                                 prepared(ctx, p.tgt).T_level)
        return evaluate_registration(ref, tgt, ctx.item("coarse", k, CoarseResult).T_ref_target,
                                     ctx.item("fine", k, FineResult).T_ref_target,
                                     _icp_result(ctx, k), evaluation=ctx.params.evaluation,
                                     T_true=T_true, branches=branches[p.ref])
    return ctx.each(one, lambda k: pair_label(ctx, k))


def _icp_result(ctx: StageContext, k: int) -> IcpResult | None:
    """ICP's result even when it failed (it then keeps its start, which is still worth evaluating)."""
    out = ctx.outputs.get("icp")
    item = out.items[k] if out is not None and k < len(out.items) else None
    return item if isinstance(item, IcpResult) else None


STAGE = Stage("evaluation", "Result", "The paper's branch-centre error (eq. 8) of coarse, fine and ICP, and errors against truth.",
              "pair", ("evaluation",), ("coarse", "fine"), PairReport, run, uses=("icp",))
