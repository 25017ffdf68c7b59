"""The crown's motion between two stations (wind), as the fine stage models it.

Stations of one tree are scanned minutes apart; in wind the stem bends, so the target's tree does
not stand as the reference's did. The stem base does not move: the instrument's pose is in it.
The motion is taken as a nuisance: the target's stem is shifted horizontally by `top * shape(z)`,
a cantilever loaded at its top (`shape` is 0 at the stem base, with zero slope there, and 1 at the
top), so that the crown's motion is not mistaken for a tilt or turn of the scanner. Two unknowns
(the shift at the top, x and y) are estimated with the pose (`joint.adjust_joint`), and the target
*unbent* by them (`Bend.warp`) is what the surfaces, the selection and the verification compare
with the reference.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.rigid import apply_transform, invert
from ..scan import Scan


def cantilever(s: np.ndarray) -> np.ndarray:
    """Deflection shape of a cantilever loaded at its tip: 0 at the base (s = 0), 1 at the top (s = 1),
    zero slope at the base (the lowest third of a stem moves a sixth of the top's sway)."""
    s = np.clip(np.asarray(s, dtype=float), 0.0, None)
    return s * s * (3.0 - s) / 2.0


@dataclass(frozen=True)
class Bend:
    """The target's tree bent relative to the reference's (reference frame).

    base_z_m, height_m : the stem's base height and the tree's height in the reference frame (where
        the shape is 0 and 1).
    top_m : horizontal shift (x, y) that lines the target's stem top up with the reference's; the
        target's crown had swayed by minus this between the two stations.
    std_m : the noise standard deviation of each component of `top_m`.
    """

    base_z_m: float
    height_m: float
    top_m: tuple[float, float] = (0.0, 0.0)
    std_m: tuple[float, float] = (float("nan"), float("nan"))

    def shape(self, z_m: np.ndarray) -> np.ndarray:
        """The share of the top's shift at heights `z_m` (reference frame)."""
        return cantilever((np.asarray(z_m, dtype=float) - self.base_z_m) / self.height_m)

    @property
    def sway_m(self) -> float:
        """How far the target's stem top had moved from where the reference saw it (metres)."""
        return float(np.hypot(*self.top_m))

    @property
    def sway_direction_deg(self) -> float:
        """Azimuth (reference frame) towards which the target's crown had moved."""
        return float(np.degrees(np.arctan2(-self.top_m[1], -self.top_m[0])))

    @property
    def sway_std_m(self) -> float:
        return float(np.hypot(*self.std_m))

    def unbend(self, points_ref: np.ndarray) -> np.ndarray:
        """Target points already in the reference frame, moved to where the reference's tree stood."""
        out = np.array(points_ref, dtype=float, copy=True)
        out[:, :2] += self.shape(out[:, 2])[:, None] * np.asarray(self.top_m)[None, :]
        return out

    def bend(self, points_ref: np.ndarray) -> np.ndarray:
        """Reference points moved to where the target's tree stood (the inverse of `unbend`)."""
        out = np.array(points_ref, dtype=float, copy=True)
        out[:, :2] -= self.shape(out[:, 2])[:, None] * np.asarray(self.top_m)[None, :]
        return out

    def significant(self, min_sway_m: float, significance: float) -> bool:
        """Worth modelling: the top moved at least `min_sway_m`, and `significance` times its noise."""
        return self.sway_m >= min_sway_m and self.sway_m >= significance * max(self.sway_std_m, 1e-12)

    def warp(self, scan: Scan, T_ref_target: np.ndarray) -> Scan:
        """The target scan (its own frame) as it would have been seen had its tree stood as the
        reference saw it: each point mapped by `T_ref_target`, unbent, and mapped back."""
        T = np.asarray(T_ref_target, dtype=float)
        moved = self.unbend(apply_transform(T, scan.points))
        return scan.with_points(apply_transform(invert(T), moved))

    def plus(self, d_top_m: np.ndarray, std_m: np.ndarray | None = None) -> "Bend":
        """This bend with `d_top_m` more shift at the top (the next iteration's estimate)."""
        top = (self.top_m[0] + float(d_top_m[0]), self.top_m[1] + float(d_top_m[1]))
        std = self.std_m if std_m is None else (float(std_m[0]), float(std_m[1]))
        return Bend(self.base_z_m, self.height_m, top, std)
