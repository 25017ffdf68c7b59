"""Competing pose hypotheses: which heading (and trunk position) do the scans' surfaces prefer?

A nearly round crown looks alike from several headings: the coarse stage's ties then split between
transforms, and RANSAC's winner can be the wrong one. So the candidates are RANSAC's distinct modes
(other headings, other trunk positions) and, whatever RANSAC found, the best transform turned about
the tree's vertical axis by turns about its axis: the question "would another heading explain the scans
as well?" is always asked. Each candidate goes through a cheap fine step (a point-to-plane
alignment of the target's surface to the reference's, the pairing gate narrowing from 10 cm) and
is scored by the free-space test (`visibility`): points both stations see in the same place count
for it, points placed where the reference saw through count against it. The best candidate is
kept; the margin to the best *distinct* runner-up is the ambiguity evidence.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..fine.surface import Surface, align_narrowing, pose_update, refine_along
from .. import parallel
from ..geometry.rigid import apply_transform, make_transform, rotation_angle_deg, rotation_z
from ..params import HypothesesParams
from ..results import Metric
from .visibility import RangeImage, Visibility, visibility

#: Turns about the tree's axis tried against the coarse transform, whatever RANSAC found: a crown
#: with two-, three- or fourfold symmetry looks alike after one of them.
TURNS_DEG = (90.0, 120.0, 180.0, 240.0, 270.0)
#: Points of the target scored per candidate (a seeded subset: the score needs no more).
SCORE_POINTS = 20_000
#: The cheap fine step's pairing gates before its final one (the full fine stage uses more).
POLISH_GATES_M = (0.1, 0.05)


@dataclass(frozen=True, kw_only=True)
class Candidate:
    """One pose hypothesis, polished by the surfaces, and how the reference's view judges it."""

    label: str
    T_start: np.ndarray
    T_ref_target: np.ndarray
    support: int
    visibility: Visibility
    start_visibility: Visibility | None = None

    def score(self, violation_weight: float) -> float:
        """Points seen alike by both stations, minus the weighted points in the reference's free space."""
        return self.visibility.consistent - violation_weight * self.visibility.violations


@dataclass(frozen=True, kw_only=True)
class HypothesesResult:
    """The hypotheses stage's result for one pair.

    Attributes
    ----------
    ok, message, metrics
        As every stage result; ok whenever candidates could be scored.
    candidates
        Every candidate, best first.
    T_ref_target
        The transform the fine stage starts from: RANSAC's own when it won (unchanged), else the
        winner's polished pose.
    chosen
        The winning candidate's label ("coarse" = RANSAC's best mode).
    chosen_by_hand
        The user picked `chosen` (in the app), whatever the scores say.
    margin
        Consistency of the winner minus that of the best distinct runner-up (1 when none scored).
    runner_up
        The best distinct runner-up's label ("" when none).
    unscored_modes
        RANSAC's further distinct modes left out for too few agreeing ties (`hypotheses.min_mode_support`).
    """

    ok: bool
    message: str
    metrics: tuple[Metric, ...]
    candidates: tuple[Candidate, ...]
    T_ref_target: np.ndarray
    chosen: str
    margin: float
    runner_up: str
    chosen_by_hand: bool = False
    unscored_modes: int = 0


def _score(v: Visibility, p: HypothesesParams) -> float:
    return v.consistent - p.violation_weight * v.violations


def distinct(a: np.ndarray, b: np.ndarray, centre: np.ndarray, deg: float, m: float) -> bool:
    """Two poses of the target are different hypotheses (another heading or another position)."""
    d_pos = float(np.linalg.norm(apply_transform(a, centre[None])[0] - apply_transform(b, centre[None])[0]))
    return rotation_angle_deg(a[:3, :3] @ b[:3, :3].T) >= deg or d_pos >= m


def _scored_mode(support: int, p: HypothesesParams) -> bool:
    """A further RANSAC mode is a hypothesis when enough ties agree with it."""
    return support >= p.min_mode_support


def candidate_starts(T_best: np.ndarray, modes: list[tuple[np.ndarray, int]], tgt_points: np.ndarray,
                     p: HypothesesParams, axis_xy: np.ndarray | None = None) -> list[tuple[str, np.ndarray, int]]:
    """(label, start transform, tie support) of every hypothesis: RANSAC's best, its distinct
    runners-up with enough support, and the best turned about the tree's vertical axis: through the
    target's stem (`axis_xy`, target frame) when one was found, else its centroid. About the stem,
    a turn that maps a symmetric crown onto itself starts where the symmetric pose is; about the
    centroid of the one side a station sees it would start tens of centimetres off."""
    out = [("coarse", np.asarray(T_best, dtype=float), modes[0][1] if modes else 0)]
    for k, (T, n) in enumerate(modes[1:], start=2):
        if _scored_mode(n, p):
            out.append((f"RANSAC mode {k}", np.asarray(T, dtype=float), n))
    c = (apply_transform(T_best, np.array([[axis_xy[0], axis_xy[1], 0.0]]))[0] if axis_xy is not None
         else apply_transform(T_best, tgt_points).mean(axis=0))
    for deg in TURNS_DEG if p.turns else ():
        R = rotation_z(deg)
        out.append((f"turned {deg:.0f}°", make_transform(R, c - R @ c) @ T_best, 0))
    return out


def polish_wide(ref_surf: Surface, tgt_wide: Surface, T0: np.ndarray, centre: np.ndarray,
                p: HypothesesParams) -> np.ndarray:
    """A candidate's start aligned by the surfaces at the wide pairing gates (`POLISH_GATES_M`, the
    gate narrowing), with the target's small sample `tgt_wide`: finding the candidate's basin needs
    no more points."""
    return align_narrowing(ref_surf, tgt_wide, T0, centre, np.eye(6), POLISH_GATES_M[-1], p.polish_iterations,
                           p.loss_scale_m, gates_m=POLISH_GATES_M[:-1], gate_iterations=p.polish_iterations)


def polish_final(ref_surf: Surface, tgt_surf: Surface, T: np.ndarray, centre: np.ndarray,
                 p: HypothesesParams) -> np.ndarray:
    """...then at the final gate (`hypotheses.polish_gate_m`), with `tgt_surf`."""
    gate = p.polish_gate_m
    y = refine_along(ref_surf, tgt_surf, T, centre, np.eye(6), gate, max(p.loss_scale_m, gate / 4), p.polish_iterations)
    return pose_update(y, centre) @ T


# Eleven parameters: the six inputs every candidate is judged on (the reference's view and surface,
# the target's surface and points, RANSAC's pose and modes) and, by keyword, the section and four
# optional modifiers (a hand-picked label, the stem to turn about, a start adjustment for wind, the
# target's small sample for the wide gates).
def score_hypotheses(ref_image: RangeImage, ref_surf: Surface, tgt_surf: Surface, tgt_points: np.ndarray,
                     T_best: np.ndarray, modes: list[tuple[np.ndarray, int]], *,
                     hypotheses: HypothesesParams, choose: str | None = None,
                     axis_xy: np.ndarray | None = None,
                     adjust: Callable[[np.ndarray], np.ndarray] | None = None,
                     tgt_wide: Surface | None = None) -> HypothesesResult:
    """Polish every candidate with the surfaces and score it against the reference's view. `choose`
    names a candidate the user picked: it wins whatever the scores (and says so). `axis_xy`: the
    target's stem (its frame), which the turned candidates turn about. `tgt_wide`: the target's
    smaller sample for the wide pairing gates (`polish_candidate`; default `tgt_surf`).

    A candidate keeps the better of its start and its polished pose: the cheap alignment can drift
    by a few centimetres on a pose that was right already, and must not cost it the comparison.
    `adjust` moves each candidate's start first (with wind: the stem profile's shift and tilt taken
    out, the rigid fit to a moving crown having tilted it).

    Coarse first: every candidate is aligned at the wide gates and scored; only those within
    `hypotheses.finish_within` of the best consistency (and RANSAC's own, and one picked by hand)
    are aligned at the final gate and scored again. The others keep their wide alignment: the
    final gate moves a pose by millimetres, which cannot bring a candidate that far behind to within
    `verify.min_margin` of the best.
    """
    p = hypotheses
    rng = np.random.default_rng(0)
    pts = tgt_points if len(tgt_points) <= SCORE_POINTS else tgt_points[rng.choice(len(tgt_points), SCORE_POINTS, replace=False)]
    centre = pts.mean(axis=0)
    wide = tgt_surf if tgt_wide is None else tgt_wide

    def better(T0: np.ndarray, v0: Visibility, T: np.ndarray) -> tuple[np.ndarray, Visibility, np.ndarray]:
        """The better of a start and its alignment, and the alignment (to go on from)."""
        if not np.isfinite(T).all():
            return T0, v0, T0
        v1 = visibility(ref_image, pts, T, p.tolerance_m)
        return (T0, v0, T) if _score(v0, p) >= _score(v1, p) else (T, v1, T)

    def coarse_step(start: tuple[str, np.ndarray, int]) -> tuple[Candidate, np.ndarray, np.ndarray]:
        label, T0, n = start
        T0 = T0 if adjust is None else adjust(T0)
        c = apply_transform(T0, tgt_surf.points).mean(axis=0)
        v0 = visibility(ref_image, pts, T0, p.tolerance_m)
        T, v, aligned = better(T0, v0, polish_wide(ref_surf, wide, T0, c, p))
        return Candidate(label=label, T_start=T0, T_ref_target=T, support=n, visibility=v, start_visibility=v0), aligned, c

    def final_step(k: int) -> Candidate:
        cand, aligned, c = first[k]
        T, v, _ = better(cand.T_start, cand.start_visibility, polish_final(ref_surf, tgt_surf, aligned, c, p))
        return Candidate(label=cand.label, T_start=cand.T_start, T_ref_target=T, support=cand.support, visibility=v,
                         start_visibility=cand.start_visibility)
    # The candidates side by side on the run's free threads (each is judged on its own).
    first = parallel.map(coarse_step, candidate_starts(T_best, modes, pts, p, axis_xy))
    cons = [c.visibility.consistency for c, _, _ in first]
    top = max((x for x in cons if np.isfinite(x)), default=float("nan"))
    finish = [k for k, (c, _, _) in enumerate(first)
              if c.label in ("coarse", choose) or (np.isfinite(cons[k]) and cons[k] >= top - p.finish_within)]
    done = dict(zip(finish, parallel.map(final_step, finish)))
    cands = [done.get(k, c) for k, (c, _, _) in enumerate(first)]
    # The most consistent hypothesis among those that agree with the reference's view in about as many
    # points as any: a pose that puts the target where the reference saw nothing (a small overlap)
    # proves nothing. (Points in the reference's free space are no overlap: a wrong pose has many.)
    most = max(c.visibility.consistent for c in cands)
    eligible = [c for c in cands if c.visibility.consistent >= max(p.min_overlap_share * most, 1)]
    rank = sorted(eligible, key=lambda c: -c.visibility.consistency) + [c for c in cands if c not in eligible]
    picked = next((c for c in rank if c.label == choose), None)
    if picked is not None:
        rank = [picked] + [c for c in rank if c is not picked]
        eligible = [picked] + [c for c in eligible if c is not picked]
    cands = rank
    best = cands[0]
    rivals = [c for c in rank[1:len(eligible)]
              if distinct(c.T_ref_target, best.T_ref_target, centre, p.distinct_deg, p.distinct_m)]
    runner = rivals[0] if rivals else None
    cons = best.visibility.consistency
    margin = cons - runner.visibility.consistency if runner is not None else 1.0
    margin = float(margin) if np.isfinite(margin) else 0.0
    # RANSAC's own transform goes on unchanged when it wins (the paper's path); another winner
    # starts the fine stage from its polished pose.
    T_start = best.T_start if best.label == "coarse" else best.T_ref_target
    metrics = (
        Metric("hypotheses scored", "", len(cands)),
        Metric("chosen hypothesis", "", best.label),
        Metric("consistency of the chosen", "", float(cons)),
        Metric("best distinct rival", "", runner.label if runner else "none"),
        Metric("consistency of the rival", "", float(runner.visibility.consistency) if runner else float("nan")),
        Metric("ambiguity margin", "", margin),
    )
    coarse_cons = next(c for c in cands if c.label == "coarse").visibility.consistency
    if picked is not None:
        message = f"{best.label} was chosen by hand (consistency {cons:.3f}; RANSAC's transform {coarse_cons:.3f})"
        metrics += (Metric("chosen by hand", "", "yes"),)
    else:
        message = "" if best.label == "coarse" else (
            f"the surfaces prefer {best.label} to RANSAC's transform (consistency {cons:.3f} against {coarse_cons:.3f})")
    return HypothesesResult(ok=True, message=message, metrics=metrics, candidates=tuple(cands), T_ref_target=T_start,
                            chosen=best.label, margin=margin, runner_up=runner.label if runner else "",
                            chosen_by_hand=picked is not None,
                            unscored_modes=sum(not _scored_mode(n, p) for _, n in modes[1:]))


def pass_through(T_coarse: np.ndarray) -> HypothesesResult:
    """Hypotheses switched off (the paper): RANSAC's (or SVD's) transform goes on, no margin measured."""
    return HypothesesResult(ok=True, message="competing hypotheses are not scored (hypotheses.enabled is off)",
                            metrics=(), candidates=(), T_ref_target=np.asarray(T_coarse, dtype=float), chosen="coarse",
                            margin=float("nan"), runner_up="")
