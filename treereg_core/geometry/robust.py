"""Robust rigid fits over tie pairs: RANSAC with 4 DOF (yaw + translation) or 6 DOF.

Tie points from ORB matches on binary images are mostly wrong (in our trials well under half lie
within 0.5 m of where they should), so the transform is the one most ties agree with:
hypotheses from minimal samples (2 pairs for 4 DOF, 3 for 6 DOF), scored by MSAC (truncated
squared residual), then refitted by least squares on the inliers until the inlier set is stable.
All hypotheses are scored at once with numpy, in chunks.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .rigid import kabsch, kabsch_yaw

#: Hypotheses scored per numpy chunk (memory: chunk x n_ties x 3 floats).
_CHUNK = 512
#: Hypotheses refined at most while looking for distinct modes.
_MAX_EXAMINED = 40


@dataclass(frozen=True)
class RobustFit:
    """A rigid transform fitted to tie pairs, with the pairs that agree with it.

    Attributes
    ----------
    T : 4x4 mapping `src` onto `dst`.
    inliers : (N,) bool, residual below the inlier distance.
    residuals_m : (N,) distance |T src - dst| per pair, metres.
    hypotheses : minimal-sample hypotheses scored.
    inlier_m : the inlier distance `inliers` refers to (the final one when it was narrowed).
    """

    T: np.ndarray
    inliers: np.ndarray
    residuals_m: np.ndarray
    hypotheses: int
    inlier_m: float

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())


def fit(src: np.ndarray, dst: np.ndarray, dof: int) -> np.ndarray:
    """Least-squares rigid transform with `dof` = 4 (yaw + translation) or 6."""
    if dof == 4:
        return kabsch_yaw(src, dst)
    if dof == 6:
        return kabsch(src, dst)
    raise ValueError(f"dof must be 4 or 6, got {dof}")


def residuals(T: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """|T src - dst| per pair, metres."""
    return np.linalg.norm(src @ T[:3, :3].T + T[:3, 3] - dst, axis=1)


def is_degenerate(src: np.ndarray, dof: int, min_extent_m: float = 0.05) -> bool:
    """True when the points cannot fix the transform: all on one vertical line (4 DOF) or one line (6 DOF)."""
    if len(src) < (2 if dof == 4 else 3):
        return True
    c = src - src.mean(axis=0)
    if dof == 4:
        return float(np.sqrt((c[:, :2] ** 2).sum(axis=1).max())) < min_extent_m
    s = np.linalg.svd(c, compute_uv=False)
    return float(s[1] / np.sqrt(len(src))) < min_extent_m


def _hypotheses_4dof(src: np.ndarray, dst: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """(H, 3, 4) yaw + translation transforms from pairs of ties idx (H, 2)."""
    a0, a1 = src[idx[:, 0]], src[idx[:, 1]]
    b0, b1 = dst[idx[:, 0]], dst[idx[:, 1]]
    u = a1[:, :2] - a0[:, :2]
    v = b1[:, :2] - b0[:, :2]
    yaw = np.arctan2(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0], (u * v).sum(axis=1))
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros((len(idx), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    ca, cb = (a0 + a1) / 2, (b0 + b1) / 2
    t = cb - np.einsum("hij,hj->hi", R, ca)
    return np.concatenate([R, t[:, :, None]], axis=2)


def _hypotheses_6dof(src: np.ndarray, dst: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """(H, 3, 4) rigid transforms from triples of ties idx (H, 3), batched Kabsch."""
    a, b = src[idx], dst[idx]                                   # (H, 3, 3)
    ca, cb = a.mean(axis=1), b.mean(axis=1)
    H = np.einsum("hki,hkj->hij", a - ca[:, None], b - cb[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("hji,hkj->hik", Vt, U)))  # det(V U^T)
    d[d == 0] = 1.0
    D = np.zeros_like(H)
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = np.einsum("hji,hjk,hlk->hil", Vt, D, U)                   # V D U^T
    t = cb - np.einsum("hij,hj->hi", R, ca)
    return np.concatenate([R, t[:, :, None]], axis=2)


def _samples(n: int, k: int, count: int, rng: np.random.Generator) -> np.ndarray:
    """Up to `count` samples of `k` distinct indices out of `n` (samples with a repeat are dropped)."""
    idx = rng.integers(0, n, size=(count, k))
    ok = np.ones(count, dtype=bool)
    for i in range(k):
        for j in range(i + 1, k):
            ok &= idx[:, i] != idx[:, j]
    return idx[ok]


@dataclass(frozen=True, kw_only=True)
class RansacSettings:
    """How RANSAC searches (the coarse stage builds one from `CoarseParams`).

    Attributes
    ----------
    dof : 4 = yaw about z + 3-D translation (levelled scanners), 6 = full rigid.
    inlier_m : a pair is an inlier when |T src - dst| < inlier_m.
    iterations : minimal samples drawn.
    seed : random seed (results are reproducible).
    refine_steps : least-squares refits on the inliers of the best hypothesis.
    final_inlier_m : when smaller than `inlier_m`, the threshold is then halved step by step down to
        this distance, refitting on the inliers each time: the wide threshold finds the transform,
        the narrow one drops the roughly-right ties that bias it. Stops early when fewer than
        `min_inliers` remain. The returned inliers are those of the last threshold used.
    min_inliers : see `final_inlier_m`.
    """

    dof: int = 4
    inlier_m: float = 0.4
    iterations: int = 2000
    seed: int = 0
    refine_steps: int = 5
    final_inlier_m: float | None = None
    min_inliers: int = 6


def ransac(src: np.ndarray, dst: np.ndarray, settings: RansacSettings = RansacSettings()) -> RobustFit | None:
    """RANSAC (MSAC scoring) of a rigid transform mapping `src` onto `dst` (both N x 3).

    Returns
    -------
    RobustFit, or None when there are too few pairs or no non-degenerate sample.
    """
    modes = ransac_modes(src, dst, settings, max_modes=1)
    return modes[0] if modes else None


def ransac_modes(src: np.ndarray, dst: np.ndarray, settings: RansacSettings = RansacSettings(), *,
                 max_modes: int = 4, distinct_deg: float = 15.0, distinct_m: float = 1.0) -> list[RobustFit]:
    """The best RANSAC transform and up to `max_modes - 1` distinct runners-up, best first.

    A tree can look alike from two headings (a nearly round crown): the ties then split between two
    transforms, and the best may be the wrong one. Hypotheses are ranked by their MSAC cost; a mode
    is the best hypothesis not within `distinct_deg` of yaw and `distinct_m` (where the ties'
    centroid lands) of a mode already taken. Each mode is refined like the best one. The first mode
    is exactly what `ransac` returns.
    """
    dof, inlier_m, final_inlier_m = settings.dof, settings.inlier_m, settings.final_inlier_m
    refine_steps, min_inliers = settings.refine_steps, settings.min_inliers
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    k = 2 if dof == 4 else 3
    n = len(src)
    if n < k:
        return []
    rng = np.random.default_rng(settings.seed)
    idx = _samples(n, k, int(settings.iterations), rng)
    # A rigid motion keeps distances: a sample whose pair distances disagree by more than twice the
    # inlier distance cannot be all inliers; so can't a sample too small to fix the rotation.
    ds = np.linalg.norm(src[idx[:, 1]] - src[idx[:, 0]], axis=1)
    dd = np.linalg.norm(dst[idx[:, 1]] - dst[idx[:, 0]], axis=1)
    good = np.abs(ds - dd) < 2 * inlier_m
    if dof == 4:
        good &= np.linalg.norm(src[idx[:, 1], :2] - src[idx[:, 0], :2], axis=1) > inlier_m / 2
    else:
        area = np.linalg.norm(np.cross(src[idx[:, 1]] - src[idx[:, 0]], src[idx[:, 2]] - src[idx[:, 0]]), axis=1)
        good &= area > inlier_m ** 2
    idx = idx[good]
    if len(idx) == 0:
        return []
    th2 = inlier_m ** 2
    costs, Ts = [], []
    for s in range(0, len(idx), _CHUNK):
        chunk = idx[s: s + _CHUNK]
        Th = _hypotheses_4dof(src, dst, chunk) if dof == 4 else _hypotheses_6dof(src, dst, chunk)
        costs.append(np.minimum(_squared_residuals(Th, src, dst), th2).sum(axis=0))
        Ts.append(Th)
    cost, hyp = np.concatenate(costs), np.concatenate(Ts)
    # The mode test compares where the hypotheses put the ties' centroid, and their yaw.
    centre = src.mean(axis=0)
    landed = np.einsum("hij,j->hi", hyp[:, :, :3], centre) + hyp[:, :, 3]
    yaw = np.degrees(np.arctan2(hyp[:, 1, 0], hyp[:, 0, 0]))
    modes: list[RobustFit] = []
    seen: list[int] = []  # hypotheses examined (refined): a near copy of one converges the same way

    def near(T1: np.ndarray, T2: np.ndarray) -> bool:
        d_yaw = np.degrees(np.arctan2(T1[1, 0], T1[0, 0]) - np.arctan2(T2[1, 0], T2[0, 0]))
        d_pos = (T1[:3, :3] - T2[:3, :3]) @ centre + T1[:3, 3] - T2[:3, 3]
        return abs((d_yaw + 180.0) % 360.0 - 180.0) < distinct_deg and float(np.linalg.norm(d_pos)) < distinct_m

    for h in np.argsort(cost, kind="stable"):
        if len(modes) == max_modes or len(seen) == _MAX_EXAMINED:
            break
        if any(abs((yaw[h] - yaw[t] + 180.0) % 360.0 - 180.0) < distinct_deg
               and np.linalg.norm(landed[h] - landed[t]) < distinct_m for t in seen):
            continue
        seen.append(int(h))
        T = _refine(np.vstack([hyp[h], [0.0, 0.0, 0.0, 1.0]]), src, dst, dof, inlier_m, refine_steps, k)
        used = inlier_m
        if final_inlier_m is not None:
            th = inlier_m
            while th > final_inlier_m * 1.0001:
                th = max(th / 2.0, final_inlier_m)
                if (residuals(T, src, dst) < th).sum() < max(min_inliers, k):
                    break
                T = _refine(T, src, dst, dof, th, refine_steps, k)
                used = th
        if any(near(T, m.T) for m in modes):  # refined onto a mode already found
            continue
        res = residuals(T, src, dst)
        modes.append(RobustFit(T=T, inliers=res < used, residuals_m=res, hypotheses=int(len(idx)), inlier_m=used))
    return modes


def _squared_residuals(Th: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """|T src - dst|^2 of every pair (rows) under every hypothesis (columns; `Th` H x 3 x 4), a
    coordinate at a time: three matrix products, not an N x H x 3 array summed along its short axis
    (six times slower)."""
    r2 = np.zeros((len(src), len(Th)))
    for k in range(3):
        d = src @ Th[:, k, :3].T
        d += Th[:, k, 3]
        d -= dst[:, k:k + 1]
        r2 += d * d
    return r2


def chance_inliers(src: np.ndarray, dst: np.ndarray, settings: RansacSettings, shuffles: int = 3) -> int:
    """How many ties RANSAC makes agree when the pairing carries no information: the most inliers
    found over `shuffles` random re-pairings of the same ties (the level chance reaches on this data).
    Shuffle `s` runs with seed `settings.seed + s`."""
    rng = np.random.default_rng(settings.seed + 1)
    best = 0
    for s in range(shuffles):
        fit = ransac(src, dst[rng.permutation(len(dst))], replace(settings, seed=settings.seed + s))
        best = max(best, fit.n_inliers if fit is not None else 0)
    return best


def _refine(T: np.ndarray, src: np.ndarray, dst: np.ndarray, dof: int, th: float, steps: int, k: int) -> np.ndarray:
    """Least-squares refits on the pairs within `th` of `T`, until the inlier set stops changing."""
    inl = residuals(T, src, dst) < th
    for _ in range(steps):
        if inl.sum() < k or is_degenerate(src[inl], dof):
            break
        T_new = fit(src[inl], dst[inl], dof)
        inl_new = residuals(T_new, src, dst) < th
        if inl_new.sum() < inl.sum():
            break
        T = T_new
        if np.array_equal(inl_new, inl):
            break
        inl = inl_new
    return T
