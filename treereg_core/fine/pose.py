"""The fine pose (paper 2.2), made to only ever improve a pair.

The slices, arcs and sections stages give the first iteration, at the coarse pose. Each iteration
estimates an update of the transform from the corresponding sections; the next one re-slices
both scans at the new pose (`slices`), separates the arcs (`arcs`), fits them (`sections`) and
pairs them again. Two estimators (`FineParams.method`):

* ``"ties"`` — the paper: circle centres, and for cylinders the axis point at the slice height
  plus the point one unit along the axis towards +z, as tie points; SVD (or RANSAC) over them.
  Its weaknesses, measured in our feasibility trial: a fit to one scan's partial arc has a centre
  error of several cm, and tie points at equal slice heights never constrain z.
* ``"joint"`` (default, `joint.py`, parameters `JointParams`) — a model-to-point adjustment: for every pair of corresponding
  sections one cylinder is fitted to the points of *both* scans at once, while the target's
  points move with the unknown rigid update. Both scans see different sides of a stem, so
  together they cover far more arc than either alone; a shared radius removes the partial-arc
  ambiguity. Oblique branches fix z, sections at several heights fix the tilts. Bad pairs are
  dropped by their residual and by their influence (the one pair the pose hinges on); a prior
  centred on the coarse pose holds what no section constrains.

Pose directions the sections fix only weakly (z along a bare stem; a turn about the stem, which
only a few branches see) are taken from the surfaces (`surface.py`, `SurfaceParams`): a point-to-plane refinement
of the whole target against the reference along those directions only, the pairing gate
narrowing from 10 cm to 1.5 cm, pairing only points whose scanner-facing normals agree (the two
sides of a thin branch never pair). With too few sections (a leaf-on crown, a stem thinner than
the point spacing) all six directions come from the surfaces, kept only if they agree better.

Iterate (`max_iterations`, `tolerance_m`): re-slice with the new pose until the update moves the
target by less than the tolerance.

Selection (`AcceptanceParams.select`): the sections model stems as circles and cylinders; a real stem is not round,
which biases their pose by a few hundredths of a degree, and a few wrong sections can lead them
astray. So the final pose is chosen among the coarse pose, the sections' result, and each of these
two polished by the surfaces in all six directions: the one with the lowest trimmed point-to-plane
residual of the target's surface against the reference's (`surface.trimmed_residuals`, which
resolves fractions of a millimetre). If that is the coarse pose, the coarse transform stands and the
message says why. On our simulated scans the surfaces' optimum itself lies 1-3 mm (on a bent tree
1 cm) from the truth, against tenths of a millimetre on stations from real trees: there the
surfaces win, on the simulated scans mostly the sections; the residual cannot protect against
every hundredth of a degree.

Acceptance test (`AcceptanceParams.test`): the pose is also rejected when a second measure — the fraction of
the target's points lying on the reference's surface (`surface_fitness`) — is clearly lower than at
the coarse pose; it cannot rank millimetres but drops clearly when a pose is off by a centimetre.
"""

from __future__ import annotations

import threading
import weakref
from collections import OrderedDict
from dataclasses import dataclass, field, fields, replace
from typing import Any, Callable

import numpy as np

from .. import parallel
from ..geometry import robust
from ..geometry.rigid import apply_transform, invert, kabsch, rotation_vector
from ..params import (
    AcceptanceParams, ArcParams, FineParams, SectionsParams, JointParams, Params, SlicesParams, SurfaceParams, WindParams,
)
from ..results import Metric, Progress, no_progress
from ..scan import Scan
from .arcs import SliceArcs
from .correspondence import Correspondences
from .joint import JointFit, JointProblem, adjust_joint, section_offsets
from .sections import PoseFit, ScanSections, SectionsResult, fit_at_pose, match_scan_sections, tie_points
from .bend import Bend, cantilever
from .stem import MIN_SLABS, StemProfile, StemTrace, correction, stem_profile, trace_stem
from ..prepare.ground import stem_position
from .slicing import SliceResult, tree_extent
from .surface import (
    Surface, align_narrowing, mean_move, pose_update, refine_along, scan_surface, surface_fitness, surface_of,
    surface_pairs, trimmed_residuals,
)

#: Points of the target used to measure how far an update moves it (and for the acceptance measure).
_SAMPLE = 20_000
#: Joint adjustment: a section pair whose RMS exceeds this multiple of the median RMS is dropped.
_TRIM_FACTOR = 2.5
#: The drawn slices and fits are redone at the final pose only if it moved more than this (the app
#: cannot show less, and a pass of slicing and fitting costs a third of the stage).
_REDRAW_M = 0.005
#: Joint adjustment: rounds of dropping bad pairs and adjusting again.
_TRIM_ROUNDS = 6
#: Wind: solver steps of the probe for a bend at the rigid result.
PROBE_ITERATIONS = 8
#: Wind: iterations the sections get beyond fine.max_iterations when the stem's bend is fitted too.
BEND_EXTRA_ITERATIONS = 3
#: Wind: an update that undoes the last one to within this share of its own size is an oscillation.
OSCILLATION = 0.25
#: A held direction is a turn about the vertical when that makes up this share of it (metres at the lever).
HELD_TURN_SHARE = 0.7
#: Wind: the bend is kept when the target unbent has more of its points on the reference's surface
#: (voxels, pairing gate and point-to-plane tolerance of that measure) than it has rigidly.
DECIDE_VOXEL_M = 0.01
DECIDE_GATE_M = 0.02
DECIDE_TOLERANCE_M = 0.005
#: Wind: stems tilted against each other by more than this at the rigid result are a sign of a moved crown.
TILT_SIGN_DEG = 0.05
#: Wind: rounds of weighing each section by its own offset (see `_estimate_joint`).
_FLUTTER_ROUNDS = 4
#: Wind: a section's own offset at which its weight halves (Cauchy; see `_estimate_joint`).
_FLUTTER_M = 0.005


@dataclass(frozen=True, kw_only=True)
class FineSections:
    """The parameter sections `register_fine` reads: the fine pose's own (`fine`, `joint`,
    `surface`, `acceptance`, `wind`) and how later iterations slice, separate and fit (`slices`,
    `arcs`, `sections`). `FineSections.of(params)` takes them from a `Params`."""

    fine: FineParams
    joint: JointParams
    surface: SurfaceParams
    acceptance: AcceptanceParams
    slices: SlicesParams
    arcs: ArcParams
    sections: SectionsParams
    wind: WindParams = field(default_factory=lambda: WindParams(enabled=False))

    @classmethod
    def of(cls, params: Params) -> "FineSections":
        return cls(**params.pick(*FINE_SECTIONS))


#: The parameter sections `register_fine` reads (the pipeline passes exactly these).
FINE_SECTIONS: tuple[str, ...] = tuple(f.name for f in fields(FineSections))


@dataclass(frozen=True, kw_only=True)
class StemSeeds:
    """Where each scan's own stem stands (x, y in its own frame) when the prepare stage chose it (the
    target's, in a plot): the stem profile traces from there. None: the densest cell of the scan's
    lowest points (one tree in the scan; in a plot on a slope that cell can be a neighbour's)."""

    ref_xy: tuple[float, float] | None = None
    tgt_xy: tuple[float, float] | None = None


NO_SEEDS = StemSeeds()


@dataclass(frozen=True, kw_only=True, eq=False)
class Grounds:
    """The ground each station saw around the tree (the points the prepare stage removed as ground,
    each scan's own frame): it does not move in wind, so with the stem's bend fitted it carries the
    scan's tilt and height (`_anchor`). Empty arrays: no ground seen."""

    ref: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    tgt: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


NO_GROUNDS = Grounds()


@dataclass(frozen=True, kw_only=True)
class FineResult:
    """The fine stage's result for one pair.

    Attributes
    ----------
    ok, message, metrics
        `ok` is True whenever a usable transform is returned (the coarse one when the fine update
        is rejected); `message` says why the fine update was not kept, if it was not.
    T_ref_target
        The final 4x4 transform: the fine update composed with coarse, or the coarse one if rejected.
    T_coarse
        The transform the stage started from.
    accepted
        Whether the fine update was kept.
    iterations
        Iterations that produced an update (slice, separate, fit, match, estimate).
    updates_m
        Mean displacement of the target's points by each update.
    chosen
        Which candidate pose ended the stage ("coarse", "sections", "surfaces", or one of them
        "polished by the surfaces").
    residuals_m
        Trimmed point-to-plane residuals of the candidates: coarse, sections, sections polished,
        coarse polished (NaN where not computed, inf where a pose is far off).
    from_surface
        Pose directions taken from the surfaces (0-6).
    measure_coarse, measure_fine
        The acceptance measure (`surface_fitness`: fraction of the target's points on the
        reference's surface) at the coarse and at the final pose.
    slices, arcs, sections
        The slices, arcs and sections at the final pose (what the app draws for the fine stage).
    bend
        The target's stem bent against the reference's (wind between the stations), fitted with the
        pose; None when the crowns lined up rigidly (or wind is not modelled).
    profile
        The target's stem against the reference's, height by height, at the final pose (not
        unbent): flat at zero where the stem holds, bending off above where the crown moved; None
        when no stem could be traced.
    turn_held
        With a bend: the sections left the turn about the vertical undetermined (a bare stem once
        the fluttering twigs are set aside), so the heading is the start's (the hypotheses stage's):
        the verification must then show the evidence pins it.
    iteration_limit
        The iterations the sections were allowed (`iteration_limit`: more when the stem's bend is fitted).
    stopped_at_limit
        The iterations ran out with the last update still above `fine.tolerance_m` (not converged).
    anchored
        When the crown moved: where the tilt was taken from instead of the crown ("ground": the
        ground both stations saw, the stem's bend refitted under it; "stems": the stem profile of a
        rigid fit whose stems leaned), "" otherwise (`_anchor`).
    hinge_depth_m
        With `anchored`: how far below the lowest stem point traced the stem bends from (the root
        plate; the profile's best fit), 0 otherwise.
    """

    ok: bool
    message: str
    metrics: tuple[Metric, ...]
    T_ref_target: np.ndarray
    T_coarse: np.ndarray
    accepted: bool
    iterations: int
    updates_m: tuple[float, ...]
    chosen: str
    residuals_m: tuple[float, float, float, float]
    from_surface: int
    measure_coarse: float
    measure_fine: float
    slices: SliceResult | None
    arcs: SliceArcs | None
    sections: SectionsResult | None
    bend: Bend | None = None
    profile: StemProfile | None = None
    turn_held: bool = False
    iteration_limit: int = 0
    stopped_at_limit: bool = False
    anchored: str = ""
    hinge_depth_m: float = 0.0


@dataclass(frozen=True, kw_only=True)
class _Iterations:
    """What iterating the sections gave: the pose, each update's size, the last adjustment."""

    T: np.ndarray
    updates_m: tuple[float, ...]
    joint: JointFit | None
    note: str
    last: PoseFit | None
    bend: Bend | None = None


@dataclass(frozen=True, kw_only=True)
class _Run:
    """One pair's fine registration: the scans, the target's points that measure how far an update
    moves it, the parameter sections and where the stems stand."""

    ref: Scan
    tgt: Scan
    sample: np.ndarray
    params: FineSections
    seeds: StemSeeds = NO_SEEDS


@dataclass(frozen=True, kw_only=True)
class _SectionPairs:
    """Corresponding sections to adjust jointly, with the scans whose points they index (`tgt_scan`
    the target as sliced: unbent, with wind)."""

    ref_scan: Scan
    tgt_scan: Scan
    ref: ScanSections
    tgt: ScanSections
    corr: Correspondences


def _refit(run: _Run, T: np.ndarray, known: PoseFit, seen: Scan | None = None) -> PoseFit:
    """Slices, target arcs and target sections again at the pose `T` (the reference's never move:
    taken from `known`). `seen`: the target unbent (`Bend.warp`), sliced and fitted instead of
    `run.tgt` (its arcs stay those of its own grid)."""
    ps = run.params
    known_ref = known.arcs is not None and known.sections is not None
    return fit_at_pose(run.ref, run.tgt, T, slices=ps.slices, arcs=ps.arcs, sections=ps.sections, seen=seen,
                       ref_arcs=known.arcs.ref if known_ref else None,
                       ref_sections=known.sections.ref if known_ref else None)


def _estimate_ties(ref: ScanSections, tgt: ScanSections, corr: Correspondences, fp: FineParams) -> tuple[np.ndarray | None, str]:
    """Update mapping the target's tie points (reference frame) onto the reference's: SVD or RANSAC."""
    a, b = tie_points(ref, tgt, corr)
    if len(a) < 3 or robust.is_degenerate(b, 6):
        return None, f"only {len(a)} tie points, or all on one line; at least 3 spread points are needed"
    if fp.estimator == "svd":
        return kabsch(b, a), ""
    fit = robust.ransac(b, a, robust.RansacSettings(dof=6, inlier_m=fp.inlier_m, iterations=500, seed=0))
    if fit is None or fit.n_inliers < 3:
        return None, f"RANSAC found fewer than 3 tie points agreeing within {fp.inlier_m} m"
    return fit.T, ""


def _subsample(idx: np.ndarray, n: int) -> np.ndarray:
    return idx if len(idx) <= n else idx[np.linspace(0, len(idx) - 1, n).astype(np.int64)]


def _estimate_joint(sp: _SectionPairs, T: np.ndarray, jp: JointParams, *, min_pairs: int, loss: str,
                    T_prior: np.ndarray, bend: Bend | None = None,
                    flutter_rounds: int = _FLUTTER_ROUNDS) -> tuple[JointFit | None, str]:
    """Rigid update from one cylinder per section pair fitted to both scans' points at once (with a
    `bend`, the target's further bend too: `JointFit.bend_m`; `sp.tgt_scan` is then already unbent).

    Pairs whose cylinder fits badly (RMS above `_TRIM_FACTOR` times the median and above the loss
    scale: a wrong pairing or a mis-separated arc) are dropped and the adjustment is repeated.
    """
    ref_scan, tgt_scan, ref, tgt, corr = sp.ref_scan, sp.tgt_scan, sp.ref, sp.tgt, sp.corr
    K = len(corr.pairs)
    pts, sec, mov = [], [], []
    c0 = np.empty((K, 3))
    a0 = np.empty((K, 3))
    r0 = np.empty(K)
    for k, (i, j) in enumerate(corr.pairs):
        si, sj = ref.sections[i], tgt.sections[j]
        p = ref_scan.points[_subsample(ref.members[i], jp.max_section_points)]
        q = apply_transform(T, tgt_scan.points[_subsample(tgt.members[j], jp.max_section_points)])
        pts += [p, q]
        sec.append(np.full(len(p) + len(q), k))
        mov += [np.zeros(len(p), dtype=bool), np.ones(len(q), dtype=bool)]
        a0[k] = si.axis / np.linalg.norm(si.axis)
        c0[k] = (si.centre_m + sj.centre_m) / 2.0
        r0[k] = (si.radius_m + sj.radius_m) / 2.0
    P, S, M = np.vstack(pts), np.concatenate(sec), np.concatenate(mov)
    shape = None if bend is None else bend.shape(P[:, 2])
    keep = np.ones(K, dtype=bool)
    weight = np.ones(K)
    rounds = _TRIM_ROUNDS + (flutter_rounds if bend is not None else 0)
    for rnd in range(rounds):
        idx = np.flatnonzero(keep[S])
        remap = np.cumsum(keep) - 1
        problem = JointProblem(points=P[idx], section=remap[S[idx]], moving=M[idx], centres_m=c0[keep],
                               axes=a0[keep], radii_m=r0[keep], bend_shape=None if shape is None else shape[idx],
                               section_weight=None if bend is None else weight[keep])
        fit = adjust_joint(problem, joint=jp, loss=loss, prior_offset=T @ invert(T_prior))
        bad = fit.rms_m > max(_TRIM_FACTOR * float(np.median(fit.rms_m)), jp.loss_scale_m)
        if jp.influence_factor is not None and len(fit.influence_m) > 2:
            # One wrong pair can bend a direction only a few branches fix while fitting well
            # itself; it then stands out as the pair the solution hinges on.
            order = np.argsort(fit.influence_m)
            worst, second = fit.influence_m[order[-1]], fit.influence_m[order[-2]]
            if worst > max(jp.influence_min_m, jp.influence_factor * second):
                bad[order[-1]] = True
        if bad.any() and keep.sum() - bad.sum() >= min_pairs:
            keep[np.flatnonzero(keep)[bad]] = False
            continue
        if bend is None or not flutter_rounds or rnd >= rounds - 1:
            break
        # Wind: a twig that fluttered on its own fits the shared cylinder well (the radius takes up
        # its offset) yet pulls the pose. Each section's own offset, measured with the radius
        # shared, weighs it down (Cauchy at `flutter_m`); the stem and what moved with it keep theirs.
        moved = P[idx].copy()
        mv = M[idx]
        moved[mv] = apply_transform(fit.U, moved[mv])
        moved[mv, :2] += shape[idx][mv, None] * fit.bend_m[None, :]
        off, _ = section_offsets(moved, remap[S[idx]], mv, fit.points_m, fit.axes, fit.radii_m, jp.loss_scale_m)
        off_m = np.linalg.norm(off, axis=1)
        fit = replace(fit, section_offsets_m=off_m)
        new = 1.0 / (1.0 + (off_m / _FLUTTER_M) ** 2)
        settled = np.abs(new - weight[keep]).max() < 0.05
        weight[keep] = new
        if settled:
            break
    if not np.isfinite(fit.U).all():
        return None, "the joint section adjustment diverged"
    return fit, ""


def _iterate(run: _Run, T0: np.ndarray, start: PoseFit, progress: Progress, *, bend: Bend | None = None,
             max_iterations: int | None = None, T_prior: np.ndarray | None = None) -> _Iterations:
    """Estimate an update from the corresponding sections, re-slice at the new pose, repeat.

    Stops after `fine.max_iterations`, once an update moves the target by less than
    `fine.tolerance_m`, or when an iteration cannot estimate one (too few sections: `note` says why).
    With a `bend` (wind), each iteration also estimates how much more the target's stem is bent, and
    the next one slices and fits the target unbent by all of it (`_Iterations.bend`); `start` is then
    the target unbent by `bend` at `T0`. The adjustment's prior is centred on `T_prior` (default `T0`).
    """
    ref, tgt, sample = run.ref, run.tgt, run.sample
    fp, joint, fit_p = run.params.fine, run.params.joint, run.params.sections
    if start.arcs is None or start.sections is None:
        return _Iterations(T=T0.copy(), updates_m=(), joint=None,
                           note=start.slices.message or "the sections could not be fitted", last=None, bend=bend)
    cur = start
    T = T0.copy()
    updates: list[float] = []
    fit: JointFit | None = None
    last: PoseFit | None = None
    note = ""
    seen = tgt if bend is None or bend.sway_m == 0 else bend.warp(tgt, T0)
    T_prior = T0 if T_prior is None else T_prior
    prev: tuple[np.ndarray, np.ndarray] | None = None  # the last update and bend step (oscillation test)
    n_max = fp.max_iterations if max_iterations is None else max_iterations
    for it in range(1, n_max + 1):
        progress((it - 1) / (fp.max_iterations + 1), f"iteration {it}: slicing and fitting")
        if it > 1:
            seen = tgt if bend is None or bend.sway_m == 0 else bend.warp(tgt, T)
            cur = _refit(run, T, cur, seen)
        if cur.sections is None:  # the slices at the new pose miss the overlap (`slices.message`)
            note = cur.slices.message
            break
        last = cur
        ref_s, tgt_s, corr = cur.sections.ref, cur.sections.tgt, cur.sections.correspondences
        if it > 1 and corr.ok and fp.gate_factor is not None:
            # Once the pose is close, right pairs sit far closer than the coarse gate: a pair much
            # farther apart than the median (a fork mistaken for a stem) is dropped.
            corr = match_scan_sections(ref_s, tgt_s, fit_p,
                                       max(fp.min_gate_m, fp.gate_factor * float(np.median(corr.distances_m))))
        if not corr.ok or len(corr.pairs) < fp.min_pairs:  # (failed slices have no sections: above)
            note = f"only {len(corr.pairs)} corresponding sections (fine.min_pairs = {fp.min_pairs})"
            break
        if fp.method == "ties":
            U, note = _estimate_ties(ref_s, tgt_s, corr, fp)
        else:
            pairs = _SectionPairs(ref_scan=ref, tgt_scan=seen, ref=ref_s, tgt=tgt_s, corr=corr)
            fit, note = _estimate_joint(pairs, T, joint, min_pairs=fp.min_pairs,
                                        loss="soft_l1" if it == 1 else joint.refine_loss, T_prior=T_prior, bend=bend)
            U = None if fit is None else fit.U
        if U is None:
            break
        move = mean_move(U, apply_transform(T, sample))
        step_bend = None
        if bend is not None and fit is not None and fit.bend_m is not None:
            # The top's extra shift counts as a move of the crown (half the stem, on average).
            move = max(move, 0.5 * float(np.hypot(*fit.bend_m)))
            step_bend = np.asarray(fit.bend_m)
            undo = prev is not None and mean_move(U @ prev[0], apply_transform(T, sample)) < OSCILLATION * move \
                and float(np.hypot(*(step_bend + prev[1]))) < OSCILLATION * 2.0 * move
            if undo:
                # Re-slicing flips between two sets of sections, each update undoing the last: settle
                # halfway between the two states and stop.
                U = _half(U, fit.centre_m)
                step_bend = 0.5 * step_bend
                move *= 0.5
            bend = bend.plus(step_bend, fit.bend_std_m)
            if undo:
                updates.append(move)
                T = U @ T
                note = note or "the sections alternated between two sets; settled halfway"
                break
            prev = (U, step_bend)
        updates.append(move)
        T = U @ T
        if move < fp.tolerance_m:
            break
    if bend is not None and fit is not None and fit.held_directions:
        # Directions the sections left undetermined in the end (a turn about a bare stem once the
        # fluttering twigs are set aside) go back to where the iterations started: earlier
        # iterations may have moved them on sections since dropped.
        T = _held_to_prior(T, T_prior, fit)
    return _Iterations(T=T, updates_m=tuple(updates), joint=fit, note=note, last=last, bend=bend)


def _half(U: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Half of the rigid update `U` (half its rotation about `centre`, half its shift)."""
    x = np.r_[rotation_vector(U[:3, :3]), U[:3, :3] @ centre + U[:3, 3] - centre]
    return pose_update(0.5 * x, centre)


def _turn_held(fit: JointFit) -> bool:
    """Whether a direction the adjustment held is mostly a turn about the vertical."""
    D = np.r_[[fit.lever_m] * 3, [1.0] * 3]
    for v in (fit.held_basis[:6] * D[:, None]).T:
        if abs(v[2]) >= HELD_TURN_SHARE * float(np.linalg.norm(v)):
            return True
    return False


def iteration_limit(fine: FineParams, bend: Bend | None) -> int:
    """Iterations the sections get: `fine.max_iterations`, a few more when the stem's bend is fitted
    too (the bend grows from iteration to iteration as more of the crown's sections pair up)."""
    return fine.max_iterations + (BEND_EXTRA_ITERATIONS if bend is not None else 0)


def _held_to_prior(T: np.ndarray, T_prior: np.ndarray, fit: JointFit) -> np.ndarray:
    """`T` with its offset from `T_prior` removed along the adjustment's held directions."""
    c = fit.centre_m
    D = T @ invert(T_prior)
    delta = np.r_[rotation_vector(D[:3, :3]), D[:3, :3] @ c + D[:3, 3] - c]
    B = fit.held_basis[:6]  # the pose part of the held directions (a bend component is no pose)
    y = np.linalg.lstsq(B, delta, rcond=None)[0]
    return pose_update(-(B @ y), c) @ T


def _from_surfaces(ref_surf: Surface, tgt_surf: Surface, T: np.ndarray, centre: np.ndarray, B: np.ndarray,
                   sp: SurfaceParams, loss_scale_m: float) -> np.ndarray:
    """`T` refined point-to-plane along the pose directions `B` only, the pairing gate narrowing."""
    return align_narrowing(ref_surf, tgt_surf, T, centre, B, sp.gate_m, sp.iterations, loss_scale_m)


def _weak_from_surfaces(ref_surf: Surface, tgt_surf: Surface, T: np.ndarray, joint: JointFit,
                        sp: SurfaceParams, loss_scale_m: float) -> tuple[np.ndarray, int]:
    """The pose directions the sections fix only weakly, taken from the surfaces instead.

    Weak: a noise std above `sp.sigma_m` (z along a bare stem; a turn about the stem that only a
    few branches see). With `sp.polish`, all six directions come from the surfaces, started where
    the sections put the target. Returns the transform and how many directions came from the surfaces.
    """
    B = np.eye(6) if sp.polish else joint.weak_basis(loss_scale_m, sp.sigma_m)[0]
    if not B.shape[1]:
        return T, 0
    if sp.polish:
        T = pose_update(B @ refine_along(ref_surf, tgt_surf, T, joint.centre_m, B, sp.gate_m,
                                         loss_scale_m, sp.iterations), joint.centre_m) @ T
        return T, 6
    return _from_surfaces(ref_surf, tgt_surf, T, joint.centre_m, B, sp, loss_scale_m), int(B.shape[1])


def _polish(ref_surf: Surface, tgt_surf: Surface, T: np.ndarray, sp: SurfaceParams, ap: AcceptanceParams,
            loss_scale_m: float) -> np.ndarray:
    """`T` refined point-to-plane in all six directions at the final (narrow) gate. (Started on a
    smaller sample of the target's surface it took a third of the time and ended up to 0.6 mm
    worse on two of 64 pairs: the narrow gate's cost has shallow minima; issue 20.)"""
    c = apply_transform(T, tgt_surf.points).mean(axis=0)
    y = refine_along(ref_surf, tgt_surf, T, c, np.eye(6), sp.gate_m, loss_scale_m, sp.iterations, ap.polish_tolerance_m)
    return pose_update(y, c) @ T


def _select(ref_surf: Surface, tgt_surf: Surface, T0: np.ndarray, T: np.ndarray, label: str, ps: FineSections,
            stems: Callable[[np.ndarray], bool | None] | None = None) -> tuple[np.ndarray, str, np.ndarray]:
    """The final pose: of the coarse one, `T` and (for a sections' result) `T` polished by the
    surfaces in all six directions, the one with the lowest trimmed point-to-plane residual.

    The sections model stems as cylinders; a real stem is not round, which biases them by a few
    hundredths of a degree, while the surfaces carry no model. Either can be the better one; the
    residual (`trimmed_residuals`) tells them apart, and refuses an update that does not lower it.
    When too few surface pairs exist to measure, `T` stands; a candidate with far fewer surface
    pairs than the others (far off) is never chosen, nor one whose stems do not line up (`stems`:
    the stem profile's verdict at a pose) while another's do: the residual of surfaces that only
    partly overlap can rank a pose centimetres off the stem first. Returns (pose, its label, the
    residuals of coarse, `T`, `T` polished and coarse polished: NaN where not computed, inf where far off).
    """
    sp, ap, loss_scale_m = ps.surface, ps.acceptance, ps.joint.loss_scale_m
    poses, labels = [T0, T], ["coarse", label]
    if label == "sections":
        # Sections that went astray (too few, a fork taken for a stem) leave the coarse pose as the
        # only good start: it is polished too. The two polishes side by side (the run's free threads).
        starts = [T, T0] if ap.select_coarse_polish else [T]
        poses += parallel.map(lambda S: _polish(ref_surf, tgt_surf, S, sp, ap, loss_scale_m), starts)
        labels += ["sections, polished by the surfaces", "coarse, polished by the surfaces"][:len(starts)]
    r = trimmed_residuals(ref_surf, tgt_surf, poses, ap.gate_m, ap.select_trim)
    r4 = np.r_[r, np.full(4 - len(r), np.nan)]
    if not np.isfinite(r).any():
        return T, label, r4
    k = int(np.argmin(r))
    if stems is not None and stems(poses[k]) is False:
        lined = [i for i in np.argsort(r) if np.isfinite(r[i]) and stems(poses[i])]
        k = int(lined[0]) if lined else k
    return poses[k], labels[k], r4


def _verdict(n_updates: int, chosen: str, fallback: bool, note: str, residuals: np.ndarray,
             agreement: tuple[float, float], ap: AcceptanceParams, stems_vouch: bool = False) -> tuple[bool, str]:
    """Whether the fine pose is kept, and the sentence that says why not (or what happened).
    `agreement`: the acceptance measure at the coarse and at the fine pose. `stems_vouch`: the stems
    line up at the fine pose and not at the coarse one, which the surface agreement (of two views
    that may barely overlap) does not overrule."""
    m0, m1 = agreement
    if not n_updates:
        return False, f"fine registration found nothing to improve ({note}); kept the coarse transform"
    if chosen == "coarse":
        return False, (f"fine registration did not improve the alignment ({note + '; ' if fallback else ''}trimmed "
                       f"point-to-plane residual {1000 * residuals[0]:.2f} mm at coarse, "
                       f"{1000 * np.nanmin(residuals[1:]):.2f} mm after fine); kept the coarse transform")
    if fallback and not m1 > m0:
        # Surfaces alone must show a gain: they have no sections to vouch for them.
        return False, (f"fine registration found nothing to improve ({note}; aligning the surfaces did not raise "
                       f"their agreement, {m0:.1%} -> {m1:.1%}); kept the coarse transform")
    message = f"{note}; aligned by the surfaces instead of sections" if fallback else ""
    if ap.test and m1 < m0 - ap.margin and not stems_vouch:
        return False, (f"{message + '; ' if message else ''}the fine update made the alignment worse (surface "
                       f"agreement {m0:.1%} of the target's points at coarse, {m1:.1%} after fine); kept the coarse transform")
    return True, message


def register_fine(ref: Scan, tgt: Scan, T_coarse: np.ndarray, *, params: FineSections, start: PoseFit | None = None,
                  seeds: StemSeeds = NO_SEEDS, grounds: Grounds = NO_GROUNDS,
                  progress: Progress | None = None) -> FineResult:
    """Refine the coarse transform of `tgt` onto `ref` from stem and branch sections.

    Parameters
    ----------
    ref, tgt
        Reference and target scans (each in its scanner frame).
    T_coarse
        The coarse 4x4 T_ref_target.
    params
        The parameter sections it reads (`FineSections.of(params)`): the fine pose's own, and how
        later iterations slice, separate and fit at the new pose.
    start
        The first iteration as the slices, arcs and sections stages made it; computed when None.
    seeds
        Where each scan's stem stands, when the prepare stage chose it: the stem profile traces there.
    grounds
        The ground each station saw (its own frame): with the stem's bend fitted, it carries the
        scan's tilt and height (`wind.ground_anchor`).
    progress
        Optional progress callback.

    Returns
    -------
    FineResult
    """
    progress = progress or no_progress
    fine, joint, surface, acceptance, wind = params.fine, params.joint, params.surface, params.acceptance, params.wind
    T0 = np.asarray(T_coarse, dtype=float)
    if T0.shape != (4, 4) or not np.isfinite(T0).all():
        return failed_fine(T0, "the coarse transform is missing or not finite; run coarse registration first")
    if start is None:
        start = fit_at_pose(ref, tgt, T0, slices=params.slices, arcs=params.arcs, sections=params.sections)
    rng = np.random.default_rng(0)
    sample = tgt.points if tgt.n_points <= _SAMPLE else tgt.points[rng.choice(tgt.n_points, _SAMPLE, replace=False)]
    run = _Run(ref=ref, tgt=tgt, sample=sample, params=params, seeds=seeds)
    its = _iterate(run, T0, start, progress)
    if wind.enabled and fine.method == "joint":
        bent = _with_bend(run, T0, its, start, progress)
        if bent is not None:
            its = bent
    bend = its.bend
    T, updates = its.T, list(its.updates_m)
    anchored, hinge = "", 0.0
    seen = tgt if bend is None else bend.warp(tgt, T)
    progress(fine.max_iterations / (fine.max_iterations + 1), "acceptance test")
    # The scans' surfaces (trees, normals) are shared with the hypotheses and verify stages and the
    # scans' other pairs; the target unbent by the wind is its own.
    ref_surf = scan_surface(ref, ref.points, surface.voxel_m)
    tgt_surf = (scan_surface(tgt, tgt.points, surface.voxel_m, _SAMPLE) if seen is tgt
                else surface_of(seen.points, surface.voxel_m, _SAMPLE))
    from_surface = 0
    if its.joint is not None and updates and surface.refine and bend is None:
        T, from_surface = _weak_from_surfaces(ref_surf, tgt_surf, T, its.joint, surface, joint.loss_scale_m)
    fallback = not updates and fine.method == "joint" and surface.fallback
    if fallback:
        # Too few sections (a leaf-on crown, a stem too thin for the point spacing): align the
        # surfaces instead, gate narrowing from the coarse error down; the acceptance test guards it.
        T = _from_surfaces(ref_surf, tgt_surf, T0, apply_transform(T0, tgt_surf.points).mean(axis=0), np.eye(6),
                           surface, joint.loss_scale_m)
        updates.append(mean_move(T @ invert(T0), apply_transform(T0, sample)))
        from_surface = 6
    chosen, residuals = ("surfaces" if fallback else "sections"), np.full(4, np.nan)
    lined: dict[bytes, bool | None] = {}

    def stems(T_: np.ndarray) -> bool | None:
        """The stem profile's verdict at a pose: do the two stems line up there (None: no profile)?"""
        key = np.asarray(T_, dtype=float).tobytes()
        if key not in lined:
            lined[key] = profile_at(ref, tgt, T_, start.slices.z_extent_m, joint.loss_scale_m, seeds).lined_up(
                acceptance.stem_tilt_deg, acceptance.stem_shift_m) if start.slices.ok else None
        return lined[key]
    if updates and fine.method == "joint" and acceptance.select and bend is None:
        T, chosen, residuals = _select(ref_surf, tgt_surf, T0, T, chosen, params, stems)
        from_surface = 6 if chosen.endswith("by the surfaces") else from_surface
    if updates and fine.method == "joint" and wind.enabled and wind.ground_anchor:
        # The pose from what does not move (`_anchor`): when the crown moved, the tilt from the ground
        # (else from the stems, below the crown), the crown's bend refitted under it.
        got = _anchor(run, T, bend, grounds, start.slices.z_extent_m)
        if got is not None:
            T, new_bend, hinge, anchored = got
            if new_bend is not bend:
                bend = new_bend
                seen = tgt if bend is None else bend.warp(tgt, T)
                tgt_surf = (scan_surface(tgt, tgt.points, surface.voxel_m, _SAMPLE) if seen is tgt
                            else surface_of(seen.points, surface.voxel_m, _SAMPLE))
    m0 = surface_fitness(ref_surf, tgt_surf, T0, acceptance.gate_m, acceptance.tolerance_m)
    m1 = surface_fitness(ref_surf, tgt_surf, T, acceptance.gate_m, acceptance.tolerance_m) if updates else m0
    vouch = bool(updates) and m1 < m0 - acceptance.margin and stems(T) is True and stems(T0) is False
    accepted, message = _verdict(len(updates), chosen, fallback, its.note, residuals, (m0, m1), acceptance, vouch)
    if not accepted:
        T = T0.copy()
    if accepted and bend is not None:
        chosen = "sections, with the stem's bend"
    if accepted and anchored:
        chosen += f", tilt from the {anchored}"
    drawn = _drawn_at(run, T, its.last, bend)
    n_iter = len(its.updates_m)
    profile = (profile_at(ref, tgt, T, start.slices.z_extent_m, joint.loss_scale_m, seeds,
                          hinge if anchored and accepted else 0.0) if start.slices.ok else None)
    limit = iteration_limit(fine, its.bend)  # the limit the kept iterations ran under
    bend = bend if accepted else None
    metrics = (
        Metric("fine accepted", "", "yes" if accepted else "no"),
        Metric("fine iterations", "", n_iter),
        Metric("pose directions taken from the surfaces", "", from_surface),
        Metric("fine update (last iteration)", "m", updates[-1] if updates else 0.0),
        Metric("corresponding sections", "", drawn.sections.n_pairs if drawn is not None else 0),
        Metric("surface agreement, coarse", "", m0),
        Metric("surface agreement, fine", "", m1),
        Metric("final pose from", "", chosen if accepted else "coarse"),
        Metric("surface residual (trimmed), coarse", "m", float(residuals[0])),
        Metric("surface residual (trimmed), sections", "m", float(residuals[1])),
        Metric("surface residual (trimmed), polished", "m", float(residuals[2])),
        Metric("surface residual (trimmed), coarse polished", "m", float(residuals[3])),
        Metric("crown moved between the stations (stem top)" if profile is None or profile.crown else
               "stem top off the reference's (a bend of a stem without crown)", "m", bend.sway_m if bend is not None else 0.0),
        Metric("stem stands as the reference's up to (above its base)", "m",
               profile.stable_height_m(wind.stable_tolerance_m) if profile is not None else float("nan")),
        Metric("tilt taken from what does not move (wind)", "",
               {"ground": "the ground", "stems": "the stems"}.get(anchored, "no") if accepted else "no"),
        Metric("stem bends from below its lowest point traced", "m", hinge if anchored and accepted else 0.0),
    )
    progress(1.0, "done")
    return FineResult(
        ok=True, message=message, metrics=metrics, T_ref_target=T, T_coarse=T0, accepted=accepted,
        iterations=n_iter, updates_m=tuple(updates), chosen=chosen if accepted else "coarse",
        residuals_m=tuple(float(r) for r in residuals), from_surface=from_surface, measure_coarse=m0,
        measure_fine=m1, slices=drawn.slices if drawn else start.slices, arcs=drawn.arcs if drawn else None,
        sections=drawn.sections if drawn else None, bend=bend, profile=profile,
        turn_held=bend is not None and its.joint is not None and _turn_held(its.joint),
        iteration_limit=limit, stopped_at_limit=n_iter >= limit and bool(updates) and updates[-1] > fine.tolerance_m,
        anchored=anchored if accepted else "", hinge_depth_m=hinge if anchored and accepted else 0.0,
    )


def _drawn_at(run: _Run, T: np.ndarray, last: PoseFit | None, bend: Bend | None = None) -> PoseFit | None:
    """What the app draws for the fine stage: slices, arcs and fits at the pose finally returned
    (the last iteration's, unless the pose has moved since by more than the tolerance)."""
    if last is None:
        return None
    T_last = last.sections.T_ref_target
    if mean_move(T @ invert(T_last), apply_transform(T_last, run.sample)) > max(run.params.fine.tolerance_m, _REDRAW_M):
        return _refit(run, T, last, None if bend is None else bend.warp(run.tgt, T))
    return last


def _bend_probe(run: _Run, T0: np.ndarray, its: _Iterations) -> tuple[np.ndarray, Bend] | None:
    """How bent the target's stem is against the reference's at the rigid result: one adjustment of
    its last sections with the bend free; the pose and the bend it gives. None when wind is not
    modelled or there is nothing to fit."""
    fine, joint, wind = run.params.fine, run.params.joint, run.params.wind
    if not wind.enabled or fine.method != "joint" or its.last is None or not its.updates_m:
        return None
    cur = its.last
    corr = cur.sections.correspondences
    if not corr.ok or len(corr.pairs) < fine.min_pairs:
        return None
    lo, hi = cur.slices.z_extent_m
    stem = Bend(lo, max(hi - lo, 1e-3))
    # A sign, not the estimate: few solver steps and no rounds of weighing fluttering twigs (the
    # iterations do that).
    quick = replace(joint, max_solver_iterations=min(joint.max_solver_iterations, PROBE_ITERATIONS))
    pairs = _SectionPairs(ref_scan=run.ref, tgt_scan=run.tgt, ref=cur.sections.ref, tgt=cur.sections.tgt, corr=corr)
    fit, _ = _estimate_joint(pairs, its.T, quick, min_pairs=fine.min_pairs, loss=joint.refine_loss, T_prior=T0,
                             bend=stem, flutter_rounds=0)
    if fit is None or fit.bend_m is None:
        return None
    return fit.U @ its.T, stem.plus(fit.bend_m, fit.bend_std_m)


def _with_bend(run: _Run, T0: np.ndarray, rigid: _Iterations, start: PoseFit, progress: Progress) -> _Iterations | None:
    """The sections iterated with the stem's bend, when there is a sign the crown moved (None when
    there is none, or when the bend fitted turns out not to be worth modelling: the rigid result
    then stands, unchanged).

    Signs, any of: the stem profile at the start shows a bend (twice its noise: the profile is
    coarse, the iteration decides); the profile at the rigid result shows the stems tilted against
    each other (a rigid fit lines a moved crown up by tilting the scan); one adjustment of the rigid
    result's sections with the bend free finds one. The iteration starts from the stem profile's
    pose and bend when the profile saw a bend, else from the adjustment's.
    """
    ref, tgt, seeds, joint, wind = run.ref, run.tgt, run.seeds, run.params.joint, run.params.wind
    loose = replace(wind, significance=wind.significance / 1.5)
    prof = profile_at(ref, tgt, T0, start.slices.z_extent_m, joint.loss_scale_m, seeds)
    seen_start = prof.model is not None and _significant(_profile_bend(prof), loose)
    after = profile_at(ref, tgt, rigid.T, start.slices.z_extent_m, joint.loss_scale_m, seeds) if rigid.updates_m else None
    tilted = after is not None and after.model is not None and _tilted(after.model, wind)
    probe = _bend_probe(run, T0, rigid)
    probed = probe is not None and probe[1].significant(wind.min_sway_m / 2.0, wind.significance)
    if not (seen_start or tilted or probed):
        return None
    progress(0.5, "the crown may have moved between the stations: fitting the stem's bend with the pose")
    if prof.model is not None and _profile_bend(prof).sway_m >= wind.min_sway_m:
        T1, bend1 = correction(prof.model, prof.base_xy_m) @ T0, _profile_bend(prof)
    elif probe is not None:
        T1, bend1 = probe
    else:
        T1, bend1 = correction(after.model, after.base_xy_m) @ rigid.T, _profile_bend(after)
    bent = _bent(run, T1, bend1, start)
    if bent is None:
        return None
    # The bend must explain the reference's surface better than the rigid pose does (more of the
    # target's points on it, the target unbent): a bend fitted to a stem traced onto the wrong
    # twigs, or to a crown that did not move, explains less.
    ref_surf = scan_surface(ref, ref.points, DECIDE_VOXEL_M)
    rigid_fit = surface_fitness(ref_surf, scan_surface(tgt, tgt.points, DECIDE_VOXEL_M, _SAMPLE), rigid.T,
                                DECIDE_GATE_M, DECIDE_TOLERANCE_M)
    bent_fit = surface_fitness(ref_surf, surface_of(bent.bend.warp(tgt, bent.T).points, DECIDE_VOXEL_M, _SAMPLE),
                               bent.T, DECIDE_GATE_M, DECIDE_TOLERANCE_M)
    return bent if bent_fit > rigid_fit else None


def _tilted(model: Any, wind: WindParams) -> bool:
    """The stem profile shows the two stems tilted against each other (beyond 3 times its noise and
    `TILT_SIGN_DEG`)."""
    tilt = float(np.degrees(np.hypot(*model.tilt)))
    std = float(np.degrees(np.hypot(*model.std[2:4])))
    return tilt >= max(TILT_SIGN_DEG, wind.significance * std)


def _bent(run: _Run, T1: np.ndarray, bend1: Bend, start: PoseFit) -> _Iterations | None:
    """The sections iterated with the stem's bend, from the pose `T1` and the bend `bend1` (the
    target sliced and fitted unbent from the first iteration on); None when that finds no bend
    worth modelling after all, or nothing to estimate."""
    first = _refit(run, T1, start, bend1.warp(run.tgt, T1))
    bent = _iterate(run, T1, first, no_progress,
                    bend=bend1, max_iterations=iteration_limit(run.params.fine, bend1), T_prior=T1)
    if bent.updates_m and bent.bend is not None and _significant(bent.bend, run.params.wind):
        return bent
    return None


#: Ground anchor: fewest ground points of each station, the voxel its surface is taken at, the pairing
#: gates (widest first) and the iterations of the last.
ANCHOR_MIN_POINTS = 500
ANCHOR_VOXEL_M = 0.02
ANCHOR_GATES_M = (0.05, 0.03)
ANCHOR_GATE_M = 0.015
ANCHOR_ITERATIONS = 30
#: Fewest target ground points paired at the last gate for the ground to be trusted with the tilt.
ANCHOR_MIN_PAIRS = 200
#: The ground may change the scan's tilt by at most this (deg): more is no wind's doing.
ANCHOR_MAX_TILT_DEG = 0.5
#: Depths below the lowest stem point tried for where the stem bends from (m apart).
HINGE_STEP_M = 0.05
#: Robust scale of the hinge fit's residuals (m).
HINGE_SCALE_M = 0.003
#: A rigid fit's stems lean against each other when the lean is this many times its noise (and at
#: least wind.lean_deg): the crown's twigs pulled the tilt. (Measured, bench_wind.py: rigid fits in
#: still air lean at most 0.09 deg and 0.8 times their noise; pulled ones 0.14-0.33 deg, 1.4-4.3 times.)
LEAN_SIGNIFICANCE = 1.25


def _anchor(run: _Run, T: np.ndarray, bend: Bend | None, grounds: Grounds,
            z_extent: tuple[float, float]) -> tuple[np.ndarray, Bend | None, float, str] | None:
    """The pose from what does not move, when the crown moved between the stations (a bend was
    fitted, or the stem profile at `T` shows the two stems leaning against each other: the crown's
    fluttering twigs pulled a rigid fit). Returns (pose, bend, depth the stem bends from below its
    lowest point, "ground" or "stems"), None when nothing moved or nothing steadier is seen.

    * Both stations see the ground: the scan's tilt and height from the ground (point-to-plane,
      three directions), then the stem's horizontal offset and its bend refitted to the stem profile
      with that tilt held (`_hinge_fit`, which also finds how deep below the lowest point traced the
      stem bends from: a bend put 0.3 m too high is fitted 13% short and the rest taken as a tilt of
      ~0.45 deg per metre of sway).
    * No ground, stems that lean (`_leaning`): the tilt and shift the stem profile shows taken out
      (`correction`), its bend kept (a rigid fit's when significant). Stems that do not lean, with a
      bend fitted and no ground: the sections' pose stands (without the ground nothing tells a tilt
      from where the stem bends).
    """
    wind, joint = run.params.wind, run.params.joint
    lo, hi = float(z_extent[0]), float(z_extent[1])
    prof0 = profile_at(run.ref, run.tgt, T, (lo, hi), joint.loss_scale_m, run.seeds)
    leaning = prof0.model is not None and _leaning(prof0.model, wind)
    if bend is None and not leaning:
        return None
    ground = _ground_tilt(run, T, grounds, (lo, hi))
    if ground is not None:
        prof = profile_at(run.ref, run.tgt, ground, (lo, hi), joint.loss_scale_m, run.seeds)
        fit = _hinge_fit(prof, lo, hi, wind.max_hinge_depth_m)
        if fit is None:
            return ground, bend, 0.0, "ground"
        depth, shift, top = fit
        U = np.eye(4)
        U[:2, 3] = -shift
        base = lo - depth
        std = bend.std_m if bend is not None else (float(prof0.model.std[4]), float(prof0.model.std[5])) \
            if prof0.model is not None else (float("nan"), float("nan"))
        new = Bend(base, max(hi - base, 1e-3), (float(top[0]), float(top[1])), std)
        keep = bend is not None or new.significant(wind.min_sway_m, wind.significance)
        if not keep:  # no bend: the stem's shift would be fitted to noise; the ground's tilt and height stand
            return ground, None, 0.0, "ground"
        return U @ ground, new, depth, "ground"
    if not leaning:
        return None
    straight = correction(prof0.model, prof0.base_xy_m) @ T
    pb = _profile_bend(prof0)
    return straight, pb if bend is not None or _significant(pb, wind) else None, 0.0, "stems"


def _leaning(model: Any, wind: WindParams) -> bool:
    """The stem profile shows the target's stem leaning against the reference's: by at least
    `wind.lean_deg` and `LEAN_SIGNIFICANCE` times its noise (a rigid fit's tilt pulled by a moved crown)."""
    tilt = float(np.degrees(np.hypot(*model.tilt)))
    std = float(np.degrees(np.hypot(*model.std[2:4])))
    return tilt >= max(wind.lean_deg, LEAN_SIGNIFICANCE * std)


def _ground_tilt(run: _Run, T: np.ndarray, grounds: Grounds, z_extent: tuple[float, float]) -> np.ndarray | None:
    """`T` with the scan's tilt and height taken from the ground both stations saw (point-to-plane,
    turns about x and y through the stem's base and z; the gate narrowing); None when either station
    saw too little ground, too few of its points pair, or the ground would tilt the scan by more than
    `ANCHOR_MAX_TILT_DEG` (that is no wind's doing)."""
    if min(len(grounds.ref), len(grounds.tgt)) < ANCHOR_MIN_POINTS:
        return None
    ref_g = surface_of(grounds.ref, ANCHOR_VOXEL_M)
    tgt_g = surface_of(grounds.tgt, ANCHOR_VOXEL_M, _SAMPLE)
    lo, hi = z_extent
    centre = np.r_[_ref_trace(run.ref, (float(lo), float(hi)), run.seeds.ref_xy)[0], lo]
    B = np.zeros((6, 3))
    B[0, 0] = B[1, 1] = B[5, 2] = 1.0
    T1 = align_narrowing(ref_g, tgt_g, T, centre, B, ANCHOR_GATE_M, ANCHOR_ITERATIONS, run.params.joint.loss_scale_m,
                         gates_m=ANCHOR_GATES_M)
    n_pairs = len(surface_pairs(ref_g, tgt_g, T1, ANCHOR_GATE_M)[0])
    tilt = float(np.degrees(np.linalg.norm(rotation_vector((T1 @ invert(T))[:3, :3])[:2])))
    if n_pairs < ANCHOR_MIN_PAIRS or tilt > ANCHOR_MAX_TILT_DEG:
        return None
    return T1


def _hinge_fit(prof: StemProfile, lo: float, hi: float, max_depth_m: float) -> tuple[float, np.ndarray, np.ndarray] | None:
    """The stem profile's offsets (target minus reference) explained with the tilt held at zero: a
    shift plus a cantilever bending from each depth below `lo` tried (every `HINGE_STEP_M` down to
    `max_depth_m`); the depth whose fit leaves the least (Cauchy at `HINGE_SCALE_M`). Returns (depth,
    shift x y, the bend's `top_m` x y), None with fewer than `MIN_SLABS` slabs."""
    if prof.n < MIN_SLABS:
        return None
    z, d = prof.heights_m, prof.offsets_m
    sig = np.maximum(prof.std_m, 1e-4)
    best: tuple[float, float, np.ndarray] | None = None
    for depth in np.arange(0.0, max_depth_m + 1e-9, HINGE_STEP_M):
        base = lo - depth
        A = np.c_[np.ones_like(z), cantilever((z - base) / max(hi - base, 1e-3))]
        w = 1.0 / sig ** 2
        for _ in range(6):
            Aw = A * w[:, None]
            x = np.linalg.lstsq(Aw.T @ A, Aw.T @ d, rcond=None)[0]
            res = np.hypot(*(d - A @ x).T)
            w = 1.0 / sig ** 2 / (1.0 + (res / HINGE_SCALE_M) ** 2)
        cost = float(np.sum(np.log1p((res / HINGE_SCALE_M) ** 2)))
        if best is None or cost < best[0] - 1e-9:
            best = (cost, float(depth), x)
    assert best is not None
    _, depth, x = best
    return depth, x[0], -x[1]


_profiles: "weakref.WeakKeyDictionary[Scan, weakref.WeakKeyDictionary]" = weakref.WeakKeyDictionary()
_profiles_lock = threading.Lock()
#: Profiles kept per target scan (the fine stage asks for the same pose several times).
_PROFILES_KEPT = 16


def profile_at(ref: Scan, tgt: Scan, T: np.ndarray, z_extent: tuple[float, float], loss_scale_m: float,
               seeds: StemSeeds = NO_SEEDS, hinge_m: float = 0.0) -> StemProfile:
    """The target's stem profile against the reference's with the target at the pose `T` (each stem
    traced up from its base: its seed, else the densest cell of its own lowest points; the bend
    from `hinge_m` below the base). The reference's trace is made once per reference, and a profile
    once per pose."""
    key = (np.asarray(T, dtype=float).tobytes(), tuple(float(v) for v in z_extent), float(loss_scale_m), seeds,
           float(hinge_m))
    with _profiles_lock:
        per_ref = _profiles.get(tgt)
        found = per_ref.get(ref, {}).get(key) if per_ref is not None else None
    if found is not None:
        return found
    lo, hi = z_extent
    ref_xy, ref_trace = _ref_trace(ref, (float(lo), float(hi)), seeds.ref_xy)
    own = _base_xy(tgt, seeds.tgt_xy, float(tgt.points[:, 2].min()))
    tgt_xy = apply_transform(T, np.r_[own, 0.0][None])[0, :2]
    prof = stem_profile(ref.points, apply_transform(T, tgt.points), ref_xy, tgt_xy, z_extent, loss_scale_m,
                        ref_trace=ref_trace, hinge_m=hinge_m)
    with _profiles_lock:
        kept = _profiles.setdefault(tgt, weakref.WeakKeyDictionary()).setdefault(ref, OrderedDict())
        kept[key] = prof
        while len(kept) > _PROFILES_KEPT:
            kept.popitem(last=False)
    return prof


_ref_traces: "weakref.WeakKeyDictionary[Scan, dict]" = weakref.WeakKeyDictionary()


def _base_xy(scan: Scan, seed: tuple[float, float] | None, base_z: float) -> np.ndarray:
    """Where the scan's stem stands (its frame): the seed, else the densest cell of its points
    lowest above `base_z`."""
    if seed is not None:
        return np.asarray(seed, dtype=float)
    return stem_position(scan.points, scan.points[:, 2] - base_z)


def _ref_trace(ref: Scan, z_extent: tuple[float, float], seed: tuple[float, float] | None = None) -> tuple[np.ndarray, StemTrace]:
    """The reference's stem base and trace for a tree extent, made once per reference scan and seed."""
    key = (z_extent, seed)
    with _profiles_lock:
        found = _ref_traces.get(ref, {}).get(key)
    if found is None:
        xy = _base_xy(ref, seed, z_extent[0])
        found = (xy, trace_stem(ref.points, xy, z_extent[0], z_extent[1]))
        with _profiles_lock:
            _ref_traces.setdefault(ref, {})[key] = found
    return found


def _profile_bend(prof: StemProfile) -> Bend:
    """The bend the stem profile shows, as the fine stage models it."""
    m = prof.model
    return Bend(prof.base_z_m - m.hinge_m, prof.height_m + m.hinge_m, (-float(m.bend_m[0]), -float(m.bend_m[1])),
                (float(m.std[4]), float(m.std[5])))


def _significant(bend: Bend, wind: WindParams) -> bool:
    """The stem's bend is worth modelling: its top moved more than `wind.min_sway_m` and clearly
    more than its own noise."""
    return bend.significant(wind.min_sway_m, wind.significance)


def straightened(ref: Scan, tgt: Scan, T: np.ndarray, loss_scale_m: float, seeds: StemSeeds = NO_SEEDS) -> np.ndarray:
    """`T` with the stem profile's shift and tilt taken out (the stems lined up at the base and
    upright against each other, the bend left to the crown); `T` itself without a profile."""
    prof = profile_at(ref, tgt, T, tree_extent(ref.points[:, 2]), loss_scale_m, seeds)
    return T if prof.model is None else correction(prof.model, prof.base_xy_m) @ T


def profile_bend(ref: Scan, tgt: Scan, T: np.ndarray, wind: WindParams, loss_scale_m: float,
                 seeds: StemSeeds = NO_SEEDS) -> Bend | None:
    """The bend of the target's stem against the reference's that the stem profile at `T` shows,
    when it is significant (None in still air, or when wind is not modelled)."""
    if not wind.enabled:
        return None
    prof = profile_at(ref, tgt, T, tree_extent(ref.points[:, 2]), loss_scale_m, seeds)
    if prof.model is None or not prof.spans_bend:
        return None
    bend = _profile_bend(prof)
    return bend if _significant(bend, wind) else None


def failed_fine(T0: np.ndarray, message: str) -> FineResult:
    """The FineResult of a pair the fine stage cannot run on (`ok` False, the start transform kept)."""
    nan = float("nan")
    return FineResult(ok=False, message=message, metrics=(Metric("fine accepted", "", "no"),), T_ref_target=T0,
                      T_coarse=T0, accepted=False, iterations=0, updates_m=(), chosen="coarse", residuals_m=(nan,) * 4,
                      from_surface=0, measure_coarse=nan, measure_fine=nan, slices=None, arcs=None, sections=None)
