"""Procedural trees as analytic primitives, for the ray-cast scanner of `simulate_scanner`.

A tree is a trunk and 1-3 orders of branches, each a chain of short tapered cylinders (cone
frusta) so that it can curve, with a sphere at every joint (it closes the wedge a bend opens
between two segments, and rounds the tips); leaves are small disks on the outer orders. A scene
adds a ground plane (clipped to a disk around the tree) and optionally a second tree.

Everything is numpy arrays (one row per primitive), so that a whole scene can be moved into a
scanner's frame with one matrix product and ray-cast in bulk. Units are metres; the main tree's
base is at the world origin, z up.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..geometry.rigid import apply_transform

#: Part labels carried by every primitive and by every simulated point.
LABEL_GROUND = 0
LABEL_TRUNK = 1
LABEL_BRANCH = (2, 3, 4)  # branching orders 1, 2, 3
LABEL_LEAF = 5
LABEL_OTHER_TREE = 6
LABEL_NAMES: dict[int, str] = {
    -1: "unknown",
    0: "ground",
    1: "trunk",
    2: "branch order 1",
    3: "branch order 2",
    4: "branch order 3",
    5: "leaf",
    6: "other tree",
}

# Segment lengths per order (trunk, 1, 2, 3): short enough that a chain can curve smoothly and that
# each segment's angular bounding box stays tight.
_SEGMENTS = (None, 12, 6, 4)  # segments per branch of order 1, 2, 3 (the trunk uses _TRUNK_SEG_M)
_TRUNK_SEG_M = 0.3
_MIN_RADIUS_M = 0.003


@dataclass(frozen=True, eq=False)
class Cylinders:
    """Cone frusta: axis from `p0` to `p1` (M x 3), radius `r0` at p0 and `r1` at p1 (M,)."""

    p0: np.ndarray
    p1: np.ndarray
    r0: np.ndarray
    r1: np.ndarray
    label: np.ndarray

    def __len__(self) -> int:
        return int(self.p0.shape[0])


@dataclass(frozen=True, eq=False)
class Spheres:
    """Spheres (joints and tips of the cylinder chains): `centre` (S x 3), `radius` (S,)."""

    centre: np.ndarray
    radius: np.ndarray
    label: np.ndarray

    def __len__(self) -> int:
        return int(self.centre.shape[0])


@dataclass(frozen=True, eq=False)
class Disks:
    """Flat round leaves: `centre` (K x 3), unit `normal` (K x 3), `radius` (K,)."""

    centre: np.ndarray
    normal: np.ndarray
    radius: np.ndarray
    label: np.ndarray

    def __len__(self) -> int:
        return int(self.centre.shape[0])


@dataclass(frozen=True, eq=False)
class GroundPlane:
    """The plane n . x = offset (unit `normal` pointing up), kept within `radius_m` of `centre`."""

    normal: np.ndarray
    offset: float
    centre: np.ndarray
    radius_m: float

    def height_at(self, xy: np.ndarray) -> np.ndarray:
        """z of the plane above the points `xy` (... x 2), world frame."""
        n = self.normal
        return (self.offset - xy[..., 0] * n[0] - xy[..., 1] * n[1]) / n[2]


@dataclass(frozen=True, eq=False)
class Scene:
    """Everything a scanner can hit, as primitive arrays."""

    cylinders: Cylinders
    spheres: Spheres
    disks: Disks
    ground: GroundPlane | None = None

    def transformed(self, T: np.ndarray) -> "Scene":
        """The scene mapped by the rigid 4x4 `T` (e.g. into a scanner's frame)."""
        R = T[:3, :3]
        c, s, d = self.cylinders, self.spheres, self.disks
        ground = None
        if self.ground is not None:
            g = self.ground
            n = R @ g.normal
            centre = apply_transform(T, g.centre[None])[0]
            # n'.x' = n.x + n'.t for x' = R x + t
            ground = GroundPlane(n, float(g.offset + n @ T[:3, 3]), centre, g.radius_m)
        return Scene(
            Cylinders(apply_transform(T, c.p0), apply_transform(T, c.p1), c.r0, c.r1, c.label),
            Spheres(apply_transform(T, s.centre), s.radius, s.label),
            Disks(apply_transform(T, d.centre), d.normal @ R.T, d.radius, d.label),
            ground,
        )

    def points_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds (lo, hi) of the tree primitives (ground excluded)."""
        c, s, d = self.cylinders, self.spheres, self.disks
        lo = np.min(np.vstack([c.p0, c.p1, s.centre - s.radius[:, None], d.centre - d.radius[:, None]]), axis=0)
        hi = np.max(np.vstack([c.p0, c.p1, s.centre + s.radius[:, None], d.centre + d.radius[:, None]]), axis=0)
        return lo, hi


def merge_scenes(scenes: list[Scene], ground: GroundPlane | None) -> Scene:
    """One scene from several trees' primitives, with the given ground."""
    cat = np.concatenate
    return Scene(
        Cylinders(*(cat([getattr(s.cylinders, f) for s in scenes]) for f in ("p0", "p1", "r0", "r1", "label"))),
        Spheres(*(cat([getattr(s.spheres, f) for s in scenes]) for f in ("centre", "radius", "label"))),
        Disks(*(cat([getattr(s.disks, f) for s in scenes]) for f in ("centre", "normal", "radius", "label"))),
        ground,
    )


@dataclass(frozen=True)
class TreeShape:
    """The options of one procedural tree (all lengths in metres, angles in degrees)."""

    height_m: float = 12.0
    dbh_m: float = 0.3
    orders: int = 3
    bent: bool = False
    lean_deg: float = 0.0
    leaves: bool = False
    leaf_radius_m: tuple[float, float] = (0.015, 0.03)
    leaves_per_m: float = 25.0


@dataclass(frozen=True, eq=False)
class Limbs:
    """Where every primitive of a tree sits on its branching structure, so that wind can move the
    small branches on their own (`simulate.wind`).

    Flutter branches are the branches of order 2 and up, numbered 0..B-1 over all of them. Per
    primitive (cylinders, spheres, disks, in the scene's order): the flutter branch it lies on (-1
    for the trunk and order-1 branches, which move with the stem's bend) and the fraction of that
    branch's length where it sits (`cyl_t0`, `cyl_t1`: at a cylinder's two ends). Per flutter
    branch: the flutter branch it sprouts from (`parent`, -1 when it sprouts from an order-1
    branch) and at which fraction of the parent (`attach`).
    """

    cyl_branch: np.ndarray
    cyl_t0: np.ndarray
    cyl_t1: np.ndarray
    sph_branch: np.ndarray
    sph_t: np.ndarray
    disk_branch: np.ndarray
    disk_t: np.ndarray
    parent: np.ndarray
    attach: np.ndarray

    @property
    def n_branches(self) -> int:
        return int(self.parent.shape[0])


@dataclass(frozen=True, eq=False)
class TreeInfo:
    """What was drawn for one tree: where it stands and its measured-like attributes. `limbs`
    places every primitive of `scene` on the branching structure (for wind)."""

    base_m: np.ndarray
    shape: TreeShape
    crown_base_m: float
    lean_axis_deg: float
    n_branches: tuple[int, ...]
    n_leaves: int
    scene: Scene = field(repr=False)
    limbs: Limbs | None = field(default=None, repr=False)

    def to_dict(self) -> dict:
        s = self.shape
        return {
            "base_m": [float(v) for v in self.base_m],
            "height_m": s.height_m,
            "dbh_m": s.dbh_m,
            "orders": s.orders,
            "bent": s.bent,
            "lean_deg": s.lean_deg,
            "leaves": s.leaves,
            "crown_base_m": self.crown_base_m,
            "branches_per_order": list(self.n_branches),
            "leaves_count": self.n_leaves,
        }


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _perpendicular_frame(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (B x 3 each) perpendicular to the unit directions `u` and to each other."""
    helper = np.where(np.abs(u[:, 2:3]) < 0.9, np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]))
    e1 = _unit(np.cross(u, helper))
    e2 = np.cross(u, e1)
    return e1, e2


def _trunk_radius(s: np.ndarray, height: float, dbh: float) -> np.ndarray:
    """Radius along the trunk at arc length `s`: DBH at 1.3 m, tapering to a twig at the top, with a
    butt swell near the ground (real stems flare)."""
    rel = np.clip(s / height, 0.0, 1.0)
    rel_bh = min(1.3 / height, 0.5)  # a shrub lower than breast height keeps its DBH at mid height
    r = 0.5 * dbh * ((1.0 - rel) / (1.0 - rel_bh)) ** 0.85
    r = r * (1.0 + 0.25 * np.exp(-np.maximum(s, 0.0) / 0.35))
    return np.maximum(r, _MIN_RADIUS_M)


@dataclass
class _Chains:
    """Branch axes of one order, grown together: axis points (B x (n+1) x 3), radii (B x (n+1))."""

    points: np.ndarray
    radii: np.ndarray
    length: np.ndarray
    #: Per branch: the parent branch it sprouts from and at which fraction of it (None for order 1).
    parent: np.ndarray | None = None
    attach: np.ndarray | None = None

    def point_at(self, b: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Axis point, direction and radius of branches `b` at fraction `f` of their length."""
        n = self.points.shape[1] - 1
        x = np.clip(f, 0.0, 1.0) * n
        k = np.minimum(np.floor(x).astype(int), n - 1)
        w = (x - k)[:, None]
        p0 = self.points[b, k]
        p1 = self.points[b, k + 1]
        r = self.radii[b, k] * (1 - w[:, 0]) + self.radii[b, k + 1] * w[:, 0]
        return p0 * (1 - w) + p1 * w, _unit(p1 - p0), r


def _grow(start: np.ndarray, direction: np.ndarray, length: np.ndarray, r_base: np.ndarray,
          n_seg: int, wobble: float, tropism: np.ndarray, rng: np.random.Generator) -> _Chains:
    """Grow B branches at once as chains of `n_seg` segments.

    Each step turns the direction by a random perpendicular nudge (`wobble`, radians per segment)
    and towards +z (`tropism` > 0, the branch bends up) or -z (< 0, it droops); the radius tapers
    linearly from `r_base` to a twig.
    """
    B = start.shape[0]
    seg = (length / n_seg)[:, None]
    pts = np.empty((B, n_seg + 1, 3))
    pts[:, 0] = start
    d = _unit(direction)
    up = np.array([0.0, 0.0, 1.0])
    for k in range(n_seg):  # loop over segments (<= 12), vectorised over branches
        pts[:, k + 1] = pts[:, k] + d * seg
        nudge = rng.normal(0.0, wobble, (B, 3))
        nudge -= np.sum(nudge * d, axis=1, keepdims=True) * d
        d = _unit(d + nudge + tropism[:, None] * up)
    frac = np.linspace(0.0, 1.0, n_seg + 1)
    tip = np.maximum(0.15 * r_base, _MIN_RADIUS_M)
    radii = r_base[:, None] * (1 - frac) + tip[:, None] * frac
    return _Chains(pts, np.maximum(radii, _MIN_RADIUS_M), length)


def _chain_primitives(ch: _Chains, label: int) -> tuple[Cylinders, Spheres]:
    """Cylinders between consecutive axis points and a sphere at every inner joint and at the tip."""
    p0 = ch.points[:, :-1].reshape(-1, 3)
    p1 = ch.points[:, 1:].reshape(-1, 3)
    r0 = ch.radii[:, :-1].reshape(-1)
    r1 = ch.radii[:, 1:].reshape(-1)
    centre = ch.points[:, 1:].reshape(-1, 3)
    radius = ch.radii[:, 1:].reshape(-1)
    lab_c = np.full(len(r0), label, dtype=np.int8)
    return Cylinders(p0, p1, r0, r1, lab_c), Spheres(centre, radius, lab_c.copy())


def _children(parent: _Chains, per_m: float, max_per_branch: int, length_frac: tuple[float, float],
              angle_deg: tuple[float, float], radius_frac: tuple[float, float], order: int,
              rng: np.random.Generator) -> _Chains | None:
    """Branches of the next order along `parent`: position, azimuth about the parent, insertion
    angle, length (shorter towards the parent's tip) and base radius (a fraction of the parent's)."""
    counts = np.clip(np.round(per_m * parent.length * rng.uniform(0.7, 1.3, len(parent.length))), 1,
                     max_per_branch).astype(int)
    b = np.repeat(np.arange(len(counts)), counts)
    if b.size == 0:
        return None
    f = rng.uniform(0.15, 0.9, b.size)
    p, u, r_par = parent.point_at(b, f)
    e1, e2 = _perpendicular_frame(u)
    az = rng.uniform(0, 2 * np.pi, b.size)
    ang = np.radians(rng.uniform(*angle_deg, b.size))
    side = np.cos(az)[:, None] * e1 + np.sin(az)[:, None] * e2
    d = np.cos(ang)[:, None] * u + np.sin(ang)[:, None] * side
    length = parent.length[b] * rng.uniform(*length_frac, b.size) * (1.0 - 0.6 * f)
    length = np.maximum(length, 0.08)
    r = np.maximum(r_par * rng.uniform(*radius_frac, b.size), _MIN_RADIUS_M)
    tropism = rng.uniform(-0.02, 0.06, b.size)
    ch = _grow(p, d, length, r, _SEGMENTS[order], 0.08, tropism, rng)
    return replace(ch, parent=b, attach=f)


def _leaves(chains: list[_Chains], shape: TreeShape, rng: np.random.Generator) -> tuple[Disks, np.ndarray, np.ndarray]:
    """Leaves along the segments of the outer-order chains, a short petiole away from the bark,
    oriented at random but mostly facing up. Also returns, per leaf, the segment it hangs on (an
    index into the chains' segments, in order) and where along it (0-1)."""
    p0 = np.concatenate([c.points[:, :-1].reshape(-1, 3) for c in chains])
    p1 = np.concatenate([c.points[:, 1:].reshape(-1, 3) for c in chains])
    rad = np.concatenate([c.radii[:, :-1].reshape(-1) for c in chains])
    seg_len = np.linalg.norm(p1 - p0, axis=1)
    n = rng.poisson(shape.leaves_per_m * seg_len)
    s = np.repeat(np.arange(len(n)), n)
    if s.size == 0:
        empty = np.zeros((0, 3))
        return Disks(empty, empty.copy(), np.zeros(0), np.zeros(0, dtype=np.int8)), s, np.zeros(0)
    u = _unit(p1[s] - p0[s])
    e1, e2 = _perpendicular_frame(u)
    az = rng.uniform(0, 2 * np.pi, s.size)
    out = np.cos(az)[:, None] * e1 + np.sin(az)[:, None] * e2
    w = rng.uniform(0, 1, s.size)[:, None]
    radius = rng.uniform(*shape.leaf_radius_m, s.size)
    centre = p0[s] * (1 - w) + p1[s] * w + out * (rad[s] + radius + rng.uniform(0.01, 0.04, s.size))[:, None]
    normal = _unit(rng.normal(0, 1, (s.size, 3)) + np.array([0.0, 0.0, 1.2]))
    return Disks(centre, normal, radius, np.full(s.size, LABEL_LEAF, dtype=np.int8)), s, w[:, 0]


def _trunk_axis(shape: TreeShape, rng: np.random.Generator, sink_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Trunk axis points (n+1 x 3) from `sink_m` below the base to the top, and arc lengths.

    A bent trunk follows two smooth sine modes in random horizontal directions (up to ~20 degrees
    off vertical); a straight one only wavers by a degree or so.
    """
    H = shape.height_m
    n = max(int(np.ceil((H + sink_m) / _TRUNK_SEG_M)), 4)
    s = np.linspace(-sink_m, H, n + 1)
    h1, h2 = (np.array([np.cos(a), np.sin(a), 0.0]) for a in rng.uniform(0, 2 * np.pi, 2))
    if shape.bent:
        a1, a2 = rng.uniform(0.15, 0.3), rng.uniform(0.05, 0.15)
        ph = rng.uniform(0, 2 * np.pi)
    else:
        a1, a2, ph = rng.uniform(0.0, 0.02), rng.uniform(0.0, 0.015), rng.uniform(0, 2 * np.pi)
    rel = np.clip(s, 0, H)[:-1] / H
    d = _unit(np.array([0.0, 0.0, 1.0]) + (a1 * np.sin(np.pi * rel))[:, None] * h1
              + (a2 * np.sin(2 * np.pi * rel + ph))[:, None] * h2)
    steps = d * np.diff(s)[:, None]
    pts = np.vstack([np.zeros(3), np.cumsum(steps, axis=0)])
    pts[:, 2] -= sink_m  # below ground level, so that a sloped ground leaves no gap at the base
    return pts, s


def make_tree(shape: TreeShape, rng: np.random.Generator, base: np.ndarray | None = None,
              label_override: int | None = None, sink_m: float = 0.0) -> TreeInfo:
    """One procedural tree standing at `base` (world, default the origin).

    Order-1 branches leave the trunk between the crown base (25-45% of the height) and the top,
    at golden-angle azimuths, longest low in the crown (a cone-shaped crown); each further order
    sprouts from its parent. `label_override` gives every primitive one label (a second tree);
    `sink_m` starts the trunk that far below the base (into a ground plane).
    """
    H, dbh = float(shape.height_m), float(shape.dbh_m)
    base = np.zeros(3) if base is None else np.asarray(base, dtype=float)
    # Drawn first, so that switching leaves or lean on or off keeps the same tree.
    lean_axis = rng.uniform(0, 360)
    leaf_rng = np.random.default_rng(rng.integers(0, 2**63))
    axis, s = _trunk_axis(shape, rng, sink_m)
    trunk = _Chains(axis[None], _trunk_radius(s, H, dbh)[None], np.array([H + sink_m]))
    cyl, sph = [], []
    c, sp = _chain_primitives(trunk, LABEL_TRUNK)
    cyl.append(c)
    sph.append(sp)

    n_branches: list[int] = []
    chains: list[_Chains] = []
    crown_base = H * rng.uniform(0.25, 0.45)
    if shape.orders >= 1:
        n1 = int(np.clip(round(H * rng.uniform(1.6, 2.2)), 6, 50))
        z = np.sort(rng.uniform(crown_base, 0.93 * H, n1))
        p, u, r_tr = trunk.point_at(np.zeros(n1, dtype=int), (z + sink_m) / (H + sink_m))
        az = np.radians(137.5 * np.arange(n1) + rng.uniform(-25, 25, n1))
        rel = (z - crown_base) / (H - crown_base)
        ang = np.radians(rng.uniform(50, 80, n1) - 25 * rel)
        side = np.stack([np.cos(az), np.sin(az), np.zeros(n1)], axis=1)
        side -= np.sum(side * u, axis=1, keepdims=True) * u
        d = np.cos(ang)[:, None] * u + np.sin(ang)[:, None] * _unit(side)
        length = np.maximum(H * rng.uniform(0.28, 0.4) * (1 - rel) ** 0.7 * rng.uniform(0.8, 1.2, n1), 0.4)
        r = np.maximum(r_tr * rng.uniform(0.3, 0.55, n1) * np.minimum(1.0, 0.6 + 0.15 * length), 0.01)
        droop = rng.uniform(-0.03, 0.04)
        tropism = droop + rng.uniform(-0.015, 0.015, n1)
        ch = _grow(p, d, length, r, _SEGMENTS[1], 0.05, tropism, rng)
        chains.append(ch)
        n_branches.append(n1)
        params = {2: (2.5, 12, (0.3, 0.55), (30, 65), (0.35, 0.65)),
                  3: (3.0, 8, (0.3, 0.55), (30, 70), (0.4, 0.7))}
        for order in range(2, shape.orders + 1):
            per_m, mx, lf, angr, rf = params[order]
            nxt = _children(chains[-1], per_m, mx, lf, angr, rf, order, rng)
            if nxt is None:
                break
            chains.append(nxt)
            n_branches.append(len(nxt.length))
        for k, ch_k in enumerate(chains):
            c, sp = _chain_primitives(ch_k, LABEL_BRANCH[k])
            cyl.append(c)
            sph.append(sp)

    leaf_seg, leaf_w = np.zeros(0, dtype=np.int64), np.zeros(0)
    if shape.leaves and chains:
        disks, leaf_seg, leaf_w = _leaves(chains[-2:], shape, leaf_rng)  # the outer two orders carry the leaves
    else:
        disks = Disks(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int8))
    limbs = _limbs(trunk, chains, len(chains[-2:]) if chains else 0, leaf_seg, leaf_w)

    scene = Scene(
        Cylinders(*(np.concatenate([getattr(c, f) for c in cyl]) for f in ("p0", "p1", "r0", "r1", "label"))),
        Spheres(*(np.concatenate([getattr(s_, f) for s_ in sph]) for f in ("centre", "radius", "label"))),
        disks,
    )
    # Lean: the whole tree tips over about its base, around a random horizontal axis.
    T = np.eye(4)
    if shape.lean_deg:
        T[:3, :3] = _axis_angle(np.radians(lean_axis), np.radians(shape.lean_deg))
    T[:3, 3] = base
    scene = scene.transformed(T)
    if label_override is not None:
        scene = Scene(
            Cylinders(scene.cylinders.p0, scene.cylinders.p1, scene.cylinders.r0, scene.cylinders.r1,
                      np.full(len(scene.cylinders), label_override, dtype=np.int8)),
            Spheres(scene.spheres.centre, scene.spheres.radius, np.full(len(scene.spheres), label_override, dtype=np.int8)),
            Disks(scene.disks.centre, scene.disks.normal, scene.disks.radius,
                  np.full(len(scene.disks), label_override, dtype=np.int8)),
        )
    return TreeInfo(base, shape, float(crown_base), float(lean_axis), tuple(n_branches), len(disks), scene, limbs)


def _limbs(trunk: _Chains, chains: list[_Chains], n_leaf_chains: int, leaf_seg: np.ndarray,
           leaf_w: np.ndarray) -> Limbs:
    """The `Limbs` of a tree grown as `trunk` + `chains` (orders 1, 2, ...), primitives in the order
    `make_tree` lays them out; leaves hang on the segments of the last `n_leaf_chains` chains."""
    all_chains = [trunk] + chains
    # Flutter branch ids: orders 2 and up, numbered in order; -1 for the trunk and order 1.
    first_id, nxt = [], 0
    for k, ch in enumerate(all_chains):
        first_id.append(nxt if k >= 2 else -1)
        nxt += len(ch.length) if k >= 2 else 0
    cyl_b, cyl_t0, cyl_t1 = [], [], []
    for k, ch in enumerate(all_chains):
        B, n = ch.points.shape[0], ch.points.shape[1] - 1
        ids = np.repeat(np.arange(B) + first_id[k], n) if k >= 2 else np.full(B * n, -1)
        t = np.tile(np.arange(n + 1) / n, B).reshape(B, n + 1)
        cyl_b.append(ids)
        cyl_t0.append(t[:, :-1].reshape(-1))
        cyl_t1.append(t[:, 1:].reshape(-1))
    cyl_b_all, t0_all, t1_all = (np.concatenate(v) for v in (cyl_b, cyl_t0, cyl_t1))
    parent, attach = [], []
    for k, ch in enumerate(all_chains[2:], start=2):
        # A branch of order 3+ sprouts from a flutter branch; one of order 2 from an order-1 branch.
        parent.append(ch.parent + first_id[k - 1] if k >= 3 else np.full(len(ch.length), -1))
        attach.append(ch.attach if k >= 3 else np.zeros(len(ch.length)))
    # Leaves: the segment index runs over the segments of the leaf-bearing chains, in order.
    leaf_chains = all_chains[len(all_chains) - n_leaf_chains:] if n_leaf_chains else []
    seg_b, seg_t0, seg_t1 = [], [], []
    for k0, ch in enumerate(leaf_chains):
        k = len(all_chains) - n_leaf_chains + k0
        B, n = ch.points.shape[0], ch.points.shape[1] - 1
        seg_b.append(np.repeat(np.arange(B) + first_id[k], n) if k >= 2 else np.full(B * n, -1))
        t = np.tile(np.arange(n) / n, B)
        seg_t0.append(t)
        seg_t1.append(t + 1.0 / n)
    if seg_b and leaf_seg.size:
        sb, st0, st1 = (np.concatenate(v) for v in (seg_b, seg_t0, seg_t1))
        disk_b = sb[leaf_seg]
        disk_t = st0[leaf_seg] * (1 - leaf_w) + st1[leaf_seg] * leaf_w
    else:
        disk_b, disk_t = np.zeros(0, dtype=np.int64), np.zeros(0)
    cat = (lambda v: np.concatenate(v) if v else np.zeros(0))
    return Limbs(cyl_b_all.astype(np.int64), t0_all, t1_all, cyl_b_all.astype(np.int64).copy(), t1_all.copy(),
                 disk_b.astype(np.int64), disk_t, cat(parent).astype(np.int64), cat(attach))


def _axis_angle(axis_azimuth: float, angle: float) -> np.ndarray:
    """Rotation by `angle` (rad) about the horizontal axis at azimuth `axis_azimuth` (rad)."""
    k = np.array([np.cos(axis_azimuth), np.sin(axis_azimuth), 0.0])
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def tilt_rotation(tilt_deg: float, axis_azimuth_deg: float) -> np.ndarray:
    """3x3 rotation by `tilt_deg` about the horizontal axis at `axis_azimuth_deg` (an instrument that
    is not perfectly levelled)."""
    return _axis_angle(np.radians(axis_azimuth_deg), np.radians(tilt_deg))


def make_ground(slope_deg: float, slope_azimuth_deg: float, radius_m: float) -> GroundPlane:
    """A plane through the main tree's base (the origin), rising by `slope_deg` towards
    `slope_azimuth_deg`, kept within `radius_m` of the origin."""
    a, b = np.radians(slope_deg), np.radians(slope_azimuth_deg)
    g = np.tan(a) * np.array([np.cos(b), np.sin(b)])  # dz/dx, dz/dy
    n = _unit(np.array([-g[0], -g[1], 1.0]))
    return GroundPlane(n, 0.0, np.zeros(3), float(radius_m))
