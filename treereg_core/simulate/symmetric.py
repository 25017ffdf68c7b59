"""A tree whose crown looks alike from several headings: the negative case of the verification.

A straight trunk with `fold` identical branches at each whorl, `360 / fold` degrees apart, on flat
ground: turning it by that angle about its stem maps it onto itself, so scans of it cannot tell
their heading apart by more than that turn. A registration of such scans is right only by luck, and
the verification must refuse it (unverified, "the heading is ambiguous"), never verify it at a wrong
heading. `whorl_jitter_deg` > 0 breaks the symmetry (each branch turned at random by up to that
much): the control case, which must register and verify.
"""

from __future__ import annotations

import numpy as np

from ..geometry.rigid import invert, make_transform, rotation_z
from ..scan import Scan
from .scanner import scan_scene
from .tree import Cylinders, Disks, GroundPlane, Scene, Spheres, TreeInfo, TreeShape
from .wind import draw_sway, sway_tree


def symmetric_tree(fold: int, whorls: int = 5, height_m: float = 8.0, whorl_jitter_deg: float = 0.0,
                   seed: int = 0) -> Scene:
    """The scene: trunk (15 cm radius at the base, 5 cm at the top), `whorls` whorls of `fold`
    branches (1.8 m long, rising 35 deg), flat ground of 15 m radius."""
    rng = np.random.default_rng(seed)
    p0, p1, r0, r1 = [[0.0, 0.0, -0.2]], [[0.0, 0.0, height_m]], [0.15], [0.05]
    rise = np.radians(35.0)
    for i in range(whorls):
        h = 2.0 + i * (height_m - 3.0) / max(whorls - 1, 1)
        trunk_r = 0.15 - 0.1 * h / height_m
        for k in range(fold):
            a = np.radians(25.0 * i + k * 360.0 / fold + rng.uniform(-whorl_jitter_deg, whorl_jitter_deg))
            start = np.array([0.5 * trunk_r * np.cos(a), 0.5 * trunk_r * np.sin(a), h])
            d = np.array([np.cos(a) * np.cos(rise), np.sin(a) * np.cos(rise), np.sin(rise)])
            p0.append(start)
            p1.append(start + 1.8 * d)
            r0.append(0.05)
            r1.append(0.02)
    cylinders = Cylinders(np.array(p0), np.array(p1), np.array(r0), np.array(r1), np.zeros(len(p0), np.int8))
    none = np.zeros((0, 3))
    return Scene(cylinders, Spheres(none, np.zeros(0), np.zeros(0, np.int8)),
                 Disks(none, none, np.zeros(0), np.zeros(0, np.int8)),
                 GroundPlane(np.array([0.0, 0.0, 1.0]), 0.0, np.zeros(3), 15.0))


def symmetric_case(fold: int, azimuths_deg: tuple[float, ...] = (0.0, 100.0, 215.0), distance_m: float = 8.0,
                   step_deg: float = 0.1, whorl_jitter_deg: float = 0.0, seed: int = 0, wind_m: float = 0.0
                   ) -> tuple[list[Scan], dict[str, np.ndarray]]:
    """Scans of `symmetric_tree(fold)` from stations at these azimuths (none a multiple of the
    symmetry apart, so their views differ), each turned at random about its vertical axis; and the
    truth {name: T_ref_scan}. `wind_m`: before each station scans, the stem bends with this top sway
    in a direction of the station's own (`simulate.wind`; the ground stays)."""
    scene = symmetric_tree(fold, whorl_jitter_deg=whorl_jitter_deg, seed=seed)
    tree = TreeInfo(np.zeros(3), TreeShape(height_m=8.0), 2.0, 0.0, (), 0, scene)
    rng = np.random.default_rng(seed)
    rng_wind = np.random.default_rng([seed, 11])
    scans, poses = [], []
    for k, az in enumerate(np.radians(azimuths_deg)):
        T_world_scan = make_transform(rotation_z(rng.uniform(0.0, 360.0)),
                                      np.array([distance_m * np.cos(az), distance_m * np.sin(az), 1.5]))
        seen = scene if wind_m <= 0 else sway_tree(tree, draw_sway(wind_m, 0.0, rng_wind), rng_wind)
        rays = scan_scene(seen.transformed(invert(T_world_scan)), (step_deg, step_deg), rng,
                          ground_near_m=distance_m - 2.0)
        scans.append(Scan.from_points(rays.points, name=f"scan{k + 1}.ply", angular_step_deg=(step_deg, step_deg)))
        poses.append(T_world_scan)
    return scans, {s.name: invert(poses[0]) @ T for s, T in zip(scans, poses)}
