"""A survey pair registered on every stem and the ground both stations see.

The paper's fine step (2.2) fits circles to one tree's slices and matches their centres. A survey pair
shares tens of stems spread over the plot, which hold its pose far better than one tree: a stem 20 m
away pins the heading ten times tighter than a branch 2 m away. So each shared stem's sections are
fitted jointly with the pose:

* one circle per stem and section height, common to both stations (the reference's points and the
  target's points under the pose both lie on it), with a lean and a taper per stem (a section's two
  views stand a few centimetres apart in height);
* the target's ground points on the reference's ground (point to plane): the height and the tilt
  over the whole plot.

The unknowns are the pose and the circles, solved by robust Gauss-Newton (soft-L1 weights against a
branch or a leaf left in a section) on the analytic, sparse Jacobian (a stem's unknowns touch only its
own points). A stem whose two views still disagree after the fit (it moved, or the stem map paired two
different stems) is left out and the fit repeated.

A start comes from the stem maps (`prepare.target.stem_map_hypotheses`: yaw and shift) and the ground
(height). A planting in rows fits its stem map shifted by a row too: the next distinct stem map is
fitted as well, and the crowns, which differ from tree to tree, decide — or, when they agree as well
under both, the pair is refused as ambiguous.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.sparse import csr_matrix

from ..geometry.rigid import apply_transform, make_transform, rotation_from_vector
from ..params import SurveyParams
from .stations import SurveyStation

#: Fit rounds: solve, drop the stems whose views disagree, re-pair the ground points, solve again.
_ROUNDS = 3
#: Gauss-Newton steps at most, and the damping of their normal equations (relative to the diagonal).
_MAX_STEPS = 40
_DAMPING = 1e-6
#: The pose has converged when a step turns it less than this (rad; 0.6 micrometre 20 m out) and shifts it less (m).
_POSE_STEP = 3e-8
#: A rival stem map is fitted too when it matches at least this share of the best one's stems.
_RIVAL_SHARE = 0.6
#: The pose's uncertainty is said as the displacement it allows this far from the reference scanner.
_SD_RANGE_M = 20.0
#: Crowns agree where a target point has a reference point within this many cloud voxels.
_AGREE_VOXELS = 1.5
#: The crowns' check covers points within this of both scanners (a station sees little beyond).
_AGREE_RANGE_M = 20.0


@dataclass(frozen=True, kw_only=True)
class StemTie:
    """One shared stem of a pair: where it stands (reference frame), how many sections both stations
    fitted, the two views' disagreement after the fit, and whether it was used."""

    ref_index: int
    tgt_index: int
    xy: tuple[float, float]
    sections: int
    offset_m: float
    used: bool


@dataclass(frozen=True, kw_only=True)
class PairFit:
    """A survey pair's registration: `T_ref_target` maps the target station's (levelled) points into
    the reference station's, with the evidence the verdict rests on."""

    ok: bool
    message: str
    T_ref_target: np.ndarray | None
    stems: tuple[StemTie, ...] = ()
    residual_m: float = float("nan")
    ground_residual_m: float = float("nan")
    ground_points: int = 0
    agreement: float = float("nan")
    runner_up_agreement: float = float("nan")
    runner_up_shift_m: float = float("nan")
    spread_m: float = float("nan")
    points: int = 0
    #: The pose's uncertainty: one standard deviation of the displacement it allows 20 m from the
    #: reference scanner (the joint fit's normal equations; the stems' and ground's residuals).
    pose_sd_m: float = float("inf")

    @property
    def stems_used(self) -> int:
        return sum(s.used for s in self.stems)


def register_pair(ref: SurveyStation, tgt: SurveyStation, starts: list[tuple[np.ndarray, np.ndarray]],
                  sv: SurveyParams) -> PairFit:
    """Register `tgt` onto `ref` from the stem-map starts (best first, see the module doc)."""
    if not starts:
        return PairFit(ok=False, message="their stem maps do not match", T_ref_target=None)
    # The next distinct stem map is fitted only when it matches nearly as many stems (a planting's
    # shifted rows do; a chance alignment of a few stems in a natural stand does not).
    rivals = [h for h in starts[1:2] if len(h[1]) >= _RIVAL_SHARE * len(starts[0][1])]
    fits = [_fit(ref, tgt, _start(ref, tgt, T2, pairs), pairs, sv) for T2, pairs in starts[:1] + rivals]
    fits = [f for f in fits if f.T_ref_target is not None]
    if not fits:
        return PairFit(ok=False, message=f"fewer than survey.min_stems = {sv.min_stems} shared stems could be fitted",
                       T_ref_target=None)
    fits = sorted((_with_agreement(ref, tgt, f, sv) for f in fits), key=lambda f: -f.agreement)
    best = fits[0]
    if len(fits) > 1:
        assert best.T_ref_target is not None and fits[1].T_ref_target is not None
        at = np.column_stack([tgt.stems.xy, np.zeros(len(tgt.stems))])
        shift = float(np.linalg.norm(apply_transform(best.T_ref_target, at) - apply_transform(fits[1].T_ref_target, at),
                                     axis=1).mean())
        best = replace(best, runner_up_agreement=fits[1].agreement, runner_up_shift_m=shift)
    return best


def _start(ref: SurveyStation, tgt: SurveyStation, T2: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """The stem map's yaw and shift, with the height from the ground under the matched stems."""
    T = T2.copy()
    zr = ref.ground_z(ref.stems.xy[pairs[:, 0]])
    zt = tgt.ground_z(tgt.stems.xy[pairs[:, 1]])
    T[2, 3] = float(np.median(zr - zt))
    return T


def _fit(ref: SurveyStation, tgt: SurveyStation, T0: np.ndarray, pairs: np.ndarray, sv: SurveyParams) -> PairFit:
    use = np.ones(len(pairs), dtype=bool)
    T = T0
    offsets = np.zeros(len(pairs))
    sections = np.zeros(len(pairs), dtype=int)
    result: tuple[float, float, int, int, float] = (float("nan"), float("nan"), 0, 0, float("inf"))
    for _ in range(_ROUNDS):
        problem = _Problem.build(ref, tgt, pairs, use, T, sv)
        if problem is None or problem.n_stems < sv.min_stems:
            return PairFit(ok=False, message="", T_ref_target=None)
        T, offs, result = problem.solve(sv)
        offsets[:] = np.nan
        offsets[problem.stem_ids] = offs
        sections[problem.stem_ids] = problem.sections_per_stem
        bad = np.isfinite(offsets) & (offsets > sv.max_stem_offset_m) & use
        if not bad.any():
            break
        use &= ~bad
    ties = tuple(StemTie(ref_index=int(a), tgt_index=int(b), xy=(float(ref.stems.xy[a][0]), float(ref.stems.xy[a][1])),
                         sections=int(sections[k]), offset_m=float(offsets[k]), used=bool(use[k] and np.isfinite(offsets[k])))
                 for k, (a, b) in enumerate(pairs))
    used_xy = np.array([t.xy for t in ties if t.used])
    spread = float(np.linalg.svd(used_xy - used_xy.mean(axis=0), compute_uv=False)[-1] / np.sqrt(len(used_xy))) \
        if len(used_xy) >= 2 else 0.0
    residual, ground_res, n_ground, n_points, sd = result
    return PairFit(ok=True, message="", T_ref_target=T, stems=ties, residual_m=residual, ground_residual_m=ground_res,
                   ground_points=n_ground, spread_m=spread, points=n_points, pose_sd_m=sd)


@dataclass(eq=False)
class _Problem:
    """The joint least-squares problem of one round: points, their stems and sections, the ground."""

    P: np.ndarray            # reference stem points (fixed)
    Q: np.ndarray            # target stem points (target frame, moved by the pose)
    p_sec: np.ndarray        # section unknown index of each reference point
    q_sec: np.ndarray
    p_stem: np.ndarray       # stem unknown index of each point
    q_stem: np.ndarray
    z_sec: np.ndarray        # each section's reference height (its reference points' mean z)
    circles: np.ndarray      # start: cx, cy, r per section
    G: np.ndarray            # target ground points
    A: np.ndarray            # their reference ground points
    N: np.ndarray            # and those points' normals
    T0: np.ndarray
    stem_ids: np.ndarray     # which pairs' stems are in the problem
    sections_per_stem: np.ndarray

    @property
    def n_stems(self) -> int:
        return len(self.stem_ids)

    @classmethod
    def build(cls, ref: SurveyStation, tgt: SurveyStation, pairs: np.ndarray, use: np.ndarray, T0: np.ndarray,
              sv: SurveyParams) -> "_Problem | None":
        Ps, Qs, ps, qs, pk, qk, zs, circ, ids, per = [], [], [], [], [], [], [], [], [], []
        for k in np.flatnonzero(use):
            a, b = (int(v) for v in pairs[k])
            ca, cb = ref.columns[a], tgt.columns[b]
            both = np.flatnonzero(np.isfinite(ca.radii) & np.isfinite(cb.radii))
            if len(both) < 2:
                continue
            stem = len(ids)
            ids.append(k)
            per.append(len(both))
            for s in both:
                j = len(zs)
                pa = ca.points[ca.section == s]
                qb = cb.points[cb.section == s]
                Ps.append(pa)
                Qs.append(qb)
                ps.append(np.full(len(pa), j))
                qs.append(np.full(len(qb), j))
                pk.append(np.full(len(pa), stem))
                qk.append(np.full(len(qb), stem))
                zs.append(float(pa[:, 2].mean()))
                circ.append([*ca.centres[s], ca.radii[s]])
        if not ids:
            return None
        G, A, N = _ground_pairs(ref, tgt, T0, sv)
        return cls(P=np.concatenate(Ps), Q=np.concatenate(Qs), p_sec=np.concatenate(ps), q_sec=np.concatenate(qs),
                   p_stem=np.concatenate(pk), q_stem=np.concatenate(qk), z_sec=np.array(zs), circles=np.array(circ),
                   G=G, A=A, N=N, T0=T0, stem_ids=np.array(ids), sections_per_stem=np.array(per))

    def _unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        T = make_transform(rotation_from_vector(x[:3]), x[3:6]) @ self.T0
        ns = self.n_stems
        stem = x[6:6 + 3 * ns].reshape(ns, 3)          # lean x, lean y (m per m), taper (m per m)
        sec = x[6 + 3 * ns:].reshape(-1, 3)             # cx, cy, r
        return T, stem, sec

    def _stem_residuals(self, pts: np.ndarray, sec_i: np.ndarray, stem_i: np.ndarray, stem: np.ndarray,
                        sec: np.ndarray) -> np.ndarray:
        dz = pts[:, 2] - self.z_sec[sec_i]
        cx = sec[sec_i, 0] + dz * stem[stem_i, 0]
        cy = sec[sec_i, 1] + dz * stem[stem_i, 1]
        return np.hypot(pts[:, 0] - cx, pts[:, 1] - cy) - (sec[sec_i, 2] + dz * stem[stem_i, 2])

    def residuals(self, x: np.ndarray) -> np.ndarray:
        T, stem, sec = self._unpack(x)
        Qm = apply_transform(T, self.Q)
        out = [self._stem_residuals(self.P, self.p_sec, self.p_stem, stem, sec),
               self._stem_residuals(Qm, self.q_sec, self.q_stem, stem, sec)]
        if len(self.G):
            out.append(np.einsum("ij,ij->i", apply_transform(T, self.G) - self.A, self.N))
        return np.concatenate(out)

    def jacobian(self, x: np.ndarray) -> csr_matrix:
        """The residuals' Jacobian, analytic and sparse: a point's row touches the pose (a target or
        ground point), its stem's lean and taper and its section's circle. The pose's columns are
        the derivative at the current pose of a small turn and shift applied after it."""
        T, stem, sec = self._unpack(x)
        ns = self.n_stems
        rows, cols, vals = [], [], []
        off = 0
        for pts, sec_i, stem_i, moving in ((self.P, self.p_sec, self.p_stem, False),
                                           (apply_transform(T, self.Q), self.q_sec, self.q_stem, True)):
            n = len(pts)
            r = off + np.arange(n)
            dz = pts[:, 2] - self.z_sec[sec_i]
            dx = pts[:, 0] - (sec[sec_i, 0] + dz * stem[stem_i, 0])
            dy = pts[:, 1] - (sec[sec_i, 1] + dz * stem[stem_i, 1])
            rho = np.maximum(np.hypot(dx, dy), 1e-9)
            ux, uy = dx / rho, dy / rho
            c_stem, c_sec = 6 + 3 * stem_i, 6 + 3 * ns + 3 * sec_i
            for c, v in ((c_stem, -ux * dz), (c_stem + 1, -uy * dz), (c_stem + 2, -dz),
                         (c_sec, -ux), (c_sec + 1, -uy), (c_sec + 2, -np.ones(n))):
                rows.append(r), cols.append(c), vals.append(v)
            if moving:
                g = np.column_stack([ux, uy, -ux * stem[stem_i, 0] - uy * stem[stem_i, 1] - stem[stem_i, 2]])
                self._pose_columns(r, pts, g, rows, cols, vals)
            off += n
        if len(self.G):
            self._pose_columns(off + np.arange(len(self.G)), apply_transform(T, self.G), self.N, rows, cols, vals)
        return csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(off + len(self.G), len(x)))

    @staticmethod
    def _pose_columns(r: np.ndarray, p: np.ndarray, g: np.ndarray, rows: list[np.ndarray], cols: list[np.ndarray],
                      vals: list[np.ndarray]) -> None:
        """Rows `r` of residuals with gradient `g` (per point) at the moved points `p`: d/d(turn) is
        p x g, d/d(shift) is g."""
        turn = np.cross(p, g)
        for c in range(3):
            rows += [r, r]
            cols += [np.full(len(r), c), np.full(len(r), 3 + c)]
            vals += [turn[:, c], g[:, c]]

    def solve(self, sv: SurveyParams) -> tuple[np.ndarray, np.ndarray, tuple[float, float, int, int, float]]:
        x = self._gauss_newton(np.concatenate([np.zeros(6), np.zeros(3 * self.n_stems), self.circles.ravel()]),
                               sv.loss_scale_m)
        T, stem, sec = self._unpack(x)
        Qm = apply_transform(T, self.Q)
        rp = self._stem_residuals(self.P, self.p_sec, self.p_stem, stem, sec)
        rq = self._stem_residuals(Qm, self.q_sec, self.q_stem, stem, sec)
        offsets = np.array([self._offset(Qm, rq, self.q_sec, self.q_stem, sec, stem, k)
                            - self._offset(self.P, rp, self.p_sec, self.p_stem, sec, stem, k) for k in range(self.n_stems)])
        r_all = np.concatenate([rp, rq])
        residual = float(1.4826 * np.median(np.abs(r_all)))
        ground = float(1.4826 * np.median(np.abs(np.einsum("ij,ij->i", apply_transform(T, self.G) - self.A, self.N)))) \
            if len(self.G) else float("nan")
        return T, np.linalg.norm(offsets, axis=1), (residual, ground, len(self.G), len(r_all), self._pose_sd(x, sv))

    def _pose_sd(self, x: np.ndarray, sv: SurveyParams) -> float:
        """How far (m, one standard deviation) the pose's uncertainty moves a point `_SD_RANGE_M` from
        the reference scanner: the pose block of the weighted normal equations' inverse (the circles
        marginalised), scaled by the residuals' variance."""
        r, w, H, _ = self._normal_equations(x, sv.loss_scale_m)
        dof = max(len(r) - len(x), 1)
        try:
            C = np.linalg.inv(H)[:6, :6] * float(np.sum(w * r ** 2)) / dof
        except np.linalg.LinAlgError:
            return float("inf")
        return float(np.sqrt(max(np.trace(C[3:, 3:]) + _SD_RANGE_M ** 2 * np.trace(C[:3, :3]), 0.0)))

    def _normal_equations(self, x: np.ndarray, scale_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """At `x`: the residuals, their soft-L1 weights at `scale_m`, and the weighted normal equations
        J^T W J (dense: the unknowns are few; a hair added to the diagonal) and J^T W r."""
        r = self.residuals(x)
        J = self.jacobian(x)
        w = 1.0 / np.sqrt(1.0 + (r / scale_m) ** 2)
        JW = J.multiply(w[:, None]).tocsr()
        H = (J.T @ JW).toarray()
        H[np.diag_indices_from(H)] += 1e-12
        return r, w, H, JW.T @ r

    def _gauss_newton(self, x: np.ndarray, scale_m: float) -> np.ndarray:
        """Robust Gauss-Newton (IRLS, soft-L1 weights; the scale from ten times `scale_m` down to it, so
        a centimetre start is not cut off): the normal equations are small (the pose and a few
        hundred circle unknowns) while the points are tens of thousands, so they are formed and
        solved directly. The pose update is applied to `T0` each step (its Jacobian is exact at zero)."""
        for it in range(_MAX_STEPS):
            s = scale_m * max(1.0, 10.0 / (1 + it))
            _, _, H, g = self._normal_equations(x, s)
            H[np.diag_indices_from(H)] *= 1.0 + _DAMPING
            step = np.linalg.solve(H, -g)
            self.T0 = make_transform(rotation_from_vector(step[:3]), step[3:6]) @ self._unpack(x)[0]
            x = np.concatenate([np.zeros(6), x[6:] + step[6:]])
            if s == scale_m and np.abs(step[:6]).max() < _POSE_STEP:  # the circles may creep on; the pose has stopped
                break
        return x

    def _offset(self, pts: np.ndarray, r: np.ndarray, sec_i: np.ndarray, stem_i: np.ndarray, sec: np.ndarray,
                stem: np.ndarray, k: int) -> np.ndarray:
        """The horizontal shift that best explains stem `k`'s residuals `r` from one station's points
        `pts` (their sections `sec_i` and stems `stem_i`): its view stands off the joint circle by this much."""
        m = stem_i == k
        dz = pts[m, 2] - self.z_sec[sec_i[m]]
        c = sec[sec_i[m], :2] + dz[:, None] * stem[k, :2]
        u = pts[m, :2] - c
        u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-9)
        keep = np.abs(r[m]) < 5 * max(float(np.median(np.abs(r[m]))), 1e-4)
        if keep.sum() < 3:
            return np.full(2, np.nan)
        d, *_ = np.linalg.lstsq(u[keep], r[m][keep], rcond=None)
        return np.asarray(d)


def _ground_pairs(ref: SurveyStation, tgt: SurveyStation, T: np.ndarray, sv: SurveyParams
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The target's ground points near both scanners, each with its nearest reference ground point
    within a voxel and that point's normal."""
    empty = (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)))
    if len(ref.ground) < 20 or len(tgt.ground) < 20:
        return empty
    g = apply_transform(T, tgt.ground)
    origin_t = T[:3, 3]
    near = (np.hypot(*g[:, :2].T) < sv.ground_range_m) & (np.hypot(*(g[:, :2] - origin_t[:2]).T) < sv.ground_range_m)
    if near.sum() < 20:
        return empty
    d, nb = ref.ground_tree.query(g[near], distance_upper_bound=2 * sv.ground_voxel_m)
    ok = np.isfinite(d)
    return tgt.ground[np.flatnonzero(near)[ok]], ref.ground[nb[ok]], ref.ground_normals[nb[ok]]


def _with_agreement(ref: SurveyStation, tgt: SurveyStation, f: PairFit, sv: SurveyParams) -> PairFit:
    """The share of the target's thinned cloud near both scanners that lands on the reference's."""
    assert f.T_ref_target is not None
    c = apply_transform(f.T_ref_target, tgt.cloud)
    o = f.T_ref_target[:3, 3]
    near = (np.linalg.norm(c, axis=1) < _AGREE_RANGE_M) & (np.linalg.norm(c - o, axis=1) < _AGREE_RANGE_M)
    if near.sum() < 100:
        return replace(f, agreement=0.0)
    d, _ = ref.cloud_tree.query(c[near], distance_upper_bound=_AGREE_VOXELS * sv.cloud_voxel_m)
    return replace(f, agreement=float(np.isfinite(d).mean()))
