"""The joint placement of all stations (`verify.graph.solve_pose_graph`): time and accuracy on
synthetic pose graphs, against the previous implementation.

Stations on a grid (10 m apart, random headings, tilts of a few tenths of a degree), 300 sample
points per station spread over 15 m round it, edges to the grid neighbours and the diagonals, each
measured from the truth with noise (1 mm and 0.005 deg per axis), and a few wrong edges (2-6 cm
and 0.05-0.5 deg off) that the loops must drop. Per graph: the time of the previous solver (dense
finite differences, every dropped edge re-solved from scratch) and of the new one (sparse analytic
Jacobian, compact residuals, warm start after a drop) as ratios to the new one at the smallest
graph, each station's error against the truth (mean displacement of its samples, mm; rotation,
deg), and which edges were dropped.

    python benchmarks/bench_graph.py                 # 9, 16, 36, 60, 200 stations; previous solver up to 16
    python benchmarks/bench_graph.py --old-max 36    # the previous solver at 36 too (tens of minutes)
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from treereg_core.geometry.rigid import (apply_transform, invert, make_transform, mean_displacement,  # noqa: E402
                                         rotation_error_deg, rotation_from_vector)
from treereg_core.params import GraphParams  # noqa: E402
from treereg_core.verify.evidence import VERIFIED  # noqa: E402
from treereg_core.verify.graph import Edge, solve_pose_graph  # noqa: E402

GRIDS = {9: (3, 3), 16: (4, 4), 36: (6, 6), 60: (6, 10), 200: (10, 20)}
MAX_LOOP_M = 0.01  # wrong edges of centimetres must go, right ones (1-3 mm, up to 6 mm at 15 m) stay


# ---- the previous implementation, kept here only as the baseline of this comparison --------------
# treereg_core/verify/graph.py as of commit 5808760: a dense finite-difference least-squares solve
# over all poses on every sample point, re-chained and re-solved from scratch after each drop.
def _old_chain(n: int, edges: list[Edge]) -> dict[int, np.ndarray]:
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


def _old_solve(poses: dict[int, np.ndarray], edges: list[Edge], samples: dict[int, np.ndarray],
               scale_m: float, refine_scale_m: float) -> tuple[dict[int, np.ndarray], np.ndarray]:
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


def old_solve_pose_graph(n: int, edges: list[Edge], samples: dict[int, np.ndarray], *, graph: GraphParams,
                         max_loop_m: float) -> tuple[dict[int, np.ndarray], list[tuple[Edge, float]]]:
    good = [e for e in edges if e.verdict == VERIFIED]
    dropped: list[tuple[Edge, float]] = []
    while True:
        poses = _old_chain(n, good)
        subset = [e for e in good if e.i in poses and e.j in poses]
        poses, res = _old_solve(poses, subset, samples, graph.loss_scale_m, graph.refine_scale_m)
        if not len(res) or res.max() <= max_loop_m:
            return poses, dropped
        worst = int(np.argmax(res))
        dropped.append((subset[worst], float(res[worst])))
        good = [e for e in good if e is not subset[worst]]
# ---- end of the previous implementation -----------------------------------------------------------


@dataclass
class Graph:
    n: int
    truth: list[np.ndarray]  # T_0_k
    edges: list[Edge]
    samples: dict[int, np.ndarray]
    wrong: set[tuple[int, int]]


def _noisy(rng: np.random.Generator, rot_deg: float, shift_m: float) -> np.ndarray:
    return make_transform(rotation_from_vector(np.radians(rng.normal(0.0, rot_deg, 3))), rng.normal(0.0, shift_m, 3))


def make_graph(n: int, seed: int, spacing_m: float = 10.0) -> Graph:
    """A grid survey of n stations (GRIDS), its edges measured with noise, a few of them wrong."""
    rows, cols = GRIDS[n]
    rng = np.random.default_rng(seed)
    world = []
    for r in range(rows):
        for c in range(cols):
            R = rotation_from_vector(np.r_[np.radians(rng.normal(0, 0.3, 2)), rng.uniform(-np.pi, np.pi)])
            world.append(make_transform(R, [c * spacing_m + rng.normal(0, 1), r * spacing_m + rng.normal(0, 1), rng.normal(0, 0.5)]))
    truth = [invert(world[0]) @ T for T in world]
    samples = {k: np.c_[rng.uniform(-15, 15, (300, 2)), rng.uniform(0, 20, 300)] for k in range(n)}
    pairs = [(r * cols + c, rr * cols + cc) for r in range(rows) for c in range(cols)
             for rr, cc in ((r, c + 1), (r + 1, c), (r + 1, c + 1), (r + 1, c - 1)) if rr < rows and 0 <= cc < cols]
    n_wrong = max(1, len(pairs) // 40)
    wrong_at = set(rng.choice(len(pairs), n_wrong, replace=False).tolist())
    edges, wrong = [], set()
    for k, (i, j) in enumerate(pairs):
        T = invert(truth[i]) @ truth[j] @ _noisy(rng, 0.005, 0.001)
        if k in wrong_at:  # a wrong match: centimetres and a fraction of a degree off
            off = rng.uniform(0.02, 0.06) * rng.choice([-1, 1], 3) / np.sqrt(3)
            T = make_transform(rotation_from_vector(np.radians(rng.uniform(0.05, 0.5)) * np.r_[0, 0, 1]), off) @ T
            wrong.add((i, j))
        edges.append(Edge(i=i, j=j, T=T, verdict=VERIFIED, weight=float(rng.uniform(0.5, 2.0))))
    return Graph(n, truth, edges, samples, wrong)


@dataclass
class Result:
    seconds: float
    disp_mm: np.ndarray
    rot_deg: np.ndarray
    dropped: set[tuple[int, int]]
    poses: dict[int, np.ndarray]


def _errors(g: Graph, poses: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    disp = np.array([mean_displacement(poses[k], g.truth[k], g.samples[k]) * 1000 if k in poses else np.inf
                     for k in range(1, g.n)])
    rot = np.array([rotation_error_deg(poses[k], g.truth[k]) if k in poses else np.inf for k in range(1, g.n)])
    return disp, rot


def run(g: Graph, old: bool) -> Result:
    t0 = time.perf_counter()
    if old:
        poses, dropped = old_solve_pose_graph(g.n, g.edges, g.samples, graph=GraphParams(), max_loop_m=MAX_LOOP_M)
    else:
        sol = solve_pose_graph(g.n, g.edges, g.samples, graph=GraphParams(), max_loop_m=MAX_LOOP_M)
        poses, dropped = sol.poses, list(sol.dropped)
    seconds = time.perf_counter() - t0
    disp, rot = _errors(g, poses)
    return Result(seconds, disp, rot, {(e.i, e.j) for e, _ in dropped}, poses)


def _cell(r: Result | None, base: float) -> tuple[str, str, str]:
    if r is None:
        return "not run", "", ""
    return (f"{r.seconds / base:.1f}", f"{np.max(r.disp_mm):.2f} / {np.median(r.disp_mm):.2f}",
            f"{np.max(r.rot_deg):.4f} / {np.median(r.rot_deg):.4f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=sorted(GRIDS), choices=sorted(GRIDS))
    ap.add_argument("--old-max", type=int, default=16, help="run the previous solver up to this many stations")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rows = []
    for n in args.sizes:
        g = make_graph(n, args.seed + n)
        new = run(g, old=False)
        old = run(g, old=True) if n <= args.old_max else None
        rows.append((n, g, new, old))
        print(f"{n} stations, {len(g.edges)} edges: new {new.seconds:.3f} s"
              + (f", previous {old.seconds:.2f} s" if old else ""), flush=True)
    base = rows[0][2].seconds
    print(f"\nTimes as ratios to the new solver at {rows[0][0]} stations ({base:.3f} s).\n")
    print("| stations | edges (wrong) | time, new | time, previous | error new, mm max / median | deg max / median "
          "| error previous, mm max / median | deg max / median | new vs previous, mm max "
          "| wrong edges dropped (right ones dropped), new; previous |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for n, g, new, old in rows:
        t_new, d_new, r_new = _cell(new, base)
        t_old, d_old, r_old = _cell(old, base)
        drops = f"{len(g.wrong & new.dropped)}/{len(g.wrong)} ({len(new.dropped - g.wrong)})"
        if old is not None:
            drops += f"; {len(g.wrong & old.dropped)}/{len(g.wrong)} ({len(old.dropped - g.wrong)})"
        apart = "" if old is None else f"{max(mean_displacement(new.poses[k], old.poses[k], g.samples[k]) for k in range(1, n)) * 1000:.2f}"
        print(f"| {n} | {len(g.edges)} ({len(g.wrong)}) | {t_new} | {t_old} | {d_new} | {r_new} | {d_old} | {r_old} | {apart} "
              f"| {drops} |")


if __name__ == "__main__":
    main()
