"""Many stations, one consistent answer: which pairs to register, and every scan placed jointly.

Pairs. Two scans are registered together when their projection sequences look alike (the coarse
similarity of the paper's 2.1.3): the pairs of a maximum spanning tree over that similarity, so
every scan is connected, plus each scan's next most similar partner, so loops exist to check
(with three scans: all three pairs). The reference's pairs come first, in scan order (the pairs
the paper registers, 2->1, 3->1, ...).

Placement. Every verified pair is an edge of a pose graph. Loops of edges must close: the product
of the transforms around a loop is the identity for right registrations; an edge that keeps a loop
open is dropped (the one with the largest residual in a robust joint solve). The poses of all scans
are then solved together (scipy's `least_squares`, soft-L1 loss), scan 1 fixed: a scan opposite
the reference is placed through its neighbours, and small pairwise errors are averaged out rather
than chained. A scan not reachable through verified edges keeps its best guess, unverified.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse.csgraph import minimum_spanning_tree

from ..geometry.rigid import apply_transform, invert, make_transform, rotation_from_vector
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


def _chain(n: int, edges: list[Edge]) -> dict[int, np.ndarray]:
    """Poses by walking a spanning tree of the edges from scan 0 (breadth first)."""
    poses = {0: np.eye(4)}
    frontier = [0]
    while frontier:
        nxt = []
        for a in frontier:
            for e in edges:
                if e.i == a and e.j not in poses:
                    poses[e.j] = poses[a] @ e.T
                    nxt.append(e.j)
                elif e.j == a and e.i not in poses:
                    poses[e.i] = poses[a] @ invert(e.T)
                    nxt.append(e.i)
        frontier = nxt
    return poses


def _solve(poses: dict[int, np.ndarray], edges: list[Edge], samples: dict[int, np.ndarray],
           scale_m: float, refine_scale_m: float) -> tuple[dict[int, np.ndarray], np.ndarray]:
    """Joint poses of every scan in `poses` (scan 0 fixed) minimising, over the edges, how far each
    edge's measured transform and the poses' relative one put the sample points of scan j apart.

    An edge counts by its weight (`edge_weight`: how much of the two scans overlaps and how well
    their surfaces agree at its pose). Soft-L1 at `scale_m` first (safe
    from a chained start), then Cauchy at `refine_scale_m`: an edge that disagrees with the others
    by several times that (a pair the fine stage could not improve) loses its pull.
    """
    free = sorted(k for k in poses if k != 0)
    if not free:
        return poses, np.zeros(len(edges))
    index = {k: n for n, k in enumerate(free)}

    def pose(x: np.ndarray, k: int) -> np.ndarray:
        if k == 0:
            return np.eye(4)
        v = x[6 * index[k]: 6 * index[k] + 6]
        return make_transform(rotation_from_vector(v[:3]), v[3:]) @ poses[k]

    w = np.sqrt(np.array([e.weight for e in edges]) / max(np.mean([e.weight for e in edges]), 1e-12))

    def residuals(x: np.ndarray) -> np.ndarray:
        out = []
        for wk, e in zip(w, edges):
            rel = invert(pose(x, e.i)) @ pose(x, e.j)
            out.append(wk * (apply_transform(rel, samples[e.j]) - apply_transform(e.T, samples[e.j])).ravel())
        return np.concatenate(out)

    x = least_squares(residuals, np.zeros(6 * len(free)), loss="soft_l1", f_scale=scale_m, max_nfev=200).x
    x = least_squares(residuals, x, loss="cauchy", f_scale=refine_scale_m, max_nfev=200).x
    solved = {k: pose(x, k) for k in poses}
    r = residuals(x).reshape(len(edges), -1, 3) / w[:, None, None]
    return solved, np.linalg.norm(r, axis=2).mean(axis=1)


def place_scans(n: int, edges: list[Edge], samples: dict[int, np.ndarray], *, graph: GraphParams,
                max_loop_m: float) -> list[Placement]:
    """Every scan placed onto scan 0 from the registered pairs (see the module docstring).

    `samples[k]` are a few hundred of scan k's points (its own frame): an edge's error is how far it
    moves them. An edge enters the joint solve only when verified; a loop that does not close
    within `max_loop_m` drops its worst edge (that edge's scans then rest on their other edges).
    """
    good = [e for e in edges if e.verdict == VERIFIED]
    dropped: list[tuple[Edge, float]] = []
    poses: dict[int, np.ndarray] = {}
    res = np.zeros(0)
    while True:
        poses = _chain(n, good)
        subset = [e for e in good if e.i in poses and e.j in poses]
        poses, res = _solve(poses, subset, samples, graph.loss_scale_m, graph.refine_scale_m)
        if not len(res) or res.max() <= max_loop_m:
            break
        worst = int(np.argmax(res))
        dropped.append((subset[worst], float(res[worst])))
        good = [e for e in good if e is not subset[worst]]
    loop = {(e.i, e.j): float(r) for e, r in zip([e for e in good if e.i in poses and e.j in poses], res)}
    loop.update({(e.i, e.j): r for e, r in dropped})
    all_edges = tuple(replace(e, loop_error_m=loop.get((e.i, e.j), float("nan")), used=any(e is g for g in good))
                      for e in edges)
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
            metrics = (Metric("verdict", "", VERIFIED), Metric("placed through scans", "", ", ".join(str(v + 1) for v in via)),
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
