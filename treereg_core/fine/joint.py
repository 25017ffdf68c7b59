"""Joint adjustment of a rigid update and one cylinder per section pair (the fine stage's core).

For every pair of corresponding sections, one cylinder is fitted to the points of *both* scans at
once, while the target's points move with an unknown rigid update. Two stations see different
sides of a stem: together they cover far more arc than either alone, and the shared radius removes
the ambiguity of a partial-arc fit (whose centre slides along the viewing direction as the radius
changes). A cylinder only constrains motion across its axis, so oblique branches fix z and
sections at several heights fix the tilts.

Gauss-Newton with IRLS weights (soft-L1 or Cauchy), analytic Jacobian; the five unknowns of each
section are eliminated per section (Schur complement), leaving a 6 x 6 system for the update.

Wind (`bend_shape`): the target's tree may stand bent relative to the reference's, its stem moved
horizontally by `bend * shape(z)` (a cantilever: nothing at the base, the most at the top). The two
horizontal components of that sway at the top are then two more unknowns beside the pose, so the
crown's motion is not mistaken for a tilt of the scanner.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from ..geometry.losses import robust_cost, robust_weight
from ..geometry.rigid import make_transform, rotation_from_vector, rotation_vector
from ..params import JointParams


def _basis_rows(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per row of unit vectors `a` (K x 3), two unit vectors completing it to an orthonormal frame."""
    helper = np.where(np.abs(a[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    e1 = np.cross(a, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(a, e1)


#: The adjustment stops once a step moves the pose by less than this share of its noise std.
_CONVERGED_NOISE = float(__import__("os").environ.get("TREEREG_CONV", "0"))


def section_gram(A: np.ndarray, w: np.ndarray, section: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Per section k, the weighted Gram matrix sum_n w_n A_n A_n^T of its rows (K x Q x Q; w >= 0).

    The rows of a section are contiguous (`starts`): they are laid out as a zero-padded K x L x Q
    block and multiplied in one batched product, not summed from N outer products (N x Q x Q, most
    of the adjustment's time and memory when it was so)."""
    counts = np.diff(np.append(starts, len(A)))
    K, L, Q = len(starts), int(counts.max()), A.shape[1]
    flat = np.arange(len(A)) + (section * L - starts[section])  # row n -> its place in the K x L block
    padded = np.zeros((K * L, Q))
    padded[flat] = A * np.sqrt(w)[:, None]
    padded = padded.reshape(K, L, Q)
    # M^T M of one array (weights as square roots): numpy hands it to BLAS's symmetric product,
    # which stays on this thread; a product of two arrays woke BLAS's threads for a few
    # microseconds' work and cost five times as much.
    return np.matmul(padded.transpose(0, 2, 1), padded)


def _cross_rows(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Row-wise cross products of two N x 3 arrays (np.cross's generality costs more than the sums)."""
    out = np.empty_like(u)
    out[:, 0] = u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1]
    out[:, 1] = u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2]
    out[:, 2] = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
    return out


def _scales(n: int, lever_m: float) -> np.ndarray:
    """Per unknown of the update (rotation 3, translation 3, then any bend: 2), the factor that makes
    it metres: rotations times the lever arm, translations and the top's sway as they are."""
    return np.r_[[lever_m] * 3, [1.0] * (n - 3)]


def solve_well_determined(S_data: np.ndarray, S_prior: np.ndarray, b: np.ndarray, lever_m: float,
                           sigma_m: float, max_sigma_m: float | None) -> tuple[np.ndarray, int]:
    """Gauss-Newton step of the 6 pose unknowns (8 with a bend), restricted to the directions the
    data determine.

    Rotations are scaled by the lever arm `lever_m` so all six directions are in metres. A direction
    whose noise-propagated standard deviation sigma / sqrt(eigenvalue) exceeds `max_sigma_m` (a
    stem of vertical cylinders says nothing about z, or about a turn about itself) gets no update:
    it stays where coarse put it instead of wandering with noise and model error.
    Returns (step, held directions as a 6 x h basis of the unscaled pose parameters).
    """
    n = len(b)
    D = _scales(n, lever_m)
    Sy = S_data / np.outer(D, D)
    lam, V = np.linalg.eigh((Sy + Sy.T) / 2.0)
    if max_sigma_m is None:
        good = np.ones(n, dtype=bool)
    else:
        good = sigma_m / np.sqrt(np.maximum(lam, 1e-300)) <= max_sigma_m
    held = V[:, ~good] / D[:, None]
    if not good.any():
        return np.zeros(n), held
    Vg = V[:, good]
    A = Vg.T @ ((Sy + S_prior / np.outer(D, D)) @ Vg)
    dy = -Vg @ np.linalg.solve(A, Vg.T @ (b / D))
    return dy / D, held


@dataclass(frozen=True)
class JointFit:
    """Outcome of the joint adjustment.

    Attributes
    ----------
    U
        4x4 update that maps the moving (target) points, as given, to their adjusted place.
    points_m, axes, radii_m
        One cylinder per section (reference frame): a point on its axis, unit axis, radius.
    rms_m
        RMS residual of each section's points (both scans) to its cylinder.
    iterations
        Gauss-Newton iterations run.
    held_basis
        6 x h basis of the pose directions held at the prior (see `solve_well_determined`).
    centre_m, lever_m
        The rotation centre of the update (centroid of the points) and the RMS distance of the
        points from it (rotations times the lever arm are metres).
    information
        6 x 6 information matrix of the update from the sections alone (their own unknowns and the
        bend eliminated).
    influence_m
        Per section, how far the update would move without it (see `_influence`).
    bend_m
        With `bend_shape`: the horizontal shift (x, y, reference frame) that the adjustment gave the
        target's stem at its top (where the shape is 1) to line it up with the reference's; None
        without. The target's crown had swayed by minus this between the stations.
    bend_std_m
        The noise standard deviation of `bend_m` (per component, for the loss scale as residual scale).
    """

    U: np.ndarray
    points_m: np.ndarray
    axes: np.ndarray
    radii_m: np.ndarray
    rms_m: np.ndarray
    iterations: int
    held_basis: np.ndarray
    centre_m: np.ndarray
    information: np.ndarray
    lever_m: float
    influence_m: np.ndarray
    bend_m: np.ndarray | None = None
    bend_std_m: np.ndarray | None = None
    #: With a bend: each kept section's own offset (m) after the adjustment (`section_offsets`):
    #: how far the small branches moved on their own.
    section_offsets_m: np.ndarray | None = None

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


@dataclass(frozen=True, kw_only=True)
class JointProblem:
    """What the joint adjustment fits: the points of every section pair and where its cylinders start.

    Attributes
    ----------
    points
        N x 3 points in the reference frame, grouped by section (`section` non-decreasing).
    section
        Section number 0..K-1 of each point; every section must have points.
    moving
        N bools: True for target points (they move with the update).
    centres_m, axes, radii_m
        K x 3 axis points, K x 3 unit axes, K radii to start from.
    bend_shape
        Per point, the share of the top's sway by which a moving point is shifted (its height on the
        cantilever; ignored for fixed points): the two horizontal components of the top's shift are
        then unknowns too. None = rigid.
    section_weight
        Per section, a weight of all its points (a section that moved on its own in the wind counts
        less); None = all 1.
    """

    points: np.ndarray
    section: np.ndarray
    moving: np.ndarray
    centres_m: np.ndarray
    axes: np.ndarray
    radii_m: np.ndarray
    bend_shape: np.ndarray | None = None
    section_weight: np.ndarray | None = None


def adjust_joint(problem: JointProblem, *, joint: JointParams, loss: str = "soft_l1",
                 prior_offset: np.ndarray | None = None, prior_bend_m: float = 1.0) -> JointFit:
    """Fit one cylinder per section to all its points while the `moving` points follow a rigid update.

    A Gauss-Newton (IRLS, soft-L1 or Cauchy loss) bundle adjustment with an analytic Jacobian. The section
    unknowns (axis point across the axis: 2, axis tilt: 2, radius: 1) are eliminated per section
    (Schur complement of their 5 x 5 blocks), leaving a 6 x 6 system for the update (rotation
    vector about the data centroid, translation); a prior centred on the coarse pose keeps
    directions that the sections hardly constrain near it.

    Parameters
    ----------
    problem
        The points, their sections, which of them move, the cylinders to start from and any bend.
    joint
        `loss_scale_m`; `prior_m`, `prior_deg` (prior standard deviations of the translation and
        rotation away from the prior pose); `max_direction_sigma_m` (pose directions determined
        worse than this are held, see `solve_well_determined`); `max_solver_iterations`.
    loss
        "soft_l1" (convex beyond the scale: safe far from the solution) or "cauchy" (redescending:
        a wrong pair's points lose their pull once the right pose is near).
    prior_offset
        4x4 taking the prior pose of the moving points to the pose they are given in (the fine
        updates so far); None = they are given at the prior pose.
    prior_bend_m
        With `problem.bend_shape`: the prior std of the top's sway about zero.

    Returns
    -------
    JointFit
        `U` maps the moving points (as given) to their adjusted position.
    """
    points, section, moving = problem.points, problem.section, problem.moving
    c0, a0, r0 = problem.centres_m, problem.axes, problem.radii_m
    bend_shape, section_weight = problem.bend_shape, problem.section_weight
    loss_scale_m, prior_m, prior_deg = joint.loss_scale_m, joint.prior_m, joint.prior_deg
    max_sigma_m, max_iterations = joint.max_direction_sigma_m, joint.max_solver_iterations
    starts = np.flatnonzero(np.r_[True, section[1:] != section[:-1]])
    centre = points.mean(axis=0)
    lever = float(np.sqrt(np.mean(np.sum((points - centre) ** 2, axis=1))))
    held = np.zeros((6, 0))
    mv = np.flatnonzero(moving)
    base = points[mv] - centre
    c, a, r = c0.astype(float).copy(), a0.astype(float).copy(), r0.astype(float).copy()
    R, tau = np.eye(3), np.zeros(3)
    nb = 0 if bend_shape is None else 2
    fz = np.zeros(len(mv)) if bend_shape is None else np.asarray(bend_shape, dtype=float)[mv]
    sway = np.zeros(2)
    # The pose relative to the prior (coarse) one, in the same parametrisation: rotation about `centre`.
    Rp = np.eye(3) if prior_offset is None else prior_offset[:3, :3]
    tp = np.zeros(3) if prior_offset is None else Rp @ centre + prior_offset[:3, 3] - centre
    prior = (loss_scale_m ** 2) * np.r_[[1 / np.radians(prior_deg) ** 2] * 3, [1 / prior_m ** 2] * 3,
                                        [1 / prior_bend_m ** 2] * nb]
    eye5 = np.eye(5)
    pw = None if section_weight is None else np.asarray(section_weight, dtype=float)[section]

    def prior_state(Rt: np.ndarray, t: np.ndarray, w_: np.ndarray) -> np.ndarray:
        return np.r_[rotation_vector(Rt), t, w_[:nb]]

    def residuals(R_: np.ndarray, tau_: np.ndarray, c_: np.ndarray, a_: np.ndarray, r_: np.ndarray,
                  w_: np.ndarray = sway):
        cur = points.copy()
        moved = base @ R_.T
        moved += centre + tau_
        if nb:
            moved[:, :2] += fz[:, None] * w_[None, :]
        cur[mv] = moved
        d = cur - c_[section]
        ax = a_[section]
        along = np.einsum("ij,ij->i", d, ax)
        perp = d - along[:, None] * ax
        nrm = np.sqrt(np.einsum("ij,ij->i", perp, perp))
        return cur, d, along, perp, nrm, nrm - r_[section]

    def cost(res: np.ndarray, Rt: np.ndarray, t: np.ndarray, w_: np.ndarray) -> float:
        return robust_cost(res, loss_scale_m, loss, pw) + float(prior @ prior_state(Rt, t, w_) ** 2)

    def linearise(cur, along, perp, nrm, res, a):
        """Normal-equation blocks: per section (5 x 5, 5 x 6, 5) and per section's pose part."""
        w = robust_weight(res, loss_scale_m, loss)
        if pw is not None:
            w = w * pw
        n = perp / np.maximum(nrm, 1e-12)[:, None]
        e1, e2 = _basis_rows(a)
        ne1 = np.einsum("ij,ij->i", n, e1[section])
        ne2 = np.einsum("ij,ij->i", n, e2[section])
        # The rows of [section unknowns (5) | pose unknowns (6, 8 with a bend) | residual], filled
        # in place; one Gram matrix per section of them gives every block of the normal equations.
        A = np.zeros((len(res), 12 + nb))
        A[:, 0], A[:, 1] = -ne1, -ne2
        A[:, 2], A[:, 3] = -along * ne1, -along * ne2
        A[:, 4] = -1.0
        nm = n[mv]
        arm = cur[mv] - centre
        if nb:  # the bend is added after the rigid part, so a rotation turns the point without its bend
            arm[:, :2] -= fz[:, None] * sway[None, :]
        A[mv, 5:8] = _cross_rows(arm, nm)
        A[mv, 8:11] = nm
        if nb:
            A[mv, 11:13] = fz[:, None] * nm[:, :2]
        A[:, -1] = res
        G = section_gram(A, w, section, starts)
        P = 5 + 6 + nb
        Hss, Hsp, gs, Hpp_k, gp_k = G[:, :5, :5], G[:, :5, 5:P], G[:, :5, P], G[:, 5:P, 5:P], G[:, 5:P, P]
        # Levenberg damping on the section blocks keeps near-degenerate sections (tiny arcs) finite.
        Hss = Hss + 1e-9 * eye5 + 1e-6 * np.einsum("kii->ki", Hss)[:, :, None] * eye5
        Hinv = np.linalg.inv(Hss)
        HinvHsp = Hinv @ Hsp
        # Each section's contribution to the reduced (pose-only) system, its own unknowns eliminated.
        S_k = Hpp_k - np.einsum("kji,kjl->kil", Hsp, HinvHsp)
        b_k = gp_k - np.einsum("kji,kj->ki", Hsp, np.einsum("kij,kj->ki", Hinv, gs))
        return e1, e2, Hinv, HinvHsp, gs, S_k, b_k

    cur, d, along, perp, nrm, res = residuals(R, tau, c, a, r, sway)
    f = cost(res, Rp, tp, sway)
    it = 0
    for it in range(1, max_iterations + 1):
        e1, e2, Hinv, HinvHsp, gs, S_k, b_k = linearise(cur, along, perp, nrm, res, a)
        S = S_k.sum(axis=0) + np.diag(prior)
        b = b_k.sum(axis=0) + prior * prior_state(Rp, tp, sway)
        dp, held = solve_well_determined(S - np.diag(prior), np.diag(prior), b, lever, loss_scale_m, max_sigma_m)
        ds = -(np.einsum("kij,kj->ki", Hinv, gs) + HinvHsp @ dp)
        step = 1.0
        for _ in range(8):  # backtracking: IRLS steps on a robust cost can overshoot
            Rd = rotation_from_vector(step * dp[:3])
            R_n, tau_n = Rd @ R, Rd @ tau + step * dp[3:6]
            Rp_n, tp_n = Rd @ Rp, Rd @ tp + step * dp[3:6]
            w_n = sway + step * dp[6:8] if nb else sway
            c_n = c + step * (ds[:, :1] * e1 + ds[:, 1:2] * e2)
            a_n = a + step * (ds[:, 2:3] * e1 + ds[:, 3:4] * e2)
            a_n /= np.linalg.norm(a_n, axis=1, keepdims=True)
            r_n = r + step * ds[:, 4]
            out = residuals(R_n, tau_n, c_n, a_n, r_n, w_n)
            f_n = cost(out[-1], Rp_n, tp_n, w_n)
            if f_n <= f:
                break
            step /= 2.0
        else:
            break
        R, tau, Rp, tp, sway, c, a, r = R_n, tau_n, Rp_n, tp_n, w_n, c_n, a_n, r_n
        cur, d, along, perp, nrm, res = out
        # Converged when the cost stalls, the pose moves by less than about 10 micrometres, or the
        # step is a small share of the pose's own noise (its Mahalanobis length under the sections'
        # information): IRLS creeps along a weakly fixed direction for dozens of steps otherwise.
        S_data = S - np.diag(prior)
        noise_steps = float(np.sqrt(max(step * dp @ S_data @ (step * dp), 0.0))) / loss_scale_m
        converged = f - f_n <= 1e-7 * max(f, 1e-12) or (
            np.linalg.norm(step * dp[:3]) * lever < 1e-5 and np.linalg.norm(step * dp[3:]) < 1e-5) or (
            noise_steps < _CONVERGED_NOISE)
        f = f_n
        if converged:
            break
    counts = np.diff(np.r_[starts, len(res)])
    rms = np.sqrt(np.add.reduceat(res ** 2, starts) / counts)
    _, _, _, _, _, S_k, b_k = linearise(cur, along, perp, nrm, res, a)
    U = make_transform(R, centre - R @ centre + tau)
    S = S_k.sum(axis=0)
    bend = bend_std = None
    if nb:
        # The bend as a nuisance: the pose's information with it eliminated, and its own noise.
        Sb = S[6:, 6:] + np.diag(prior[6:])
        bend, bend_std = sway.copy(), loss_scale_m * np.sqrt(np.diag(np.linalg.inv(Sb)))
        S = S[:6, :6] - S[:6, 6:] @ np.linalg.solve(Sb, S[6:, :6])
    return JointFit(U, c, a, np.abs(r), rms, it, held, centre, S, lever,
                    _influence(S_k, b_k, np.diag(prior), lever, loss_scale_m, max_sigma_m), bend, bend_std)


def section_offsets(points: np.ndarray, section: np.ndarray, moving: np.ndarray, centres: np.ndarray,
                    axes: np.ndarray, radii: np.ndarray, loss_scale_m: float,
                    iterations: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Per section, how far its moving (target) points sit off the fixed (reference) points.

    In the plane across each section's axis, one circle (a shared radius) is fitted to the fixed
    points and the same circle shifted by an offset to the moving ones (Gauss-Newton, Cauchy
    weights at `loss_scale_m`, from the given cylinders). With the radius shared, a partial arc's
    centre cannot slide along the view, so the offset is the section's own displacement: a twig that
    moved in the wind, or a stem bent further than the model. Returns the offsets (K x 3, reference
    frame, across the axes) and each offset's noise std (metres; inf where a scan's arc fixes nothing).
    """
    K = len(centres)
    starts = np.flatnonzero(np.r_[True, section[1:] != section[:-1]])
    e1, e2 = _basis_rows(axes)
    d = points - centres[section]
    u = np.c_[np.einsum("ij,ij->i", d, e1[section]), np.einsum("ij,ij->i", d, e2[section])]
    m = moving.astype(float)
    x = np.zeros((K, 5))  # centre shift (2), the moving points' offset (2), radius change
    eye = np.eye(5)
    H = np.zeros((K, 5, 5))
    res = np.zeros(len(points))
    for _ in range(iterations):
        q = u - x[section, :2] - m[:, None] * x[section, 2:4]
        nrm = np.maximum(np.linalg.norm(q, axis=1), 1e-12)
        n = q / nrm[:, None]
        res = nrm - (radii[section] + x[section, 4])
        J = np.c_[-n, -m[:, None] * n, -np.ones(len(q))]
        w = robust_weight(res, loss_scale_m, "cauchy")
        G = section_gram(np.c_[J, res], w, section, starts)
        H = G[:, :5, :5] + 1e-9 * eye
        g = G[:, :5, 5]
        step = -np.linalg.solve(H, g[:, :, None])[:, :, 0]
        x += step
        if np.abs(step).max() < 1e-6:
            break
    counts = np.diff(np.r_[starts, len(res)])
    sigma = np.sqrt(np.add.reduceat(res ** 2, starts) / np.maximum(counts - 5, 1))
    cov = np.linalg.inv(H)
    std = sigma * np.sqrt(np.maximum(cov[:, 2, 2] + cov[:, 3, 3], 0.0))
    offset = x[:, 2:3] * e1 + x[:, 3:4] * e2
    return offset, np.where(np.isfinite(std), std, np.inf)


def _influence(S_k: np.ndarray, b_k: np.ndarray, S_prior: np.ndarray, lever_m: float, sigma_m: float,
               max_sigma_m: float | None) -> np.ndarray:
    """How far the pose would move without each section (metres at the lever arm).

    Linearised at the solution, where the summed gradient vanishes: the shift is (S - S_k)^-1 b_k.
    It measures conflict, not information: a section that alone fixes a direction, and that the
    others do not contradict, has a near-zero gradient there. Only directions the sections
    determine count; in the others the prior alone holds the pose and any gradient would look huge.
    """
    S = S_k.sum(axis=0)
    D = _scales(S.shape[0], lever_m)
    lam, V = np.linalg.eigh(S / np.outer(D, D))
    good = np.ones(S.shape[0], dtype=bool) if max_sigma_m is None else sigma_m / np.sqrt(np.maximum(lam, 1e-300)) <= max_sigma_m
    Vg = V[:, good] / D[:, None]
    A = np.einsum("ia,kij,jb->kab", Vg, S[None] + S_prior - S_k, Vg)
    y = np.linalg.solve(A + 1e-12 * np.eye(A.shape[1]), (b_k @ Vg)[:, :, None])[:, :, 0]
    return np.linalg.norm((y @ Vg.T) * D, axis=1)
