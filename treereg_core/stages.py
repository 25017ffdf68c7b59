"""The registry of stages, in the order they run.

Each entry names its stage, the parameter sections it reads, the stages it depends on, its result
type, and a small run function that unpacks the pipeline's state into the stage function's own
arguments (a stage function never sees the whole parameter tree). Adding a stage: write its
module (a function returning a frozen result with `ok`, `message`, `metrics`) and add one entry.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from .coarse.estimate import CoarseResult, estimate_coarse
from .coarse.matching import MatchResult, match_sequences
from .coarse.sequences import ImageSequence, build_sequence
from .evaluate.branches import find_branches
from .evaluate.icp import IcpResult, align_icp, icp_off
from .evaluate.report import PairReport, evaluate_registration
from .fine.arcs import SliceArcs, separate_scan_slices, separate_slices
from .fine.pose import FINE_SECTIONS, FineResult, FineStart, register_fine
from .fine.sections import SectionsResult, fit_scan_sections, fit_sections
from .fine.slicing import SliceResult, slice_scans
from .geometry.rigid import invert
from .prepare.ground import PreparedScan, prepare_scan
from .prepare.resolution import working_resolution
from .scan import Scan
from .stage import Stage, StageContext


def _scan(ctx: StageContext, i: int) -> Scan:
    """Scan `i` as prepared (ground removed, cropped): what every stage after preparation uses."""
    return ctx.item("prepare", i).scan


def _label(ctx: StageContext, k: int) -> str:
    p = ctx.pairs[k]
    return f"{ctx.scans[p.tgt].name} -> {ctx.scans[p.ref].name}"


def _run_prepare(ctx: StageContext) -> list[Any]:
    def one(i: int) -> PreparedScan:
        # First the working resolution (prepare/resolution.py), then ground and crops on it.
        work = working_resolution(ctx.scans[i], resolution=ctx.params.resolution)
        prep = prepare_scan(work.scan, prepare=ctx.params.prepare)
        return replace(prep, metrics=work.metrics + prep.metrics) if work.reduced else prep
    return ctx.each(one, lambda i: ctx.scans[i].name)


def _run_projection(ctx: StageContext) -> list[Any]:
    n = len(ctx.scans)
    return ctx.each(lambda i: build_sequence(_scan(ctx, i), projection=ctx.params.projection, n_scans=n),
                    lambda i: ctx.scans[i].name)


def _run_matching(ctx: StageContext) -> list[Any]:
    def one(k: int) -> MatchResult:
        p = ctx.pairs[k]
        return match_sequences(ctx.item("projection", p.ref), ctx.item("projection", p.tgt), _scan(ctx, p.ref),
                               _scan(ctx, p.tgt), matching=ctx.params.matching)
    return ctx.each(one, lambda k: _label(ctx, k))


def _run_coarse(ctx: StageContext) -> list[Any]:
    return ctx.each(lambda k: estimate_coarse(ctx.item("matching", k), coarse=ctx.params.coarse), lambda k: _label(ctx, k))


def _run_slices(ctx: StageContext) -> list[Any]:
    def one(k: int) -> SliceResult:
        p = ctx.pairs[k]
        return slice_scans(_scan(ctx, p.ref), _scan(ctx, p.tgt), ctx.item("coarse", k).T_ref_target,
                           slicing=ctx.params.slicing)
    return ctx.each(one, lambda k: _label(ctx, k))


def _run_arcs(ctx: StageContext) -> list[Any]:
    shared: dict[int, Any] = {}  # a reference's arcs depend on it alone: shared by its pairs

    def one(k: int) -> SliceArcs:
        p, sl = ctx.pairs[k], ctx.item("slices", k)
        ref = _scan(ctx, p.ref)
        if p.ref not in shared:
            shared[p.ref] = separate_scan_slices(ref, sl.ref_indices, ctx.params.arcs)
        return separate_slices(ref, _scan(ctx, p.tgt), sl.ref_indices, sl.tgt_indices, arcs=ctx.params.arcs,
                               ref_arcs=shared[p.ref])
    return ctx.each(one, lambda k: _label(ctx, k))


def _run_sections(ctx: StageContext) -> list[Any]:
    shared: dict[int, Any] = {}  # as for arcs: one fit of the reference's sections

    def one(k: int) -> SectionsResult:
        p, sl, ar = ctx.pairs[k], ctx.item("slices", k), ctx.item("arcs", k)
        ref = _scan(ctx, p.ref)
        if p.ref not in shared:
            shared[p.ref] = fit_scan_sections(ref, ar.ref, sl.heights_m, np.eye(4), ctx.params.fitting)
        return fit_sections(ref, _scan(ctx, p.tgt), ar.ref, ar.tgt, sl.heights_m, ctx.item("coarse", k).T_ref_target,
                            fitting=ctx.params.fitting, ref_sections=shared[p.ref])
    return ctx.each(one, lambda k: _label(ctx, k))


def _run_fine(ctx: StageContext) -> list[Any]:
    def one(k: int) -> FineResult:
        p = ctx.pairs[k]
        sl = ctx.outputs["slices"].items[k]
        start = FineStart(sl, ctx.ok_item("arcs", k), ctx.ok_item("sections", k)) if isinstance(sl, SliceResult) else None
        return register_fine(_scan(ctx, p.ref), _scan(ctx, p.tgt), ctx.item("coarse", k).T_ref_target, start=start,
                             **ctx.params.pick(*FINE_SECTIONS))
    return ctx.each(one, lambda k: _label(ctx, k))


def _run_icp(ctx: StageContext) -> list[Any]:
    def one(k: int) -> IcpResult:
        p, T = ctx.pairs[k], ctx.item("coarse", k).T_ref_target
        if not ctx.params.icp.enabled:
            return icp_off(T)
        return align_icp(_scan(ctx, p.ref).points, _scan(ctx, p.tgt).points, T, icp=ctx.params.icp)
    return ctx.each(one, lambda k: _label(ctx, k))


def _run_evaluation(ctx: StageContext) -> list[Any]:
    branches: dict[int, Any] = {}  # a reference's branches: found once for all its pairs and transforms

    def one(k: int) -> PairReport:
        p = ctx.pairs[k]
        ref, tgt = _scan(ctx, p.ref), _scan(ctx, p.tgt)
        if p.ref not in branches:
            branches[p.ref] = find_branches(ref, evaluation=ctx.params.evaluation)
        T_true = None
        if ctx.truth and tgt.name in ctx.truth and ref.name in ctx.truth:
            T_true = invert(ctx.truth[ref.name]) @ ctx.truth[tgt.name]
        return evaluate_registration(ref, tgt, ctx.item("coarse", k).T_ref_target, ctx.item("fine", k).T_ref_target,
                                     _icp_result(ctx, k), evaluation=ctx.params.evaluation,
                                     T_true=T_true, branches=branches[p.ref])
    return ctx.each(one, lambda k: _label(ctx, k))


def _icp_result(ctx: StageContext, k: int) -> IcpResult | None:
    """ICP's result even when it failed (it then keeps its start, which is still worth evaluating)."""
    out = ctx.outputs.get("icp")
    item = out.items[k] if out is not None and k < len(out.items) else None
    return item if isinstance(item, IcpResult) else None


STAGES: tuple[Stage, ...] = (
    Stage("prepare", "Scans", "Each station as measured; the ground removed and the scan cropped to the tree.",
          "scan", ("prepare", "resolution"), (), PreparedScan, _run_prepare),
    Stage("projection", "Projection", "Spherical binary images of each scan, rotated in steps about the tree (2.1.1-2.1.2).",
          "scan", ("projection",), ("prepare",), ImageSequence, _run_projection),
    Stage("matching", "Matching", "The most similar image pairs, ORB matches and 3-D tie points (2.1.3-2.1.4, 4.1).",
          "pair", ("matching",), ("projection",), MatchResult, _run_matching),
    Stage("coarse", "Coarse", "The rigid transform that maps the target's tie points onto the reference's (2.1.4).",
          "pair", ("coarse",), ("matching",), CoarseResult, _run_coarse),
    Stage("slices", "Slices", "Both scans cut into thin horizontal slices at the coarse pose (2.2.1).",
          "pair", ("slicing",), ("coarse",), SliceResult, _run_slices),
    Stage("arcs", "Arcs", "Each slice separated into arcs by angular connectivity (2.2.2).",
          "pair", ("arcs",), ("slices",), SliceArcs, _run_arcs),
    Stage("sections", "Fits", "Circles and cylinders fitted to the arcs, and corresponding sections paired (2.2.3, 4.2).",
          "pair", ("fitting",), ("arcs",), SectionsResult, _run_sections),
    Stage("fine", "Fine", "The fine transform from the corresponding sections, iterated and checked against the surfaces.",
          "pair", FINE_SECTIONS, ("coarse",), FineResult, _run_fine, uses=("slices", "arcs", "sections")),
    Stage("icp", "ICP", "The ICP baseline, started from the coarse transform (3.3).",
          "pair", ("icp",), ("coarse",), IcpResult, _run_icp),
    Stage("evaluation", "Result", "The paper's branch-centre error (eq. 8) of coarse, fine and ICP, and errors against truth.",
          "pair", ("evaluation",), ("coarse", "fine"), PairReport, _run_evaluation, uses=("icp",)),
)

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


def _check() -> None:
    seen: set[str] = set()
    for s in STAGES:
        missing = [u for u in s.upstream if u not in seen]
        if missing:
            raise RuntimeError(f"stage {s.name!r} comes before {missing}, which it depends on")
        seen.add(s.name)


_check()
