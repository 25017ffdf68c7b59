"""Fine registration from stem and branch sections (paper 2.2), made to only ever improve a pair.

Each iteration: slice both scans at heights of the reference frame (`slicing`), separate each
slice into arcs in each scan's own angular grid (`arcs`), fit circles and cylinders (`fitting`),
pair the sections of the two scans (`correspondence`) and estimate an update of the transform.
Two estimators (`FineParams.method`):

* ``"ties"`` — the paper: circle centres, and for cylinders the axis point at the slice height
  plus the point one unit along the axis towards +z, as tie points; SVD (or RANSAC) over them.
  Its weaknesses, measured in our feasibility trial: a fit to one scan's partial arc has a centre
  error of several cm, and tie points at equal slice heights never constrain z.
* ``"joint"`` (default, `joint.py`) — a model-to-point adjustment: for every pair of corresponding
  sections one cylinder is fitted to the points of *both* scans at once, while the target's
  points move with the unknown rigid update. Both scans see different sides of a stem, so
  together they cover far more arc than either alone; a shared radius removes the partial-arc
  ambiguity. Oblique branches fix z, sections at several heights fix the tilts. Bad pairs are
  dropped by their residual and by their influence (the one pair the pose hinges on); a prior
  centred on the coarse pose holds what no section constrains.

Pose directions the sections fix only weakly (z along a bare stem; a turn about the stem, which
only a few branches see) are taken from the surfaces (`surface.py`): a point-to-plane refinement
of the whole target against the reference along those directions only, the pairing gate
narrowing from 10 cm to 1.5 cm, pairing only points whose scanner-facing normals agree (the two
sides of a thin branch never pair). With too few sections (a leaf-on crown, a stem thinner than
the point spacing) all six directions come from the surfaces, kept only if they agree better.

Iterate (`max_iterations`, `tolerance_m`): re-slice with the new pose until the update moves the
target by less than the tolerance.

Selection (`select`): the sections model stems as circles and cylinders; a real stem is not round,
which biases their pose by a few hundredths of a degree, and a few wrong sections can lead them
astray. So the final pose is chosen among the coarse pose, the sections' result, and each of these
two polished by the surfaces in all six directions: the one with the lowest trimmed point-to-plane
residual of the target's surface against the reference's (`surface.trimmed_residuals`, which
resolves fractions of a millimetre). If that is the coarse pose, the coarse transform stands and the
message says why. On our simulated scans the surfaces' optimum itself lies 1-3 mm (on a bent tree
1 cm) from the truth, against tenths of a millimetre on stations from real trees: there the
surfaces win, on the simulated scans mostly the sections; the residual cannot protect against
every hundredth of a degree.

Acceptance test (`accept_test`): the pose is also rejected when a second measure — the fraction of
the target's points lying on the reference's surface (`surface_fitness`) — is clearly lower than at
the coarse pose; it cannot rank millimetres but drops clearly when a pose is off by a centimetre.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from . import robust
from .arcs import ArcResult, separate_arcs
from .correspondence import Correspondences, match_sections
from .fitting import Section, check_taper, fit_section, unfitted_section
from .joint import JointFit, adjust_joint
from .params import ArcParams, FineParams, FitParams, Params
from .results import Metric, Progress, no_progress
from .rigid import apply_transform, invert, kabsch
from .scan import Scan
from .slicing import SliceResult, slice_scans
from .surface import Surface, mean_move, pose_update, refine_along, surface_fitness, surface_of, trimmed_residuals

#: Points of the target used to measure how far an update moves it (and for the acceptance measure).
_SAMPLE = 20_000
#: Joint adjustment: a section pair whose RMS exceeds this multiple of the median RMS is dropped.
_TRIM_FACTOR = 2.5
#: The drawn slices and fits are redone at the final pose only if it moved more than this (the app
#: cannot show less, and a pass of slicing and fitting costs a third of the stage).
_REDRAW_M = 0.005
#: Joint adjustment: rounds of dropping bad pairs and adjusting again.
_TRIM_ROUNDS = 6


@dataclass(frozen=True)
class FineResult:
    """Fine registration of one target onto the reference.

    Attributes
    ----------
    ok, message, metrics
        `ok` is True whenever a usable transform is returned (the coarse one when the fine update
        is rejected); `message` says why the fine update was not kept, if it was not.
    T_ref_tgt
        The final 4x4 transform: fine update composed with coarse, or the coarse one if rejected.
    T_coarse
        The transform fine registration started from.
    accepted
        Whether the fine update was kept.
    iterations
        Iterations run (slice, separate, fit, match, estimate).
    updates_m
        Mean displacement of the target's points by each iteration's update.
    measure_coarse, measure_fine
        The acceptance measure (`surface_fitness`: fraction of the target's points on the
        reference's surface) at the coarse and at the fine pose. The selection's trimmed
        residuals of each candidate pose and the candidate chosen are among the `metrics`.
    slices
        The last iteration's slices (heights in the reference frame).
    ref_arcs, tgt_arcs
        Per slice, the arcs of each scan (indices into each scan's own points).
    ref_sections, tgt_sections
        Fitted sections of each scan, in the reference frame (the target's under the final transform).
    correspondences
        Pairs (index into ref_sections, index into tgt_sections).
    tie_points_ref, tie_points_tgt
        K x 3 tie points in the reference frame (the target's under the final transform).
    """

    ok: bool
    message: str
    metrics: tuple[Metric, ...]
    T_ref_tgt: np.ndarray
    T_coarse: np.ndarray
    accepted: bool
    iterations: int
    updates_m: tuple[float, ...]
    measure_coarse: float
    measure_fine: float
    slices: SliceResult | None
    ref_arcs: tuple[ArcResult, ...]
    tgt_arcs: tuple[ArcResult, ...]
    ref_sections: tuple[Section, ...]
    tgt_sections: tuple[Section, ...]
    correspondences: Correspondences | None
    tie_points_ref: np.ndarray
    tie_points_tgt: np.ndarray


@dataclass(frozen=True)
class _Sections:
    """Arcs and fitted sections of one scan, plus each section's point indices into the scan."""

    arcs: tuple[ArcResult, ...]
    sections: tuple[Section, ...]
    members: tuple[np.ndarray, ...]


def _fit_scan_sections(scan: Scan, slice_idx: Sequence[np.ndarray], heights: np.ndarray, T: np.ndarray,
                       ap: ArcParams, fp: FitParams, guide: _Sections | None = None) -> _Sections:
    """Separate every slice of `scan` into arcs and fit each arc (points mapped by `T`).

    With a `guide` (the other scan's sections), an arc is fitted only if its centroid lies within
    reach of a plausible guide section of the same slice (the gate plus three radii: the centroid
    of a visible arc sits up to a radius from the centre): leaves and twigs that have no
    counterpart cost no fit. The others get an unfitted, implausible section.
    """
    arcs: list[ArcResult] = []
    sections: list[Section] = []
    members: list[np.ndarray] = []
    near: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    if guide is not None:
        for s in guide.sections:
            if s.plausible:
                c, r = near.get(s.slice_index, (np.empty((0, 3)), np.empty(0)))
                near[s.slice_index] = (np.vstack([c, s.centre_m]), np.r_[r, s.radius_m])
    for k, (idx, h) in enumerate(zip(slice_idx, heights)):
        ar = separate_arcs(scan, idx, ap)
        arcs.append(ar)
        circle = fp.circle_lowest and k == 0
        for j, members_j in enumerate(ar.arcs()):
            pts = apply_transform(T, scan.points[members_j])
            if guide is not None:
                c, r = near.get(k, (np.empty((0, 3)), np.empty(0)))
                d = np.linalg.norm(c[:, :2] - pts[:, :2].mean(axis=0), axis=1)
                if not np.any(d <= fp.gate_m + 3.0 * r):
                    sections.append(unfitted_section(len(pts), k, j, float(h), "no section of the other scan nearby"))
                    members.append(members_j)
                    continue
            sections.append(fit_section(pts, k, j, float(h), circle, fp))
            members.append(members_j)
    if fp.taper_check:
        sections = check_taper(sections, fp.taper_tolerance, fp.gate_m)
    return _Sections(tuple(arcs), tuple(sections), tuple(members))


def _match(ref: _Sections, tgt: _Sections, fp: FitParams, gate_m: float | None = None) -> Correspondences:
    """Pair plausible sections of the two scans, slice by slice, nearest centres within the gate."""
    ri = np.array([i for i, s in enumerate(ref.sections) if s.plausible], dtype=np.int64)
    ti = np.array([i for i, s in enumerate(tgt.sections) if s.plausible], dtype=np.int64)
    rc = np.array([ref.sections[i].centre_m for i in ri]).reshape(-1, 3)
    tc = np.array([tgt.sections[i].centre_m for i in ti]).reshape(-1, 3)
    rg = np.array([ref.sections[i].slice_index for i in ri])
    tg = np.array([tgt.sections[i].slice_index for i in ti])
    rr = np.array([ref.sections[i].radius_m for i in ri])
    tr = np.array([tgt.sections[i].radius_m for i in ti])
    c = match_sections(rc, tc, fp.gate_m if gate_m is None else gate_m, rg, tg, rr, tr, fp.max_radius_ratio)
    if c.ok:
        c = Correspondences(c.ok, c.message, c.metrics, np.c_[ri[c.pairs[:, 0]], ti[c.pairs[:, 1]]], c.distances_m)
    return c


def _tie_points(s: Section) -> np.ndarray:
    """Paper 2.2.3: a circle's centre; a cylinder's axis point and the point one unit further towards +z."""
    if s.kind == "circle":
        return s.centre_m[None, :]
    return np.vstack([s.centre_m, s.centre_m + s.axis])


def _ties(ref: _Sections, tgt: _Sections, corr: Correspondences) -> tuple[np.ndarray, np.ndarray]:
    a, b = [], []
    for i, j in corr.pairs:
        ta, tb = _tie_points(ref.sections[i]), _tie_points(tgt.sections[j])
        n = min(len(ta), len(tb))
        a.append(ta[:n])
        b.append(tb[:n])
    return (np.vstack(a), np.vstack(b)) if a else (np.empty((0, 3)), np.empty((0, 3)))


def _estimate_ties(ref: _Sections, tgt: _Sections, corr: Correspondences, fp: FineParams) -> tuple[np.ndarray | None, str]:
    """Update mapping the target's tie points (reference frame) onto the reference's: SVD or RANSAC."""
    a, b = _ties(ref, tgt, corr)
    if len(a) < 3 or robust.is_degenerate(b, 6):
        return None, f"only {len(a)} tie points, or all on one line; at least 3 spread points are needed"
    if fp.estimator == "svd":
        return kabsch(b, a), ""
    fit = robust.ransac(b, a, dof=6, inlier_m=fp.inlier_m, iterations=500, seed=0)
    if fit is None or fit.n_inliers < 3:
        return None, f"RANSAC found fewer than 3 tie points agreeing within {fp.inlier_m} m"
    return fit.T, ""


def _subsample(idx: np.ndarray, n: int) -> np.ndarray:
    return idx if len(idx) <= n else idx[np.linspace(0, len(idx) - 1, n).astype(np.int64)]


def _estimate_joint(ref_scan: Scan, tgt_scan: Scan, T: np.ndarray, ref: _Sections, tgt: _Sections,
                    corr: Correspondences, fp: FineParams, loss: str,
                    T_prior: np.ndarray) -> tuple[JointFit | None, str, np.ndarray]:
    """Rigid update from one cylinder per section pair fitted to both scans' points at once.

    Pairs whose cylinder fits badly (RMS above `_TRIM_FACTOR` times the median and above the loss
    scale: a wrong pairing or a mis-separated arc) are dropped and the adjustment is repeated.
    Returns (adjustment or None, message, kept pair mask).
    """
    K = len(corr.pairs)
    pts, sec, mov = [], [], []
    c0 = np.empty((K, 3))
    a0 = np.empty((K, 3))
    r0 = np.empty(K)
    for k, (i, j) in enumerate(corr.pairs):
        si, sj = ref.sections[i], tgt.sections[j]
        p = ref_scan.points[_subsample(ref.members[i], fp.max_section_points)]
        q = apply_transform(T, tgt_scan.points[_subsample(tgt.members[j], fp.max_section_points)])
        pts += [p, q]
        sec.append(np.full(len(p) + len(q), k))
        mov += [np.zeros(len(p), dtype=bool), np.ones(len(q), dtype=bool)]
        a0[k] = si.axis / np.linalg.norm(si.axis)
        c0[k] = (si.centre_m + sj.centre_m) / 2.0
        r0[k] = (si.radius_m + sj.radius_m) / 2.0
    P, S, M = np.vstack(pts), np.concatenate(sec), np.concatenate(mov)
    keep = np.ones(K, dtype=bool)
    for _ in range(_TRIM_ROUNDS):
        idx = np.flatnonzero(keep[S])
        remap = np.cumsum(keep) - 1
        fit = adjust_joint(P[idx], remap[S[idx]], M[idx], c0[keep], a0[keep], r0[keep], fp.loss_scale_m,
                           fp.prior_m, fp.prior_deg, loss, fp.max_direction_sigma_m, T @ invert(T_prior),
                           fp.max_solver_iterations)
        bad = fit.rms_m > max(_TRIM_FACTOR * float(np.median(fit.rms_m)), fp.loss_scale_m)
        if fp.influence_factor is not None and len(fit.influence_m) > 2:
            # One wrong pair can bend a direction only a few branches fix while fitting well
            # itself; it then stands out as the pair the solution hinges on.
            order = np.argsort(fit.influence_m)
            worst, second = fit.influence_m[order[-1]], fit.influence_m[order[-2]]
            if worst > max(fp.influence_min_m, fp.influence_factor * second):
                bad[order[-1]] = True
        if not bad.any() or keep.sum() - bad.sum() < fp.min_pairs:
            break
        keep[np.flatnonzero(keep)[bad]] = False
    if not np.isfinite(fit.U).all():
        return None, "the joint section adjustment diverged", keep
    return fit, "", keep


#: Surface refinement: pairing gates (m), widest first, each run for `_GATE_ITERATIONS`, then the
#: final narrow gate (`FineParams.surface_gate_m`) for `FineParams.surface_iterations`. Directions
#: the sections leave weak still carry the coarse error, centimetres: a narrow gate alone would
#: never see it.
_GATES_M = (0.1, 0.05, 0.03)
_GATE_ITERATIONS = 10


def _from_surfaces(ref_surf: Surface, tgt_surf: Surface, T: np.ndarray, centre: np.ndarray, B: np.ndarray,
                   fp: FineParams) -> np.ndarray:
    """`T` refined point-to-plane along the pose directions `B` only, the pairing gate narrowing."""
    for gate in _GATES_M + (fp.surface_gate_m,):
        final = gate == fp.surface_gate_m
        y = refine_along(ref_surf, tgt_surf, T, centre, B, max(gate, fp.surface_gate_m),
                         max(fp.loss_scale_m, gate / 4), fp.surface_iterations if final else _GATE_ITERATIONS)
        T = pose_update(B @ y, centre) @ T
    return T


def _weak_from_surfaces(ref_surf: Surface, tgt_surf: Surface, T: np.ndarray, joint: JointFit,
                        fp: FineParams) -> tuple[np.ndarray, int]:
    """The pose directions the sections fix only weakly, taken from the surfaces instead.

    Weak: a noise std above `fp.surface_sigma_m` (z along a bare stem; a turn about the stem that
    only a few branches see). With `fp.surface_polish`, all six directions come from the surfaces,
    started where the sections put the target. Returns the transform and how many directions came
    from the surfaces.
    """
    B = np.eye(6) if fp.surface_polish else joint.weak_basis(fp.loss_scale_m, fp.surface_sigma_m)[0]
    if not B.shape[1]:
        return T, 0
    if fp.surface_polish:
        T = pose_update(B @ refine_along(ref_surf, tgt_surf, T, joint.centre_m, B, fp.surface_gate_m,
                                         fp.loss_scale_m, fp.surface_iterations), joint.centre_m) @ T
        return T, 6
    return _from_surfaces(ref_surf, tgt_surf, T, joint.centre_m, B, fp), int(B.shape[1])


def _select(ref_surf: Surface, tgt_surf: Surface, T0: np.ndarray, T: np.ndarray, label: str, fp: FineParams
            ) -> tuple[np.ndarray, str, np.ndarray]:
    """The final pose: of the coarse one, `T` and (for a sections' result) `T` polished by the
    surfaces in all six directions, the one with the lowest trimmed point-to-plane residual.

    The sections model stems as cylinders; a real stem is not round, which biases them by a few
    hundredths of a degree, while the surfaces carry no model. Either can be the better one; the
    residual (`trimmed_residuals`) tells them apart, and refuses an update that does not lower it.
    When too few surface pairs exist to measure, `T` stands; a candidate with far fewer surface
    pairs than the others (far off) is never chosen. Returns (pose, its label, the residuals of
    coarse, `T`, `T` polished and coarse polished: NaN where not computed, inf where far off).
    """
    poses, labels = [T0, T], ["coarse", label]
    if label == "sections":
        poses.append(_polish(ref_surf, tgt_surf, T, fp))
        labels.append("sections, polished by the surfaces")
        if fp.select_coarse_polish:
            # Sections that went astray (too few, a fork taken for a stem) leave the coarse pose
            # as the only good start.
            poses.append(_polish(ref_surf, tgt_surf, T0, fp))
            labels.append("coarse, polished by the surfaces")
    r = trimmed_residuals(ref_surf, tgt_surf, poses, fp.measure_gate_m, fp.select_trim)
    r4 = np.r_[r, np.full(4 - len(r), np.nan)]
    if not np.isfinite(r).any():
        return T, label, r4
    k = int(np.argmin(r))
    return poses[k], labels[k], r4


def _polish(ref_surf: Surface, tgt_surf: Surface, T: np.ndarray, fp: FineParams) -> np.ndarray:
    """`T` refined point-to-plane in all six directions at the final (narrow) gate."""
    c = apply_transform(T, tgt_surf.points).mean(axis=0)
    y = refine_along(ref_surf, tgt_surf, T, c, np.eye(6), fp.surface_gate_m, fp.loss_scale_m, fp.surface_iterations,
                     fp.polish_tolerance_m)
    return pose_update(y, c) @ T


def register_fine(ref: Scan, tgt: Scan, T_coarse: np.ndarray, params: Params,
                  progress: Progress | None = None) -> FineResult:
    """Refine the coarse transform of `tgt` onto `ref` from stem and branch sections.

    Parameters
    ----------
    ref, tgt
        Reference and target scans (each in its scanner frame).
    T_coarse
        The coarse 4x4 T_ref_tgt.
    params
        Uses the sections slicing, arcs, fitting and fine.
    progress
        Optional progress callback.

    Returns
    -------
    FineResult
        Final transform, whether the fine update was accepted and why not, and the last
        iteration's slices, arcs, fits, correspondences and tie points for drawing.
    """
    progress = progress or no_progress
    fp, sp, ap, fitp = params.fine, params.slicing, params.arcs, params.fitting
    T0 = np.asarray(T_coarse, dtype=float)
    if T0.shape != (4, 4) or not np.isfinite(T0).all():
        return _failed(T0, "the coarse transform is missing or not finite; run coarse registration first")
    rng = np.random.default_rng(0)
    sample = tgt.points if tgt.n_points <= _SAMPLE else tgt.points[rng.choice(tgt.n_points, _SAMPLE, replace=False)]
    T = T0.copy()
    updates: list[float] = []
    ref_secs: _Sections | None = None
    joint: JointFit | None = None
    drawn: tuple | None = None
    note = ""
    it = 0
    for it in range(1, fp.max_iterations + 1):
        progress((it - 1) / (fp.max_iterations + 1), f"iteration {it}: slicing and fitting")
        sl = slice_scans(ref, tgt, T, sp)
        if ref_secs is None:  # reference slices never move: fit them once
            ref_secs = _fit_scan_sections(ref, sl.ref_indices, sl.heights_m, np.eye(4), ap, fitp)
        tgt_secs = _fit_scan_sections(tgt, sl.tgt_indices, sl.heights_m, T, ap, fitp, ref_secs)
        corr = _match(ref_secs, tgt_secs, fitp)
        drawn = (T, sl, tgt_secs, corr)
        if it > 1 and corr.ok and fp.gate_factor is not None:
            # Once the pose is close, right pairs sit far closer than the coarse gate: a pair much
            # farther apart than the median (a fork mistaken for a stem) is dropped.
            corr = _match(ref_secs, tgt_secs, fitp, max(fp.min_gate_m, fp.gate_factor * float(np.median(corr.distances_m))))
        if not sl.ok or not corr.ok or len(corr.pairs) < fp.min_pairs:
            note = (sl.message if not sl.ok else
                    f"only {len(corr.pairs)} corresponding sections (fine.min_pairs = {fp.min_pairs})")
            it -= 1
            break
        if fp.method == "ties":
            U, note = _estimate_ties(ref_secs, tgt_secs, corr, fp)
        else:
            joint, note, _ = _estimate_joint(ref, tgt, T, ref_secs, tgt_secs, corr, fp,
                                             "soft_l1" if it == 1 else fp.refine_loss, T0)
            U = None if joint is None else joint.U
        if U is None:
            it -= 1
            break
        move = mean_move(U, apply_transform(T, sample))
        updates.append(move)
        T = U @ T
        if move < fp.tolerance_m:
            break
    progress(fp.max_iterations / (fp.max_iterations + 1), "acceptance test")
    ref_surf = surface_of(ref.points, fp.measure_voxel_m)
    tgt_surf = surface_of(tgt.points, fp.measure_voxel_m, _SAMPLE)
    from_surface = 0
    if joint is not None and updates and fp.surface_refine:
        T, from_surface = _weak_from_surfaces(ref_surf, tgt_surf, T, joint, fp)
    fallback = not updates and fp.method == "joint" and fp.surface_fallback
    if fallback:
        # Too few sections (a leaf-on crown, a stem too thin for the point spacing): align the
        # surfaces instead, gate narrowing from the coarse error down; the acceptance test guards it.
        T = _from_surfaces(ref_surf, tgt_surf, T0, apply_transform(T0, tgt_surf.points).mean(axis=0), np.eye(6), fp)
        updates.append(mean_move(T @ invert(T0), apply_transform(T0, sample)))
        from_surface = 6
    chosen, residuals = ("surfaces" if fallback else "sections"), np.full(4, np.nan)
    if updates and fp.method == "joint" and fp.select:
        T, chosen, residuals = _select(ref_surf, tgt_surf, T0, T, chosen, fp)
        from_surface = 6 if chosen.endswith("by the surfaces") else from_surface
    m0 = surface_fitness(ref_surf, tgt_surf, T0, fp.measure_gate_m, fp.measure_tolerance_m)
    m1 = surface_fitness(ref_surf, tgt_surf, T, fp.measure_gate_m, fp.measure_tolerance_m) if updates else m0
    accepted = bool(updates)
    message = f"{note}; aligned by the surfaces instead of sections" if fallback else ""
    if not updates:
        message = f"fine registration found nothing to improve ({note}); kept the coarse transform"
    elif chosen == "coarse":
        accepted = False
        message = (f"fine registration did not improve the alignment ({note + '; ' if fallback else ''}trimmed "
                   f"point-to-plane residual {1000 * residuals[0]:.2f} mm at coarse, "
                   f"{1000 * np.nanmin(residuals[1:]):.2f} mm after fine); kept the coarse transform")
    elif fallback and not m1 > m0:
        # Surfaces alone must show a gain: they have no sections to vouch for them.
        accepted = False
        message = (f"fine registration found nothing to improve ({note}; aligning the surfaces did not raise "
                   f"their agreement, {m0:.1%} -> {m1:.1%}); kept the coarse transform")
    elif fp.accept_test and m1 < m0 - fp.accept_margin:
        accepted = False
        message = (f"{message + '; ' if message else ''}the fine update made the alignment worse (surface "
                   f"agreement {m0:.1%} of the target's points at coarse, {m1:.1%} after fine); kept the coarse transform")
    if not accepted:
        T = T0.copy()
    # What the app draws: slices, arcs, fits and ties at the pose finally returned (the last
    # iteration's, unless the pose has moved since by more than the tolerance).
    if drawn is None or mean_move(T @ invert(drawn[0]), apply_transform(drawn[0], sample)) > max(fp.tolerance_m, _REDRAW_M):
        sl = slice_scans(ref, tgt, T, sp)
        if ref_secs is None:
            ref_secs = _fit_scan_sections(ref, sl.ref_indices, sl.heights_m, np.eye(4), ap, fitp)
        tgt_secs = _fit_scan_sections(tgt, sl.tgt_indices, sl.heights_m, T, ap, fitp, ref_secs)
        corr = _match(ref_secs, tgt_secs, fitp)
    else:
        _, sl, tgt_secs, corr = drawn
    ties_r, ties_t = _ties(ref_secs, tgt_secs, corr) if corr.ok else (np.empty((0, 3)), np.empty((0, 3)))
    metrics = (
        Metric("fine accepted", "", "yes" if accepted else "no"),
        Metric("fine iterations", "", it),
        Metric("pose directions taken from the surfaces", "", from_surface),
        Metric("fine update (last iteration)", "m", updates[-1] if updates else 0.0),
        Metric("corresponding sections", "", int(len(corr.pairs))),
        Metric("surface agreement, coarse", "", m0),
        Metric("surface agreement, fine", "", m1),
        Metric("final pose from", "", chosen if accepted else "coarse"),
        Metric("surface residual (trimmed), coarse", "m", float(residuals[0])),
        Metric("surface residual (trimmed), sections", "m", float(residuals[1])),
        Metric("surface residual (trimmed), polished", "m", float(residuals[2])),
        Metric("surface residual (trimmed), coarse polished", "m", float(residuals[3])),
    )
    progress(1.0, "done")
    return FineResult(True, message, metrics, T, T0, accepted, it, tuple(updates), m0, m1, sl,
                      ref_secs.arcs, tgt_secs.arcs, ref_secs.sections, tgt_secs.sections, corr,
                      ties_r, ties_t)


def skipped_fine(T0: np.ndarray, message: str) -> FineResult:
    """The FineResult of a pair the fine stage did not run on (e.g. its coarse stage failed)."""
    return _failed(T0, message)


def _failed(T0: np.ndarray, message: str) -> FineResult:
    e = np.empty((0, 3))
    return FineResult(False, message, (Metric("fine accepted", "", "no"),), T0, T0, False, 0, (), np.nan, np.nan,
                      None, (), (), (), (), None, e, e)
