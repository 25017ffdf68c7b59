"""A scan's surface for point-to-plane terms, and the fine stage's uses of it.

The surface is the scan's voxel centroids with normals oriented towards its scanner (the origin of
the scan's frame). Two stations see the two sides of a thin branch; their oriented normals point
opposite ways, so `surface_pairs` never pairs them — the main bias of point-to-plane alignment
between stations on trees. A narrow gate keeps points past the edge of the other station's view
from pairing with that edge.

Uses: `surface_fitness`, the fine stage's independent acceptance measure, and `refine_along`, a
point-to-plane refinement restricted to the pose directions the sections leave weak.
"""

from __future__ import annotations

import threading
import weakref
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from ..geometry.losses import robust_weight
from ..geometry.normals import NORMAL_K, pca_normals, voxel_downsample
from ..geometry.rigid import apply_transform, make_transform, rotation_from_vector

#: Surface pairs count only when their scanner-facing normals agree this well (cosine).
NORMAL_AGREEMENT = 0.5


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
    #: The pairs computed side by side share a scan's surface: its normals are filled under this lock.
    _lock: threading.Lock = field(default_factory=threading.Lock, compare=False, repr=False)

    def normals_at(self, idx: np.ndarray) -> np.ndarray:
        """Oriented unit normals of `points[idx]`."""
        with self._lock:
            todo = np.unique(idx[np.isnan(self._normals[idx, 0])])
        if len(todo):
            # Outside the lock: two threads may compute the same normals, which are the same values.
            n = pca_normals(self.cloud, self.cloud_tree, self.points[todo], NORMAL_K)
            n *= np.where(np.einsum("ij,ij->i", n, self.points[todo]) > 0, -1.0, 1.0)[:, None]
            with self._lock:
                self._normals[todo] = n
        with self._lock:
            return self._normals[idx]


def surface_of(points: np.ndarray, voxel_m: float, max_points: int | None = None, seed: int = 0) -> Surface:
    """Voxel-subsampled surface of a scan (at most `max_points` used, a seeded random subset)."""
    cloud = voxel_downsample(points, voxel_m)
    return _sampled(cloud, cKDTree(cloud), max_points, seed)


def _sampled(cloud: np.ndarray, cloud_tree: cKDTree, max_points: int | None, seed: int = 0) -> Surface:
    """The surface of the voxel centroids `cloud` (indexed by `cloud_tree`), at most `max_points` of
    them used (a seeded random subset)."""
    pts, tree = cloud, cloud_tree
    if max_points is not None and len(cloud) > max_points:
        pts = cloud[np.sort(np.random.default_rng(seed).choice(len(cloud), max_points, replace=False))]
        tree = cKDTree(pts)
    return Surface(pts, tree, cloud, cloud_tree, np.full((len(pts), 3), np.nan))


_cache: "weakref.WeakKeyDictionary[object, dict]" = weakref.WeakKeyDictionary()
_cache_lock = threading.Lock()


def scan_surface(scan: object, points: np.ndarray, voxel_m: float, max_points: int | None = None) -> Surface:
    """`surface_of(points, ...)` of a scan, made once per (scan, voxel, size) and shared: the
    hypotheses, fine and verify stages of every pair with this scan use the same surface (and the
    normals it has computed so far). `scan` is the immutable object the points belong to."""
    key = (float(voxel_m), max_points)
    with _cache_lock:
        found = _cache.get(scan, {}).get(key)
    if found is None:
        # A sample shares the whole surface's voxel centroids and their tree (a few MB a scan, the
        # same values surface_of would make again).
        whole = scan_surface(scan, points, voxel_m) if max_points is not None else None
        found = (_sampled(whole.cloud, whole.cloud_tree, max_points) if whole is not None
                 else surface_of(points, voxel_m))
        with _cache_lock:
            _cache.setdefault(scan, {})[key] = found
    return found


#: A point's neighbours span a surface (not one scan line) when their spread across their longest
#: direction is at least this share of their spread along it (as variances: the middle eigenvalue of
#: their covariance over the largest; 0.03 is 17 % as a length). On one scan line the neighbours
#: lie in the plane of that line's rays, range noise included, so their plane fits them exactly.
PLANAR_MIN = 0.03


def noise_floor(surf: Surface, samples: int = 2000) -> float:
    """The surface's own roughness: median distance of its points to the plane through their
    neighbours (what a perfect registration's residual cannot go below), metres; over the points
    whose neighbours span a surface (`PLANAR_MIN`). Neighbours along one scan line (far ground, a
    twig, where the lines are dense along and sparse across) lie in one plane with their noise and
    gave a floor of 0.009 mm (the paper preset keeps the ground). NaN when no point's do."""
    cloud = surf.cloud
    if len(cloud) < NORMAL_K + 1:
        return float("nan")
    at = cloud[np.linspace(0, len(cloud) - 1, min(samples, len(cloud))).astype(np.int64)]
    _, nb = surf.cloud_tree.query(at, k=NORMAL_K)
    q = cloud[nb]
    mean = q.mean(axis=1)
    c = q - mean[:, None, :]
    spread = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", c, c))  # ascending, per point
    planar = spread[:, 1] >= PLANAR_MIN * spread[:, 2]
    if not planar.any():
        return float("nan")
    n = pca_normals(cloud, surf.cloud_tree, at[planar], NORMAL_K)
    return float(np.median(np.abs(np.einsum("ij,ij->i", at[planar] - mean[planar], n))))


def surface_pairs(ref: Surface, tgt: Surface, T: np.ndarray, gate_m: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Target points (mapped by T) with a reference neighbour within the gate whose normal agrees.

    Returns (target indices, mapped target points, point-to-plane residuals) of the kept pairs.
    """
    moved = apply_transform(T, tgt.points)
    d, j = ref.tree.query(moved, distance_upper_bound=gate_m)
    ok = np.flatnonzero(np.isfinite(d))
    nr = ref.normals_at(j[ok])
    agree = np.einsum("ij,ij->i", nr, tgt.normals_at(ok) @ T[:3, :3].T) > NORMAL_AGREEMENT
    ok, nr = ok[agree], nr[agree]
    r = np.einsum("ij,ij->i", moved[ok] - ref.points[j[ok]], nr)
    return ok, moved[ok], r


def surface_fitness(ref: Surface, tgt: Surface, T: np.ndarray, gate_m: float, tolerance_m: float) -> float:
    """Independent alignment measure: the fraction of the target's surface points lying on the
    reference's surface under `T` — a reference point within `gate_m` whose scanner-facing normal
    agrees, and a point-to-plane distance below `tolerance_m`. Higher is better.

    Only where the two stations saw the same surface can this be high, so its value is small
    (0.1-0.2 on our simulated trees); what matters is that it drops clearly once the target is
    off by a centimetre or more.
    """
    _, _, r = surface_pairs(ref, tgt, T, gate_m)
    return float(np.count_nonzero(np.abs(r) < tolerance_m) / max(len(tgt.points), 1))


def trimmed_residuals(ref: Surface, tgt: Surface, poses: list[np.ndarray], gate_m: float, trim: float,
                      min_pair_ratio: float = 0.5) -> np.ndarray:
    """Alignment measure that ranks millimetres, for comparing candidate poses (metres, lower is better).

    For each pose: the target's surface points paired with the reference's (within `gate_m`,
    scanner-facing normals agreeing), their absolute point-to-plane distances sorted, and the mean
    of the K smallest, K being `trim` times the fewest pairs any pose has. A fixed K keeps the
    poses comparable (a mean over each pose's own pairs favours a pose that pairs fewer points);
    trimming drops points the other station saw differently (edges, leaves). A pose with fewer
    than `min_pair_ratio` times the most pairs is far off and gets infinity (it would otherwise
    shrink K to a handful of lucky pairs). With thousands of pairs the mean resolves differences
    well below a millimetre.
    """
    res = [np.sort(np.abs(surface_pairs(ref, tgt, T, gate_m)[2])) for T in poses]
    n = np.array([len(r) for r in res])
    valid = n >= min_pair_ratio * n.max()
    k = int(trim * n[valid].min())
    if k < 10:
        return np.full(len(poses), np.inf)
    return np.array([r[:k].mean() if v else np.inf for r, v in zip(res, valid)])


# Nine parameters: the two surfaces, the pose, the directions refined (centre, basis) and the three
# numbers of one point-to-plane run (gate, loss scale, iterations) besides its tolerance.
def refine_along(ref: Surface, tgt: Surface, T: np.ndarray, centre: np.ndarray, basis: np.ndarray,
                 gate_m: float, loss_scale_m: float, iterations: int, tol_m: float = 1e-5) -> np.ndarray:
    """Point-to-plane refinement of `T` along the pose directions in `basis` only.

    Returns the coefficients y of the refinement: it is `pose_update(basis @ y, centre) @ T`.
    Stops early once a step moves the paired points by less than `tol_m` on average.

    The sections fix the other directions to millimetres. Point-to-plane alignment of the whole
    target against the reference's surface (twigs, leaves, ground: all that the sections ignore)
    uses only pairs within `gate_m` whose oriented normals agree, with a Cauchy loss of scale
    `loss_scale_m`; it is used only where the sections are weak.
    """
    B = basis
    T0 = T
    y_total = np.zeros(B.shape[1])
    for _ in range(iterations):
        T = pose_update(B @ y_total, centre) @ T0
        idx, q, r = surface_pairs(ref, tgt, T, gate_m)
        if len(idx) < 10 * B.shape[1]:
            break
        n = tgt.normals_at(idx) @ T[:3, :3].T
        w = robust_weight(r, loss_scale_m, "cauchy")
        # d r / d pose uses the reference normal; the target's (agreeing) normal is close to it.
        J = np.c_[np.cross(q - centre, n), n] @ B
        H = J.T @ (J * w[:, None])
        try:
            y = -np.linalg.solve(H + 1e-12 * np.eye(len(H)), J.T @ (w * r))
        except np.linalg.LinAlgError:
            break
        y_total = y_total + y
        if mean_move(pose_update(B @ y, centre), q) < tol_m:
            break
    return y_total


#: Narrowing alignment: pairing gates (m), widest first, each run for `GATE_ITERATIONS`, then the final
#: narrow gate. Directions still carrying a coarse error (centimetres) would never be seen by a narrow
#: gate alone.
GATES_M = (0.1, 0.05, 0.03)
GATE_ITERATIONS = 10


# Ten parameters: those of `refine_along` plus the narrowing schedule (gates, iterations per gate).
def align_narrowing(ref: Surface, tgt: Surface, T: np.ndarray, centre: np.ndarray, basis: np.ndarray,
                    final_gate_m: float, final_iterations: int, loss_scale_m: float,
                    gates_m: tuple[float, ...] = GATES_M, gate_iterations: int = GATE_ITERATIONS) -> np.ndarray:
    """`T` refined point-to-plane along the pose directions `basis`, the pairing gate narrowing from
    `gates_m` (each for `gate_iterations`) down to `final_gate_m` (for `final_iterations`)."""
    for gate in gates_m + (final_gate_m,):
        final = gate == final_gate_m
        y = refine_along(ref, tgt, T, centre, basis, max(gate, final_gate_m), max(loss_scale_m, gate / 4),
                         final_iterations if final else gate_iterations)
        T = pose_update(basis @ y, centre) @ T
    return T


def pose_update(x: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """4x4 of the pose parameters x = (rotation vector about `centre`, translation)."""
    R = rotation_from_vector(x[:3])
    return make_transform(R, centre - R @ centre + x[3:])


def mean_move(U: np.ndarray, pts: np.ndarray) -> float:
    """Mean distance the points move under the 4x4 `U`."""
    return float(np.linalg.norm(apply_transform(U, pts) - pts, axis=1).mean())
