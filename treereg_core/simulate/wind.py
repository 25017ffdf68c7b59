"""Wind between stations: the tree as each station found it.

A station takes 5-20 minutes, so the stations of one tree are minutes apart and the crown is never
where it was. Before each station scans, its tree is deformed:

* the stem bends as a cantilever loaded at its top: the horizontal displacement at height z is
  `top * s^2 (3 - s) / 2` with s = z / height (zero at the base, with zero slope there; the lowest
  third of an 8 m stem moves a sixth of the top's sway). Everything on the stem (its order-1
  branches, their twigs and leaves) goes with it;
* branches of order 2 and up flutter on their own: each moves by a random vector (up to `flutter`
  times the top sway at its tip, growing along it from zero at its base, carried by its parent);
* leaves follow their twig and flutter a little more, and turn.

The ground and the stem base stay put: the instrument's pose is in them. Each station has its own
sway (its own direction); `Sway` records it, in the world frame of the simulation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..fine.bend import cantilever
from .tree import Cylinders, Disks, Scene, Spheres, TreeInfo

#: A leaf's own flutter, beyond its twig's, as a share of the branch flutter.
LEAF_FLUTTER = 0.3
#: Leaves turn by up to about this much (radians) in the wind.
LEAF_TURN_RAD = 0.5


@dataclass(frozen=True)
class Sway:
    """One tree's wind at one station, world frame: the stem top's horizontal displacement (m) and
    the largest flutter of a small branch's tip (m)."""

    top_m: tuple[float, float]
    flutter_m: float

    @property
    def magnitude_m(self) -> float:
        return float(np.hypot(*self.top_m))

    @property
    def direction_deg(self) -> float:
        return float(np.degrees(np.arctan2(self.top_m[1], self.top_m[0])))

    def to_dict(self) -> dict[str, float | list[float]]:
        return {"top_sway_m": round(self.magnitude_m, 6), "direction_deg": round(self.direction_deg, 4),
                "top_m": [round(float(v), 6) for v in self.top_m], "flutter_m": round(self.flutter_m, 6)}


def draw_sway(top_sway_m: float, flutter: float, rng: np.random.Generator) -> Sway:
    """A station's sway: `top_sway_m` at the top in a random direction; small branches flutter by up
    to `flutter` times that."""
    a = rng.uniform(0.0, 2.0 * np.pi)
    return Sway((float(top_sway_m * np.cos(a)), float(top_sway_m * np.sin(a))), float(flutter * top_sway_m))


def bend_at(z_m: np.ndarray, base_z_m: float, height_m: float) -> np.ndarray:
    """The share of the top sway by which the stem moves at heights `z_m` (world)."""
    return cantilever((np.asarray(z_m, dtype=float) - base_z_m) / height_m)


def sway_tree(tree: TreeInfo, sway: Sway, rng: np.random.Generator) -> Scene:
    """`tree`'s scene as a station found it under `sway` (bent stem, fluttering branches and leaves).

    A tree without branching structure (`limbs` None) only bends. The same rng draws give the same
    flutter.
    """
    scene, limbs = tree.scene, tree.limbs
    H, z0 = float(tree.shape.height_m), float(tree.base_m[2])
    top = np.array([sway.top_m[0], sway.top_m[1], 0.0])

    def bend(p: np.ndarray) -> np.ndarray:
        return p + bend_at(p[:, 2], z0, H)[:, None] * top

    c, s, d = scene.cylinders, scene.spheres, scene.disks
    p0, p1, cen, dcen, dn = c.p0, c.p1, s.centre, d.centre, d.normal
    if limbs is not None and sway.flutter_m > 0:
        B = limbs.n_branches
        # Mostly horizontal, as the wind pushes; up to flutter_m at a branch's tip.
        v = rng.normal(0.0, 1.0, (B, 3)) * np.array([1.0, 1.0, 0.4])
        v *= (sway.flutter_m * rng.uniform(0.0, 1.0, B) / np.maximum(np.linalg.norm(v, axis=1), 1e-12))[:, None]
        # A branch's base moves with its parent at the point it sprouts from (parents come first).
        off = np.zeros((B, 3))
        for b in range(B):
            q = limbs.parent[b]
            if q >= 0:
                off[b] = off[q] + v[q] * limbs.attach[b]

        def flutter(branch: np.ndarray, t: np.ndarray) -> np.ndarray:
            on = branch >= 0
            out = np.zeros((len(branch), 3))
            out[on] = off[branch[on]] + v[branch[on]] * t[on, None]
            return out

        p0 = p0 + flutter(limbs.cyl_branch, limbs.cyl_t0)
        p1 = p1 + flutter(limbs.cyl_branch, limbs.cyl_t1)
        cen = cen + flutter(limbs.sph_branch, limbs.sph_t)
        k = len(d)
        own = rng.normal(0.0, 1.0, (k, 3))
        own *= (LEAF_FLUTTER * sway.flutter_m * rng.uniform(0.0, 1.0, k) /
                np.maximum(np.linalg.norm(own, axis=1), 1e-12))[:, None]
        dcen = dcen + flutter(limbs.disk_branch, limbs.disk_t) + own
        dn = dn + rng.normal(0.0, LEAF_TURN_RAD, (k, 3))
        dn = dn / np.maximum(np.linalg.norm(dn, axis=1, keepdims=True), 1e-12)
    return Scene(Cylinders(bend(p0), bend(p1), c.r0, c.r1, c.label), Spheres(bend(cen), s.radius, s.label),
                 Disks(bend(dcen), dn, d.radius, d.label), scene.ground)
