"""Many stations, one consistent answer: which pairs to register, and every scan placed jointly.

Pairs. Two scans are registered together when their projection sequences look alike (the coarse
similarity of the paper's 2.1.3): the pairs of a maximum spanning tree over that similarity, so
every scan is connected, plus each scan's next most similar partner, so loops exist to check
(with three scans: all three pairs). The reference's pairs come first, in scan order (the pairs
the paper registers, 2->1, 3->1, ...).

Placement. Every verified pair is an edge of a pose graph. Loops of edges must close: the product
of the transforms around a loop is the identity for right registrations; an edge that keeps a loop
open is dropped (the one with the largest residual in a robust joint solve). The poses of all scans
are then solved together (soft-L1, then Cauchy loss), scan 1 fixed: a scan opposite the reference
is placed through its neighbours, and small pairwise errors are averaged out rather than chained. A
scan not reachable through verified edges keeps its best guess, unverified.

The solve is sparse (`solve_pose_graph`, plain edges and points, no pipeline objects): an edge's
residuals depend on the 6 unknowns of its two scans only, so its Jacobian is analytic, 12 non-zeros
a row, and each step one sparse solve of 6 unknowns a scan; an edge's disagreement over its sample
points is carried by six sigma points with their mean and covariance (exactly the same sum of
squares); after a drop the solve goes on from the poses it had. 36 stations in a fraction of a
second where the dense finite-difference solve took minutes (benchmarks/bench_graph.py).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
from scipy.sparse import coo_matrix, csc_matrix, csr_matrix, diags
from scipy.sparse.linalg import spsolve
from scipy.sparse.csgraph import minimum_spanning_tree

from ..geometry.rigid import apply_transform, invert, make_transform
from ..params import GraphParams
from ..results import Metric
from .evidence import FAILED, UNVERIFIED, VERIFIED, Evidence, joined_hints


def select_pairs(similarity: np.ndarray, extra: int) -> list[tuple[int, int]]:
    """Pairs (i, j), i < j, to register among n scans whose pairwise similarity is given (n x n, larger
    = more alike): the reference's pairs within a maximum spanning tree, the tree's others, then each
    scan's `extra` next most similar partners. Reference pairs first, then in scan order."""
    n = len(similarity)
    if n < 2:
        return []
    if n == 3:
        return [(0, 1), (0, 2), (1, 2)]
    s = np.asarray(similarity, dtype=float)
    # A maximum spanning tree = the minimum one of (max - s), every pair an edge (+1 keeps all > 0).
    w = (s.max() - s) + 1.0
    np.fill_diagonal(w, 0.0)
    tree = minimum_spanning_tree(np.triu(w)).toarray()
    chosen = {(min(i, j), max(i, j)) for i, j in zip(*np.nonzero(tree))}
    for i in range(n):
        order = [j for j in np.argsort(-s[i], kind="stable") if j != i]
        added = 0
        for j in order:
            if added == extra:
                break
            e = (min(i, j), max(i, j))
            if e not in chosen:
                chosen.add(e)
                added += 1
    return sorted(chosen, key=lambda e: (e[0] != 0, e))


@dataclass(frozen=True, kw_only=True)
class Edge:
    """A registered pair as the graph sees it: `T` maps scan j's points into scan i's frame."""

    i: int
    j: int
    T: np.ndarray
    verdict: str
    reasons: tuple[str, ...] = ()
    #: What the pair's verdict says to try, and whether it failed because the two scans show different
    #: trees (its reasons then name the other scan: a scan is never placed from such a pair).
    hint: str = ""
    other_tree: bool = False
    loop_error_m: float = float("nan")
    used: bool = False
    weight: float = 1.0


@dataclass(frozen=True, kw_only=True)
class Placement:
    """The graph stage's result for one scan: its transform onto the reference and its verdict.

    Attributes
    ----------
    ok, message, metrics
        `ok` when the scan has a transform (verified or a best guess); `message` the reasons.
    T_ref_scan
        Maps the scan's points into the reference frame (None when it could not be placed).
    verdict
        "verified", "unverified" or "failed".
    reasons, hint
        Why it is not verified, and what to try.
    via
        The scans the placement rests on (its verified neighbours in the graph).
    """

    ok: bool
    message: str
    metrics: tuple[Metric, ...]
    T_ref_scan: np.ndarray | None
    verdict: str
    reasons: tuple[str, ...]
    hint: str
    via: tuple[int, ...] = ()
    edges: tuple[Edge, ...] = field(default=(), repr=False)

    @property
    def T_ref_target(self) -> np.ndarray | None:  # the name every result uses
        return self.T_ref_scan


#: A pair's surface residual below this (m) is not believed: a few lucky pairs, not a better pose.
_MIN_RESIDUAL_M = 1e-4


def edge_weight(evidence: Evidence, graph: GraphParams) -> float:
    """How much a verified pair counts in the joint placement: as a measurement's information,
    the points both stations see over the square of the surfaces' residual at its pose (a pair
    whose surfaces agree to 0.6 mm is measured better than one at 1.2 mm, and far better than one
    seeing half as much), times `graph.coarse_weight` when its fine update was not kept (its pose
    is the coarse one: several millimetres off where the fine ones are one).

    With overlap alone, the loop of three stations let a pair whose fine stage had kept the coarse
    pose (6.7 mm off) pull a pair 3 mm off to 7.3 mm; the residual alone cannot tell which pair of
    a triangle is wrong, but it ranks them (benchmarks/RESULTS.md, issue 20)."""
    residual = evidence.residual_m if np.isfinite(evidence.residual_m) else evidence.noise_m
    residual = max(float(residual), _MIN_RESIDUAL_M) if np.isfinite(residual) else 1e-3
    weight = max(evidence.seen_by_both, 1) / residual ** 2
    return float(weight * (1.0 if evidence.fine_kept else graph.coarse_weight))


def _chain(edges: list[Edge]) -> dict[int, np.ndarray]:
    """Poses by walking a spanning tree of the edges from scan 0 (breadth first)."""
    adjacent: dict[int, list[Edge]] = {}
    for e in edges:  # per scan in the edges' order: the same tree as walking the whole list
        adjacent.setdefault(e.i, []).append(e)
        if e.j != e.i:
            adjacent.setdefault(e.j, []).append(e)
    poses = {0: np.eye(4)}
    frontier = [0]
    while frontier:
        nxt = []
        for a in frontier:
            for e in adjacent.get(a, ()):
                if e.i == a and e.j not in poses:
                    poses[e.j] = poses[a] @ e.T
                    nxt.append(e.j)
                elif e.j == a and e.i not in poses:
                    poses[e.i] = poses[a] @ invert(e.T)
                    nxt.append(e.i)
        frontier = nxt
    return poses


def _reachable(edges: list[Edge]) -> set[int]:
    """The scans the edges connect to scan 0."""
    return set(_chain(edges))


def _skew(v: np.ndarray) -> np.ndarray:
    """[v]x of each row of v (..., 3) -> (..., 3, 3)."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    out[..., 1, 0], out[..., 2, 0], out[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return out


def _rotations(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rodrigues rotations of the rotation vectors w (S, 3) and their right Jacobians J_r (S, 3, 3):
    R(w + d) ~ R(w) Exp(J_r(w) d), what the analytic Jacobian of a rotation vector needs."""
    th = np.linalg.norm(w, axis=1)[:, None, None]
    K = _skew(w)
    K2 = K @ K
    small = th < 1e-6  # series near zero: the closed forms divide by th
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th ** 2 / 6.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th ** 2 / 24.0, (1.0 - np.cos(ths)) / ths ** 2)
    c = np.where(small, 1.0 / 6.0 - th ** 2 / 120.0, (ths - np.sin(ths)) / ths ** 3)
    eye = np.eye(3)
    return eye + a * K + b * K2, eye - b * K + c * K2


def _sigma_points(points: np.ndarray) -> np.ndarray:
    """Six points with the mean and covariance of `points` (mean +- sqrt(3 lambda_k) u_k): a rigid
    disagreement r(s) = A s + b sums its squares over them, each counting len(points) / 6, exactly
    as over all the points (it depends on their mean and second moments only)."""
    mu = points.mean(axis=0)
    lam, U = np.linalg.eigh(np.cov(points.T, bias=True) if len(points) > 1 else np.zeros((3, 3)))
    step = (U * np.sqrt(3.0 * np.clip(lam, 0.0, None))).T  # rows: sqrt(3 lambda_k) u_k
    return np.concatenate([mu + step, mu - step])


def _weighted_loss(kind: str, count: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """scipy's soft-L1 or Cauchy loss, each residual counting `count` times (a sigma point stands
    for len(samples) / 6 points: the loss still sees one point's residual, at the same scale)."""
    def loss(z: np.ndarray) -> np.ndarray:
        if kind == "soft_l1":
            t = 1.0 + z
            rho = np.stack([2.0 * (np.sqrt(t) - 1.0), t ** -0.5, -0.5 * t ** -1.5])
        else:  # cauchy
            t = 1.0 + z
            rho = np.stack([np.log1p(z), 1.0 / t, -1.0 / t ** 2])
        out: np.ndarray = rho * count
        return out
    return loss


class _Problem:
    """The joint solve's residuals and their sparse analytic Jacobian.

    Each free scan k moves by x_k = (w, t): P_k = [R(w) | t] @ P_k0 (a rotation vector and a shift in
    the reference frame, about the start poses P_k0). An edge's residual block is, on the sigma
    points s of scan j, weight * (inv(P_i) P_j s - T_e s): it depends on x_i and x_j only, so the
    Jacobian has 12 non-zeros a row and the solve grows with the edges, not with their square."""

    def __init__(self, poses: dict[int, np.ndarray], edges: list[Edge], samples: dict[int, np.ndarray]) -> None:
        self.free = sorted(k for k in poses if k != 0)
        slot = {0: 0, **{k: s + 1 for s, k in enumerate(self.free)}}  # slot 0: scan 0, fixed
        self.P0 = np.stack([poses.get(0, np.eye(4))] + [poses[k] for k in self.free])
        self.i = np.array([slot[e.i] for e in edges])
        self.j = np.array([slot[e.j] for e in edges])
        sigma = {k: _sigma_points(samples[k]) for k in {e.j for e in edges}}
        S = np.stack([sigma[e.j] for e in edges])  # (E, 6, 3), scan j's frame
        T = np.stack([e.T for e in edges])
        self.target = np.einsum("eab,epb->epa", T[:, :3, :3], S) + T[:, None, :3, 3]
        Pj = self.P0[self.j]
        self.q = np.einsum("eab,epb->epa", Pj[:, :3, :3], S) + Pj[:, None, :3, 3]  # in the reference frame
        w = np.array([e.weight for e in edges], dtype=float)
        self.w = np.sqrt(w / max(float(w.mean()), 1e-12))
        self.count = np.repeat([len(samples[e.j]) / 6.0 for e in edges], 18)
        self.shape = (18 * len(edges), 6 * len(self.free))
        # Each edge's 12 unknowns: scan i's 6, then scan j's; -1 for scan 0's (fixed).
        self._cols = np.where(np.r_[self.i, self.j].reshape(2, -1).T.repeat(6, axis=1) > 0,
                              6 * (np.r_[self.i, self.j].reshape(2, -1).T.repeat(6, axis=1) - 1) + np.tile(np.arange(6), 2), -1)
        pair = (self._cols[:, :, None] >= 0) & (self._cols[:, None, :] >= 0)
        self._pair = pair.ravel()
        self._h_rows = np.broadcast_to(self._cols[:, :, None], pair.shape).ravel()[self._pair]
        self._h_cols = np.broadcast_to(self._cols[:, None, :], pair.shape).ravel()[self._pair]
        self._skew_q = _skew(self.q)

    def _moves(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        v = np.concatenate([np.zeros(6), x]).reshape(-1, 6)
        R, Jr = _rotations(v[:, :3])
        return R, Jr, v[:, 3:]

    def _parts(self, x: np.ndarray) -> tuple[np.ndarray, ...]:
        R, Jr, t = self._moves(x)
        Ri, Rj, R0i = R[self.i], R[self.j], self.P0[self.i, :3, :3]
        # Row vectors: p @ R.T is R p. u = R_j q + t_j - t_i; z = R0i^T (Ri^T u - t0i), in scan i's frame.
        u = self.q @ np.transpose(Rj, (0, 2, 1)) + (t[self.j] - t[self.i])[:, None, :]
        z = (u @ Ri - self.P0[self.i, None, :3, 3]) @ R0i
        return Jr, Ri, Rj, R0i, u, z

    def residuals(self, x: np.ndarray) -> np.ndarray:
        z = self._parts(x)[-1]
        out: np.ndarray = (self.w[:, None, None] * (z - self.target)).ravel()
        return out

    def blocks(self, x: np.ndarray) -> np.ndarray:
        """The Jacobian, one dense 18 x 12 block per edge (its residuals by x_i, x_j)."""
        Jr, Ri, Rj, R0i, u, _ = self._parts(x)
        M = np.transpose(Ri @ R0i, (0, 2, 1))[:, None]  # R0i^T Ri^T: a move in the reference frame, seen in scan i's
        d_wi = M @ _skew(u) @ np.transpose(Jr[self.i], (0, 2, 1))[:, None]  # J_l(w) = J_r(w)^T
        d_wj = -(M @ Rj[:, None]) @ self._skew_q @ Jr[self.j][:, None]
        d_t = np.broadcast_to(M, d_wi.shape)
        blocks = np.concatenate([d_wi, -d_t, d_wj, d_t], axis=3) * self.w[:, None, None, None]
        return blocks.reshape(len(self.i), 18, 12)

    def jacobian(self, x: np.ndarray) -> csr_matrix:
        """The whole Jacobian, sparse: 12 non-zeros a row (6 where scan 0 is an end)."""
        B = self.blocks(x)
        rows = np.broadcast_to(np.arange(self.shape[0]).reshape(-1, 18, 1), B.shape)
        cols = np.broadcast_to(self._cols[:, None, :], B.shape)
        keep = cols >= 0
        return csr_matrix((B[keep], (rows[keep], cols[keep])), shape=self.shape)

    def normal(self, x: np.ndarray, curvature: np.ndarray, slope: np.ndarray) -> tuple[csc_matrix, np.ndarray]:
        """J^T diag(curvature) J and J^T slope, summed edge by edge (a 12 x 12 block each)."""
        B = self.blocks(x)
        H = np.transpose(B, (0, 2, 1)) @ (B * curvature.reshape(-1, 18, 1))
        g_e = np.einsum("erc,er->ec", B, slope.reshape(-1, 18))
        g = np.zeros(self.shape[1])
        keep = self._cols >= 0
        np.add.at(g, self._cols[keep], g_e[keep])
        return coo_matrix((H.ravel()[self._pair], (self._h_rows, self._h_cols)), shape=(self.shape[1],) * 2).tocsc(), g

    def poses(self, x: np.ndarray) -> dict[int, np.ndarray]:
        R, _, t = self._moves(x)
        out = {0: np.eye(4)}
        for s, k in enumerate(self.free, start=1):
            out[k] = make_transform(R[s], t[s]) @ self.P0[s]
        return out


def _loop_errors(poses: dict[int, np.ndarray], edges: list[Edge], samples: dict[int, np.ndarray]) -> np.ndarray:
    """Each edge's disagreement with the poses: the mean distance by which its transform and theirs put
    scan j's sample points apart (m)."""
    out = np.zeros(len(edges))
    for n, e in enumerate(edges):
        rel = invert(poses[e.i]) @ poses[e.j]
        out[n] = float(np.linalg.norm(apply_transform(rel, samples[e.j]) - apply_transform(e.T, samples[e.j]), axis=1).mean())
    return out


def _minimise(pb: _Problem, x: np.ndarray, loss: Callable[[np.ndarray], np.ndarray], scale: float, *, convex: bool,
              max_iter: int = 200, ftol: float = 1e-8) -> np.ndarray:
    """The robust cost 1/2 sum scale^2 rho((f/scale)^2) (scipy's `least_squares` convention) minimised
    from x by Levenberg-Marquardt on sparse normal equations.

    The same minimum scipy's trust region reaches, but each step one sparse solve of 6 unknowns a
    scan (a few milliseconds at 200 scans): scipy's exact solver is dense, its iterative one needs
    hundreds of steps here."""
    def cost(f: np.ndarray) -> float:
        return float(0.5 * scale ** 2 * loss((f / scale) ** 2)[0].sum())

    f = pb.residuals(x)
    c, damping = cost(f), 1e-3
    for _ in range(max_iter):
        z = (f / scale) ** 2
        _, d1, d2 = loss(z)
        # Curvature: rho' alone (IRLS) for a convex loss (soft-L1: fewest steps from a chained start);
        # scipy's rho' + 2 rho'' z, kept positive, for Cauchy (IRLS there needs three times the steps).
        curvature = d1 if convex else np.maximum(d1 + 2.0 * d2 * z, 1e-12 * d1.max())
        H, g = pb.normal(x, curvature, d1 * f)
        scaling = diags(H.diagonal() + 1e-12)
        while True:
            step = spsolve(H + damping * scaling, -g)
            f_new = pb.residuals(x + step)
            c_new = cost(f_new)
            if c_new <= c:
                break
            damping *= 10.0
            if damping > 1e10:  # no step lowers the cost: at its minimum
                return x
        x, f, done = x + step, f_new, c - c_new <= ftol * c
        c, damping = c_new, max(damping / 10.0, 1e-9)
        if done:
            break
    return x


def _solve(poses: dict[int, np.ndarray], edges: list[Edge], samples: dict[int, np.ndarray],
           scale_m: float, refine_scale_m: float) -> tuple[dict[int, np.ndarray], np.ndarray]:
    """Joint poses of every scan in `poses` (scan 0 fixed) minimising, over the edges, how far each
    edge's measured transform and the poses' relative one put the sample points of scan j apart.

    An edge counts by its weight (`edge_weight`: how much of the two scans overlaps and how well
    their surfaces agree at its pose). Soft-L1 at `scale_m` first (safe
    from a chained start), then Cauchy at `refine_scale_m`: an edge that disagrees with the others
    by several times that (a pair the fine stage could not improve) loses its pull. Returns the poses
    and each edge's disagreement (`_loop_errors`).
    """
    if not edges or len(poses) < 2:
        return poses, _loop_errors(poses, edges, samples)
    pb = _Problem(poses, edges, samples)
    x = np.zeros(pb.shape[1])
    for kind, scale in (("soft_l1", scale_m), ("cauchy", refine_scale_m)):
        x = _minimise(pb, x, _weighted_loss(kind, pb.count), scale, convex=kind == "soft_l1")
    solved = pb.poses(x)
    return solved, _loop_errors(solved, edges, samples)


def _worst_edges(edges: list[Edge], res: np.ndarray, max_loop_m: float) -> list[int]:
    """The edges to drop this round, worst first: each edge over `max_loop_m` that shares no scan with a
    worse one over it. A wrong edge drags the scans it joins, so their other edges may be over the limit
    only through it: they wait for the next solve; wrong edges apart are dropped in one round."""
    over = [k for k in np.argsort(-res, kind="stable") if res[k] > max_loop_m]
    out: list[int] = []
    for k in over:
        if not any({edges[k].i, edges[k].j} & {edges[m].i, edges[m].j} for m in over if res[m] > res[k]):
            out.append(int(k))
    return out


@dataclass(frozen=True, kw_only=True)
class PoseGraph:
    """The joint placement of scans from pairwise transforms (`solve_pose_graph`).

    Attributes
    ----------
    poses
        T_0_k of every scan the kept verified edges connect to scan 0 (scan 0: the identity).
    edges
        The edges as given, each with `loop_error_m` (its disagreement with the solved poses; a
        dropped edge's when it was dropped) and `used` (verified and not dropped).
    dropped
        The edges dropped by loop closure, in the order dropped, each with its loop residual (m).
    """

    poses: dict[int, np.ndarray]
    edges: tuple[Edge, ...]
    dropped: tuple[tuple[Edge, float], ...]


def solve_pose_graph(n: int, edges: list[Edge], samples: dict[int, np.ndarray], *, graph: GraphParams,
                     max_loop_m: float) -> PoseGraph:
    """Every scan reachable from scan 0 through verified edges, placed jointly (the module docstring).

    Plain inputs only: `edges[k].T` maps scan j's points into scan i's frame, `verdict` VERIFIED for an
    edge the solve may use, `weight` its information (`edge_weight`); `samples[k]` a few hundred of
    scan k's points in its own frame (any points spanning its extent: an edge's error is how far it
    moves them). A loop that does not close within `max_loop_m` drops its worst edge (and, in the same
    round, any other over the limit sharing no scan with a worse one: `_worst_edges`), and the solve
    goes on from the poses it had (only scans cut off by the drop leave it): not from scratch.
    """
    good = [e for e in edges if e.verdict == VERIFIED]
    dropped: list[tuple[Edge, float]] = []
    poses = _chain(good)
    while True:
        subset = [e for e in good if e.i in poses and e.j in poses]
        poses, res = _solve(poses, subset, samples, graph.loss_scale_m, graph.refine_scale_m)
        if not len(res) or res.max() <= max_loop_m:
            break
        drop = _worst_edges(subset, res, max_loop_m)
        dropped += [(subset[k], float(res[k])) for k in drop]
        good = [e for e in good if not any(e is subset[k] for k in drop)]
        reach = _reachable(good)
        poses = {k: T for k, T in poses.items() if k in reach}  # warm start: the solved poses stay
    loop = {(e.i, e.j): float(r) for e, r in zip(subset, res)}
    loop.update({(e.i, e.j): r for e, r in dropped})
    all_edges = tuple(replace(e, loop_error_m=loop.get((e.i, e.j), float("nan")), used=any(e is g for g in good))
                      for e in edges)
    return PoseGraph(poses=poses, edges=all_edges, dropped=tuple(dropped))


def place_scans(n: int, edges: list[Edge], samples: dict[int, np.ndarray], *, graph: GraphParams,
                max_loop_m: float) -> list[Placement]:
    """Every scan placed onto scan 0 from the registered pairs (see the module docstring).

    `samples[k]` are a few hundred of scan k's points (its own frame): an edge's error is how far it
    moves them. An edge enters the joint solve only when verified; a loop that does not close
    within `max_loop_m` drops its worst edge (that edge's scans then rest on their other edges).
    """
    solved = solve_pose_graph(n, edges, samples, graph=graph, max_loop_m=max_loop_m)
    poses, all_edges, dropped = solved.poses, solved.edges, list(solved.dropped)
    loop = {(e.i, e.j): e.loop_error_m for e in all_edges if np.isfinite(e.loop_error_m)}
    out = []
    for k in range(n):
        mine = [e for e in all_edges if k in (e.i, e.j)]
        via = tuple(sorted({e.j if e.i == k else e.i for e in mine if e.used}))
        if k == 0:
            out.append(Placement(ok=True, message="", metrics=(Metric("verdict", "", VERIFIED),), T_ref_scan=np.eye(4),
                                 verdict=VERIFIED, reasons=(), hint="", via=via, edges=all_edges))
            continue
        if k in poses:
            reasons: tuple[str, ...] = ()
            bad = [(e, r) for e, r in dropped if k in (e.i, e.j)]
            metrics: tuple[Metric, ...] = (Metric("verdict", "", VERIFIED), Metric("placed through scans", "", ", ".join(str(v + 1) for v in via)),
                       Metric("largest edge residual in the joint solve", "m", max((loop.get((e.i, e.j), 0.0) for e in mine if e.used), default=0.0)))
            if bad:
                metrics += (Metric("pairs dropped by loop closure", "", len(bad)),)
            out.append(Placement(ok=True, message="", metrics=metrics, T_ref_scan=poses[k], verdict=VERIFIED,
                                 reasons=reasons, hint="", via=via, edges=all_edges))
            continue
        # Not reachable through verified edges: the best guess is the pair with the reference (or
        # any pair whose other scan is placed), unverified with its reasons; failed with its pair's
        # reasons and hint when a placed scan's pair says it shows another tree.
        other_tree = next((e for e in mine if e.other_tree and (e.i if e.j == k else e.j) in poses), None)
        if other_tree is not None:
            out.append(_failed(other_tree.reasons, other_tree.hint, all_edges))
            continue
        guess, why = None, []
        for e in mine:
            other = e.i if e.j == k else e.j
            T_other = poses.get(other)
            if T_other is None or e.verdict == FAILED:
                continue
            why = list(e.reasons) or [f"its pair with scan {other + 1} does not close a loop of verified pairs"]
            guess = T_other @ (e.T if e.j == k else invert(e.T))
            break
        dropped_here = [f"the pair with scan {(e.i if e.j == k else e.j) + 1} keeps a loop open by {r * 1000:.1f} mm "
                        f"(verify.max_loop_m = {max_loop_m:g})" for e, r in dropped if k in (e.i, e.j)]
        failed_here = [r for e in mine if e.verdict == FAILED for r in _failure(e, k)] if guess is None else []
        reasons = tuple(dict.fromkeys(dropped_here + why + failed_here)) or ("no registered pair links it to the reference",)
        if guess is None:
            out.append(_failed(reasons, joined_hints(e.hint for e in mine if e.other_tree) or _PLACE_HINT, all_edges))
            continue
        out.append(Placement(ok=True, message="; ".join(reasons), metrics=(Metric("verdict", "", UNVERIFIED),),
                             T_ref_scan=guess, verdict=UNVERIFIED, reasons=reasons, hint=_PLACE_HINT, edges=all_edges))
    return out


_PLACE_HINT = "add a station between it and its neighbours, or check that it shows the same tree"


def _failure(e: Edge, k: int) -> tuple[str, ...]:
    """Why scan k's failed pair `e` failed: its own reasons when they name the other scan (two
    different trees), else "its pair with scan N failed: ..."."""
    if e.other_tree:
        return e.reasons
    return (f"its pair with scan {(e.i if e.j == k else e.j) + 1} failed: {'; '.join(e.reasons)}",)


def _failed(reasons: tuple[str, ...], hint: str, edges: tuple[Edge, ...]) -> Placement:
    return Placement(ok=False, message="; ".join(reasons), metrics=(Metric("verdict", "", FAILED),), T_ref_scan=None,
                     verdict=FAILED, reasons=tuple(reasons), hint=hint, edges=edges)
