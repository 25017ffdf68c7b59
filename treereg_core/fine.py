"""Fine registration from stem and branch sections (paper 2.2), made to only ever improve a pair.

Each iteration: slice both scans at heights of the reference frame (`slicing`), separate each
slice into arcs in each scan's own angular grid (`arcs`), fit circles and cylinders (`fitting`),
pair the sections of the two scans (`correspondence`) and estimate an update of the transform.
Two estimators (`FineParams.method`):

* ``"ties"`` — the paper: circle centres, and for cylinders the axis point at the slice height
  plus the point one unit along the axis towards +z, as tie points; SVD (or RANSAC) over them.
  Its weaknesses, measured in our feasibility trial: a fit to one scan's partial arc has a centre
  error of several cm, and tie points at equal slice heights never constrain z.
* ``"joint"`` (default) — a model-to-point adjustment: for every pair of corresponding sections one
  cylinder is fitted to the points of *both* scans at once, while the target's points move with
  the unknown rigid update. Both scans see different sides of a stem, so together they cover far
  more arc than either alone; a shared radius removes the partial-arc ambiguity. A cylinder only
  constrains motion across its axis, so oblique branches fix z and sections at several heights
  fix the tilts. Directions no section constrains are held at the current pose by a weak prior.

Iterate (`max_iterations`, `tolerance_m`): re-slice with the new pose until the update moves the
target by less than the tolerance. Acceptance test (`accept_test`): the update is kept only when
an independent measure of alignment — the truncated point-to-plane residual of the target's
points against the reference's surface — is lower than at the coarse pose; otherwise the coarse
transform stands and the message says why.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from . import robust
from .arcs import ArcResult, separate_arcs
from .correspondence import Correspondences, match_sections
from .fitting import Section, _basis, check_taper, fit_section
from .icp import NORMAL_K, _skew_rotation, voxel_downsample
from .params import ArcParams, FineParams, FitParams, Params
from .results import Metric, Progress, no_progress
from .rigid import apply_transform, invert, kabsch, make_transform
from .scan import Scan
from .slicing import SliceResult, slice_scans

#: Points of the target used to measure how far an update moves it (and for the acceptance measure).
_SAMPLE = 20_000
#: Surface pairs count only when their scanner-facing normals agree this well (cosine).
_NORMAL_AGREEMENT = 0.5
#: Joint adjustment: a section pair whose RMS exceeds this multiple of the median RMS is dropped.
_TRIM_FACTOR = 2.5
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
    measure_coarse_m, measure_fine_m
        The acceptance measure (RMS of truncated point-to-plane residuals) at the coarse and at the
        fine pose.
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
    measure_coarse_m: float
    measure_fine_m: float
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
                       ap: ArcParams, fp: FitParams) -> _Sections:
    """Separate every slice of `scan` into arcs and fit each arc (points mapped by `T`)."""
    arcs: list[ArcResult] = []
    sections: list[Section] = []
    members: list[np.ndarray] = []
    for k, (idx, h) in enumerate(zip(slice_idx, heights)):
        ar = separate_arcs(scan, idx, ap)
        arcs.append(ar)
        circle = fp.circle_lowest and k == 0
        for j, members_j in enumerate(ar.arcs()):
            pts = apply_transform(T, scan.points[members_j])
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


def _basis_rows(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per row of unit vectors `a` (K x 3), two unit vectors completing it to an orthonormal frame."""
    helper = np.where(np.abs(a[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    e1 = np.cross(a, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(a, e1)


def _rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis times angle, rad) of a rotation matrix."""
    return Rotation.from_matrix(R).as_rotvec()


def _solve_well_determined(S_data: np.ndarray, S_prior: np.ndarray, b: np.ndarray, lever_m: float,
                           sigma_m: float, max_sigma_m: float | None) -> tuple[np.ndarray, int]:
    """Gauss-Newton step of the 6 pose unknowns, restricted to the directions the data determine.

    Rotations are scaled by the lever arm `lever_m` so all six directions are in metres. A direction
    whose noise-propagated standard deviation sigma / sqrt(eigenvalue) exceeds `max_sigma_m` (a
    stem of vertical cylinders says nothing about z, or about a turn about itself) gets no update:
    it stays where coarse put it instead of wandering with noise and model error.
    Returns (step, held directions as a 6 x h basis of the unscaled pose parameters).
    """
    D = np.r_[[lever_m] * 3, [1.0] * 3]
    Sy = S_data / np.outer(D, D)
    lam, V = np.linalg.eigh((Sy + Sy.T) / 2.0)
    if max_sigma_m is None:
        good = np.ones(6, dtype=bool)
    else:
        good = sigma_m / np.sqrt(np.maximum(lam, 1e-300)) <= max_sigma_m
    held = V[:, ~good] / D[:, None]
    if not good.any():
        return np.zeros(6), held
    Vg = V[:, good]
    A = Vg.T @ ((Sy + S_prior / np.outer(D, D)) @ Vg)
    dy = -Vg @ np.linalg.solve(A, Vg.T @ (b / D))
    return dy / D, held


def _robust_weight(res: np.ndarray, scale: float, loss: str) -> np.ndarray:
    """IRLS weight rho'(z), z = (res / scale)^2, of soft-L1 (2 (sqrt(1 + z) - 1)) or Cauchy (ln(1 + z))."""
    z = (res / scale) ** 2
    return 1.0 / np.sqrt(1.0 + z) if loss == "soft_l1" else 1.0 / (1.0 + z)


def _robust_cost(res: np.ndarray, scale: float, loss: str) -> float:
    z = (res / scale) ** 2
    rho = 2.0 * (np.sqrt(1.0 + z) - 1.0) if loss == "soft_l1" else np.log1p(z)
    return float(rho.sum()) * scale ** 2


@dataclass(frozen=True)
class JointFit:
    """Outcome of the joint adjustment: the update and one cylinder per section pair (reference frame)."""

    U: np.ndarray
    points_m: np.ndarray
    axes: np.ndarray
    radii_m: np.ndarray
    rms_m: np.ndarray
    iterations: int
    held_basis: np.ndarray
    centre_m: np.ndarray
    influence_m: np.ndarray
    information: np.ndarray
    lever_m: float

    def weak_basis(self, sigma_m: float, max_sigma_m: float) -> tuple[np.ndarray, np.ndarray]:
        """The pose directions the sections determine worse than `max_sigma_m` (noise std at the
        lever arm, for a residual scale `sigma_m`): a 6 x h basis of the pose parameters, whose
        unit coefficient moves the data by one metre at the lever arm, and each direction's std."""
        D = np.r_[[self.lever_m] * 3, [1.0] * 3]
        lam, V = np.linalg.eigh(self.information / np.outer(D, D))
        std = sigma_m / np.sqrt(np.maximum(lam, 1e-300))
        weak = std > max_sigma_m
        return V[:, weak] / D[:, None], std[weak]

    @property
    def held_directions(self) -> int:
        """Pose directions the sections did not determine (kept at the prior)."""
        return int(self.held_basis.shape[1])


def adjust_joint(points: np.ndarray, section: np.ndarray, moving: np.ndarray, c0: np.ndarray, a0: np.ndarray,
                 r0: np.ndarray, loss_scale_m: float, prior_m: float, prior_deg: float,
                 loss: str = "soft_l1", max_sigma_m: float | None = None, prior_offset: np.ndarray | None = None,
                 max_iterations: int = 30) -> JointFit:
    """Fit one cylinder per section to all its points while the `moving` points follow a rigid update.

    A Gauss-Newton (IRLS, soft-L1 or Cauchy loss) bundle adjustment with an analytic Jacobian. The section
    unknowns (axis point across the axis: 2, axis tilt: 2, radius: 1) are eliminated per section
    (Schur complement of their 5 x 5 blocks), leaving a 6 x 6 system for the update (rotation
    vector about the data centroid, translation); a prior centred on the coarse pose keeps
    directions that the sections hardly constrain near it.

    Parameters
    ----------
    points
        N x 3 points in the reference frame, grouped by section (`section` non-decreasing).
    section
        Section number 0..K-1 of each point; every section must have points.
    moving
        N bools: True for target points (they move with the update).
    c0, a0, r0
        K x 3 axis points, K x 3 unit axes, K radii to start from.
    loss_scale_m, prior_m, prior_deg
        Loss scale; prior standard deviations of the translation and rotation away from the prior pose.
    loss
        "soft_l1" (convex beyond the scale: safe far from the solution) or "cauchy" (redescending:
        a wrong pair's points lose their pull once the right pose is near).
    max_sigma_m
        Pose directions determined worse than this are held (see `_solve_well_determined`).
    prior_offset
        4x4 taking the prior pose of the moving points to the pose they are given in (the fine
        updates so far); None = they are given at the prior pose.

    Returns
    -------
    JointFit
        `U` maps the moving points (as given) to their adjusted position.
    """
    K = len(c0)
    starts = np.flatnonzero(np.r_[True, section[1:] != section[:-1]])
    centre = points.mean(axis=0)
    lever = float(np.sqrt(np.mean(np.sum((points - centre) ** 2, axis=1))))
    held = np.zeros((6, 0))
    mv = np.flatnonzero(moving)
    base = points[mv] - centre
    c, a, r = c0.astype(float).copy(), a0.astype(float).copy(), r0.astype(float).copy()
    R, tau = np.eye(3), np.zeros(3)
    # The pose relative to the prior (coarse) one, in the same parametrisation: rotation about `centre`.
    Rp = np.eye(3) if prior_offset is None else prior_offset[:3, :3]
    tp = np.zeros(3) if prior_offset is None else Rp @ centre + prior_offset[:3, 3] - centre
    prior = (loss_scale_m ** 2) * np.r_[[1 / np.radians(prior_deg) ** 2] * 3, [1 / prior_m ** 2] * 3]
    eye5 = np.eye(5)

    def residuals(R_: np.ndarray, tau_: np.ndarray, c_: np.ndarray, a_: np.ndarray, r_: np.ndarray):
        cur = points.copy()
        cur[mv] = base @ R_.T + centre + tau_
        d = cur - c_[section]
        along = np.einsum("ij,ij->i", d, a_[section])
        perp = d - along[:, None] * a_[section]
        nrm = np.sqrt(np.einsum("ij,ij->i", perp, perp))
        return cur, d, along, perp, nrm, nrm - r_[section]

    def cost(res: np.ndarray, Rt: np.ndarray, t: np.ndarray) -> float:
        return _robust_cost(res, loss_scale_m, loss) + float(prior @ np.r_[_rotvec(Rt), t] ** 2)

    def linearise(cur, along, perp, nrm, res, a):
        """Normal-equation blocks: per section (5 x 5, 5 x 6, 5) and per section's pose part."""
        w = _robust_weight(res, loss_scale_m, loss)
        n = perp / np.maximum(nrm, 1e-12)[:, None]
        e1, e2 = _basis_rows(a)
        ne1 = np.einsum("ij,ij->i", n, e1[section])
        ne2 = np.einsum("ij,ij->i", n, e2[section])
        Js = np.c_[-ne1, -ne2, -along * ne1, -along * ne2, -np.ones(len(res))]
        Jp = np.zeros((len(res), 6))
        Jp[mv, :3] = np.cross(cur[mv] - centre, n[mv])
        Jp[mv, 3:] = n[mv]
        wJs, wJp = Js * w[:, None], Jp * w[:, None]
        Hss = np.add.reduceat(np.einsum("ni,nj->nij", wJs, Js), starts, axis=0)
        Hsp = np.add.reduceat(np.einsum("ni,nj->nij", wJs, Jp), starts, axis=0)
        gs = np.add.reduceat(wJs * res[:, None], starts, axis=0)
        Hpp_k = np.add.reduceat(np.einsum("ni,nj->nij", wJp, Jp), starts, axis=0)
        gp_k = np.add.reduceat(wJp * res[:, None], starts, axis=0)
        # Levenberg damping on the section blocks keeps near-degenerate sections (tiny arcs) finite.
        Hss = Hss + 1e-9 * eye5 + 1e-6 * np.einsum("kii->ki", Hss)[:, :, None] * eye5
        Hinv = np.linalg.inv(Hss)
        HinvHsp = Hinv @ Hsp
        # Each section's contribution to the reduced (pose-only) system, its own unknowns eliminated.
        S_k = Hpp_k - np.einsum("kji,kjl->kil", Hsp, HinvHsp)
        b_k = gp_k - np.einsum("kji,kj->ki", Hsp, np.einsum("kij,kj->ki", Hinv, gs))
        return e1, e2, Hinv, HinvHsp, gs, S_k, b_k

    cur, d, along, perp, nrm, res = residuals(R, tau, c, a, r)
    f = cost(res, Rp, tp)
    it = 0
    for it in range(1, max_iterations + 1):
        e1, e2, Hinv, HinvHsp, gs, S_k, b_k = linearise(cur, along, perp, nrm, res, a)
        S = S_k.sum(axis=0) + np.diag(prior)
        b = b_k.sum(axis=0) + prior * np.r_[_rotvec(Rp), tp]
        dp, held = _solve_well_determined(S - np.diag(prior), np.diag(prior), b, lever, loss_scale_m, max_sigma_m)
        ds = -(np.einsum("kij,kj->ki", Hinv, gs) + HinvHsp @ dp)
        step = 1.0
        for _ in range(8):  # backtracking: IRLS steps on a robust cost can overshoot
            Rd = _skew_rotation(step * dp[:3])
            R_n, tau_n = Rd @ R, Rd @ tau + step * dp[3:]
            Rp_n, tp_n = Rd @ Rp, Rd @ tp + step * dp[3:]
            c_n = c + step * (ds[:, :1] * e1 + ds[:, 1:2] * e2)
            a_n = a + step * (ds[:, 2:3] * e1 + ds[:, 3:4] * e2)
            a_n /= np.linalg.norm(a_n, axis=1, keepdims=True)
            r_n = r + step * ds[:, 4]
            out = residuals(R_n, tau_n, c_n, a_n, r_n)
            f_n = cost(out[-1], Rp_n, tp_n)
            if f_n <= f:
                break
            step /= 2.0
        else:
            break
        R, tau, Rp, tp, c, a, r = R_n, tau_n, Rp_n, tp_n, c_n, a_n, r_n
        cur, d, along, perp, nrm, res = out
        # Converged when the cost stalls or the pose moves by less than about 10 micrometres.
        converged = f - f_n <= 1e-7 * max(f, 1e-12) or (
            np.linalg.norm(step * dp[:3]) * lever < 1e-5 and np.linalg.norm(step * dp[3:]) < 1e-5)
        f = f_n
        if converged:
            break
    counts = np.diff(np.r_[starts, len(res)])
    rms = np.sqrt(np.add.reduceat(res ** 2, starts) / counts)
    # Influence of each section: how far the pose would move without it (linearised at the
    # solution, where the summed gradient vanishes: shift = (S - S_k)^-1 b_k), in metres at the lever.
    # Only directions the sections determine count: in the others the prior alone holds the pose,
    # and any small gradient would look like a huge influence.
    _, _, _, _, _, S_k, b_k = linearise(cur, along, perp, nrm, res, a)
    S_data = S_k.sum(axis=0)
    D = np.r_[[lever] * 3, [1.0] * 3]
    lam, V = np.linalg.eigh(S_data / np.outer(D, D))
    good = np.ones(6, dtype=bool) if max_sigma_m is None else (
        loss_scale_m / np.sqrt(np.maximum(lam, 1e-300)) <= max_sigma_m)
    Vg = V[:, good] / D[:, None]
    A = np.einsum("ia,kij,jb->kab", Vg, S_data[None] + np.diag(prior) - S_k, Vg)
    y = np.linalg.solve(A + 1e-12 * np.eye(A.shape[1]), (b_k @ Vg)[:, :, None])[:, :, 0]
    influence = np.linalg.norm((y @ Vg.T) * D, axis=1)
    U = make_transform(R, centre - R @ centre + tau)
    return JointFit(U, c, a, np.abs(r), rms, it, held, centre, influence, S_data, lever)


def _estimate_joint(ref_scan: Scan, tgt_scan: Scan, T: np.ndarray, ref: _Sections, tgt: _Sections,
                    corr: Correspondences, fp: FineParams, loss: str,
                    T_prior: np.ndarray) -> tuple[JointFit | None, str, np.ndarray]:
    """Rigid update from one cylinder per section pair fitted to both scans' points at once.

    Pairs whose cylinder fits badly (RMS above `_TRIM_FACTOR` times the median and above the loss
    scale: a wrong pairing or a mis-separated arc) are dropped and the adjustment is repeated.
    So is the pair with the largest influence on the pose when it exceeds `fp.influence_factor`
    times the median and `fp.influence_min_m`: a wrong pair can bend a direction that only a few
    branches fix (a turn about the stem) so that it fits well itself, yet it still stands out as
    the one pair the solution hinges on.
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
        worst = int(np.argmax(fit.influence_m))
        if fp.influence_factor is not None and fit.influence_m[worst] > max(
                fp.influence_min_m, fp.influence_factor * float(np.median(fit.influence_m))):
            bad[worst] = True
        if not bad.any() or keep.sum() - bad.sum() < fp.min_pairs:
            break
        keep[np.flatnonzero(keep)[bad]] = False
    if not np.isfinite(fit.U).all():
        return None, "the joint section adjustment diverged", keep
    return fit, "", keep


@dataclass(frozen=True)
class Surface:
    """A scan's surface for point-to-plane terms: voxel centroids and unit normals oriented towards
    the scanner (the origin of the scan's frame), so that the two sides of a thin branch, each seen
    by a different station, have opposite normals and are never paired.

    `points` are the points used (all voxel centroids, or a seeded subset); normals come from the
    neighbours among all centroids and are computed when first needed (`normals_at`), since only
    the points that ever pair need one.
    """

    points: np.ndarray
    tree: cKDTree
    cloud: np.ndarray
    cloud_tree: cKDTree
    _normals: np.ndarray

    def normals_at(self, idx: np.ndarray) -> np.ndarray:
        """Oriented unit normals of `points[idx]`."""
        todo = np.unique(idx[np.isnan(self._normals[idx, 0])])
        if len(todo):
            k = min(NORMAL_K, len(self.cloud))
            _, nb = self.cloud_tree.query(self.points[todo], k=k)
            q = self.cloud[nb] - self.cloud[nb].mean(axis=1, keepdims=True)
            n = np.linalg.eigh(np.einsum("nki,nkj->nij", q, q))[1][:, :, 0]
            n *= np.where(np.einsum("ij,ij->i", n, self.points[todo]) > 0, -1.0, 1.0)[:, None]
            self._normals[todo] = n
        return self._normals[idx]


def surface_of(points: np.ndarray, voxel_m: float, max_points: int | None = None, seed: int = 0) -> Surface:
    """Voxel-subsampled surface of a scan (at most `max_points` used, a seeded random subset)."""
    cloud = voxel_downsample(points, voxel_m)
    cloud_tree = cKDTree(cloud)
    pts, tree = cloud, cloud_tree
    if max_points is not None and len(cloud) > max_points:
        pts = cloud[np.sort(np.random.default_rng(seed).choice(len(cloud), max_points, replace=False))]
        tree = cKDTree(pts)
    return Surface(pts, tree, cloud, cloud_tree, np.full((len(pts), 3), np.nan))


def _surface_pairs(ref: Surface, tgt: Surface, T: np.ndarray, gate_m: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Target points (mapped by T) with a reference neighbour within the gate whose normal agrees.

    Returns (target indices, mapped target points, point-to-plane residuals) of the kept pairs.
    """
    moved = apply_transform(T, tgt.points)
    d, j = ref.tree.query(moved, distance_upper_bound=gate_m)
    ok = np.flatnonzero(np.isfinite(d))
    nr = ref.normals_at(j[ok])
    agree = np.einsum("ij,ij->i", nr, tgt.normals_at(ok) @ T[:3, :3].T) > _NORMAL_AGREEMENT
    ok, nr = ok[agree], nr[agree]
    r = np.einsum("ij,ij->i", moved[ok] - ref.points[j[ok]], nr)
    return ok, moved[ok], r


def _alignment_measure(ref: Surface, tgt: Surface, T: np.ndarray, gate_m: float) -> float:
    """RMS of the point-to-plane residuals of the target's points, each truncated at `gate_m`.

    Points without a reference point within `gate_m` (or only one facing the other way) count as
    `gate_m`, so a pose cannot look better by sliding the target out of the overlap.
    """
    idx, _, r = _surface_pairs(ref, tgt, T, gate_m)
    e = np.full(len(tgt.points), gate_m)
    e[idx] = np.minimum(np.abs(r), gate_m)
    return float(np.sqrt(np.mean(e ** 2)))


def _refine_held(ref: Surface, tgt: Surface, T: np.ndarray, centre: np.ndarray, basis: np.ndarray,
                 fp: FineParams) -> np.ndarray:
    """Point-to-plane refinement of `T` along the pose directions in `basis` only.

    Returns the coefficients y of the refinement: it is `_pose_update(basis @ y, centre) @ T`.

    The sections fix the other directions to millimetres. Point-to-plane alignment of the whole
    target against the reference's surface (twigs, leaves, ground: all that the sections ignore)
    uses only pairs whose oriented normals agree, and a Cauchy loss of scale `fp.loss_scale_m`;
    it is used only where the sections are silent.
    """
    B = basis
    T0 = T
    y_total = np.zeros(B.shape[1])
    for _ in range(fp.surface_iterations):
        T = _pose_update(B @ y_total, centre) @ T0
        idx, q, r = _surface_pairs(ref, tgt, T, fp.surface_gate_m)
        if len(idx) < 10 * B.shape[1]:
            break
        n = tgt.normals_at(idx) @ T[:3, :3].T
        w = _robust_weight(r, fp.loss_scale_m, "cauchy")
        # d r / d pose uses the reference normal; the target's (agreeing) normal is close to it.
        J = np.c_[np.cross(q - centre, n), n] @ B
        H = J.T @ (J * w[:, None])
        try:
            y = -np.linalg.solve(H + 1e-12 * np.eye(len(H)), J.T @ (w * r))
        except np.linalg.LinAlgError:
            break
        y_total = y_total + y
        if _mean_move(_pose_update(B @ y, centre), q) < 1e-5:
            break
    return y_total


def _pose_update(x: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """4x4 of the pose parameters x = (rotation vector about `centre`, translation)."""
    R = _skew_rotation(x[:3])
    return make_transform(R, centre - R @ centre + x[3:])


def _mean_move(U: np.ndarray, pts: np.ndarray) -> float:
    return float(np.linalg.norm(apply_transform(U, pts) - pts, axis=1).mean())


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
        tgt_secs = _fit_scan_sections(tgt, sl.tgt_indices, sl.heights_m, T, ap, fitp)
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
        move = _mean_move(U, apply_transform(T, sample))
        updates.append(move)
        T = U @ T
        if move < fp.tolerance_m:
            break
    progress(fp.max_iterations / (fp.max_iterations + 1), "acceptance test")
    ref_surf = surface_of(ref.points, fp.measure_voxel_m)
    tgt_surf = surface_of(tgt.points, fp.measure_voxel_m, _SAMPLE)
    held = 0
    if joint is not None and updates and fp.surface_refine:
        # Directions the sections barely fix (z along a bare stem, a turn about it, which only a
        # few branches see) are taken from the surfaces; directions they fix only fairly are
        # checked against the surfaces and taken from them when the two disagree clearly (one
        # wrong branch pair can bend such a direction while fitting well itself).
        B, std = joint.weak_basis(fp.loss_scale_m, fp.surface_check_sigma_m)
        if B.shape[1]:
            y = _refine_held(ref_surf, tgt_surf, T, joint.centre_m, B, fp)
            use = (std > fp.surface_sigma_m) | (np.abs(y) > fp.surface_check_factor * std + fp.surface_tolerance_m)
            held = int(use.sum())
            T = _pose_update(B @ np.where(use, y, 0.0), joint.centre_m) @ T
    m0 = _alignment_measure(ref_surf, tgt_surf, T0, fp.measure_gate_m)
    m1 = _alignment_measure(ref_surf, tgt_surf, T, fp.measure_gate_m) if updates else m0
    accepted = bool(updates)
    message = ""
    if not updates:
        message = f"fine registration found nothing to improve ({note}); kept the coarse transform"
    elif fp.accept_test and not m1 < m0:
        accepted = False
        message = (f"the fine update did not improve the alignment (residual {m0 * 1000:.1f} mm at coarse, "
                   f"{m1 * 1000:.1f} mm after fine); kept the coarse transform")
    if not accepted:
        T = T0.copy()
    # What the app draws: slices, arcs, fits and ties at the pose finally returned (the last
    # iteration's, unless the pose has moved since by more than the tolerance).
    if drawn is None or _mean_move(T @ invert(drawn[0]), apply_transform(drawn[0], sample)) > fp.tolerance_m:
        sl = slice_scans(ref, tgt, T, sp)
        if ref_secs is None:
            ref_secs = _fit_scan_sections(ref, sl.ref_indices, sl.heights_m, np.eye(4), ap, fitp)
        tgt_secs = _fit_scan_sections(tgt, sl.tgt_indices, sl.heights_m, T, ap, fitp)
        corr = _match(ref_secs, tgt_secs, fitp)
    else:
        _, sl, tgt_secs, corr = drawn
    ties_r, ties_t = _ties(ref_secs, tgt_secs, corr) if corr.ok else (np.empty((0, 3)), np.empty((0, 3)))
    metrics = (
        Metric("fine accepted", "", "yes" if accepted else "no"),
        Metric("fine iterations", "", it),
        Metric("pose directions not fixed by sections", "", held),
        Metric("fine update (last iteration)", "m", updates[-1] if updates else 0.0),
        Metric("corresponding sections", "", int(len(corr.pairs))),
        Metric("alignment residual, coarse", "m", m0),
        Metric("alignment residual, fine", "m", m1),
    )
    progress(1.0, "done")
    return FineResult(True, message, metrics, T, T0, accepted, it, tuple(updates), m0, m1, sl,
                      ref_secs.arcs, tgt_secs.arcs, ref_secs.sections, tgt_secs.sections, corr,
                      ties_r, ties_t)


def _failed(T0: np.ndarray, message: str) -> FineResult:
    e = np.empty((0, 3))
    return FineResult(False, message, (Metric("fine accepted", "", "no"),), T0, T0, False, 0, (), np.nan, np.nan,
                      None, (), (), (), (), None, e, e)
