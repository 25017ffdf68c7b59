"""The graph stage: every scan placed onto the reference from the verified pairs, and its verdict."""

from __future__ import annotations

from dataclasses import replace
from typing import Callable

import numpy as np

from ..geometry.rigid import invert, mean_displacement, rotation_error_deg
from ..prepare.level import as_given
from ..prepare.vertical import scan_vertical
from ..params import set_flag
from ..results import Metric
from ..stage import Stage, StageContext, StageResult
from ..verify.evidence import FAILED, OTHER_TREE, VERIFIED, PairVerification
from ..verify.graph import Edge, Placement, edge_weight, place_scans
from .common import prepared, scan_of, station


def run(ctx: StageContext) -> list[StageResult | None]:
    """Every scan placed onto the reference from the verified pairs, jointly (one run for all scans)."""
    ver = ctx.outputs.get("verify")
    edges: list[Edge] = []
    for k, p in enumerate(ctx.pairs):
        it = ver.items[k] if ver is not None else None
        if isinstance(it, PairVerification):
            edges.append(Edge(i=p.ref, j=p.tgt, T=it.T_ref_target, verdict=it.verdict, reasons=it.reasons, hint=it.hint,
                              other_tree=it.other_tree, weight=edge_weight(it.evidence, ctx.params.graph)))
        else:  # the pair failed before verification: no transform
            edges.append(Edge(i=p.ref, j=p.tgt, T=np.eye(4), verdict="failed",
                              reasons=((it.message if it is not None else "") or "not registered",)))
    rng = np.random.default_rng(0)
    samples: dict[int, np.ndarray] = {}
    for i in range(len(ctx.scans)):
        pts = scan_of(ctx, i).points
        samples[i] = pts[rng.choice(len(pts), min(ctx.params.graph.sample_points, len(pts)), replace=False)]
    placed = place_scans(len(ctx.scans), edges, samples, graph=ctx.params.graph, max_loop_m=ctx.params.verify.max_loop_m)
    notes: dict[int, str] = {}

    def vertical(j: int) -> str:
        # Only for scans not verified and their reference: a clean run pays nothing for it.
        if j not in notes:
            notes[j] = scan_vertical(station(ctx, j).points).note
        return notes[j]

    return [_with_truth(ctx, i, _with_step_doubt(ctx, i, _with_vertical(ctx, i, _unprepared(ctx, i, pl), vertical)))
            for i, pl in enumerate(placed)]


def _unprepared(ctx: StageContext, i: int, pl: Placement) -> Placement:
    """A scan that could not be prepared (only ground, nothing left after the crop) failed for that
    reason, said once, with what to do: not as each of its pairs' "not run"."""
    prep = prepared(ctx, i)
    if prep.ok or pl.verdict != FAILED or not prep.reason:
        return pl
    return replace(pl, reasons=(prep.reason,), message=prep.reason, hint=prep.hint)


def _with_vertical(ctx: StageContext, i: int, pl: Placement, vertical: Callable[[int], str]) -> Placement:
    """A scan not verified while its (or the reference's) vertical is not its z (a scanner tilted or
    upside down, a scan exported y-up): every stage takes z as up, so that is the reason to give first,
    not that the scans show different trees."""
    if pl.verdict == VERIFIED:
        return pl
    off = [(ctx.scans[j].name, note) for j in dict.fromkeys((0, i)) if (note := vertical(j))]
    if not off:
        return pl
    why = tuple(f"{name}: {note}" for name, note in off)
    # "It does not show the same tree" rests on a z that is not up: not said.
    reasons = why + tuple(r for r in pl.reasons if OTHER_TREE not in r)
    hint = f"export {' and '.join(name for name, _ in off)} z-up and levelled, then register again"
    if not ctx.params.prepare.level:  # levelling was turned off: it is the first thing to try
        hint = f"let treereg level the scans (prepare.level, {set_flag('prepare.level', True)}), or {hint}"
    return replace(pl, reasons=reasons, message="; ".join(reasons), hint=hint)


def _with_step_doubt(ctx: StageContext, i: int, pl: Placement) -> Placement:
    """A scan left unverified while its (or the reference's) angular step is a doubtful estimate: the
    projection images were drawn at a guessed pixel size, so the step is the first thing to give."""
    if pl.verdict == VERIFIED or ctx.params.prepare.angular_step_deg is not None:
        return pl
    scans = [ctx.scans[j] for j in dict.fromkeys((0, i))]
    doubtful = [(s.name, s.step) for s in scans if s.step is not None and s.step.low]
    if not doubtful:
        return pl
    why = tuple(f"the angular step of {name}, {step.describe()}, is doubtful, so its projection images may "
                "be distorted" for name, step in doubtful)
    hint = "give the instrument's angular steps (--angular-step H V, or prepare.angular_step_deg in the Scans stage)"
    reasons = pl.reasons + why
    return replace(pl, reasons=reasons, message="; ".join(reasons), hint=f"{hint}; {pl.hint}" if pl.hint else hint)


def _with_truth(ctx: StageContext, i: int, pl: Placement) -> Placement:
    """A placement with its error against the truth among its metrics, when the truth is known."""
    ref, scan = ctx.scans[0], ctx.scans[i]
    if not ctx.truth or pl.T_ref_scan is None or scan.name not in ctx.truth or ref.name not in ctx.truth:
        return pl
    T_true = invert(ctx.truth[ref.name]) @ ctx.truth[scan.name]
    # The truth is of the scans as given; the placement of the levelled ones (prepare/level.py).
    T = as_given(pl.T_ref_scan, prepared(ctx, 0).T_level, prepared(ctx, i).T_level)
    rows = (Metric("rotation error against truth", "deg", rotation_error_deg(T, T_true)),
            Metric("mean displacement against truth", "m", mean_displacement(T, T_true, scan.points)))
    return replace(pl, metrics=pl.metrics + rows)


STAGE = Stage("graph", "Placement", "Every scan placed onto the reference from the verified pairs, loops closed, all poses solved together.",
              "scan", ("graph",), (), Placement, run, uses=("verify",),
              # the loop tolerance; whether the angular steps were given (a doubtful estimate is named)
              borrows=("verify", "prepare"))
