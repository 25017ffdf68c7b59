"""Levelling a scan whose up is not its z: a scanner not levelled (no tilt compensator), a tilt mount
(the scanner turned 90 deg to see the canopy), a scan upside down or exported y-up.

Every stage after preparation takes z as up (the ground plane, the stems at breast height, the
slices, the rotating projection's turn about z). So the prepare stage turns each such scan about its
scanner (the origin of its frame: the projection's geometry holds) so that its up is z, and every
stage works on levelled scans; `PreparedScan.T_level` keeps the turn (levelled <- as given) and the
transforms users see are of the scans as given: T_ref_tgt = inv(L_ref) @ T_levelled @ L_tgt
(`as_given`).

The up comes from the scan's own data (`prepare.vertical`: its ground near the scanner, its stem)
or, without a ground to go by, from its file's pose (an E57/PTX pose that tilts the scanner).
A scan is levelled only when the evidence is clear, and left exactly as given otherwise. The ground
near the scanner is a plane of thousands of points: its normal is the finer measure of the up; a stem
wavers and leans by a few degrees (a simulated 8 m tree's axis, traced 0.5-3 m above the ground, is
up to 3 deg off its true vertical), so it only tells a slope from a tilted scanner when the slope is
well beyond that:
- the ground's normal within `level_min_deg` of z: the scanner stands level (a gentle slope, or a
  scanner tilted by less than the pipeline tolerates);
- more than 45 deg from z (a tilt mount, upside down, y-up): no slope explains it, the ground's
  normal is the up;
- else the stem must say the scanner is tilted too (its axis `level_min_deg` or more off z; within
  it, a levelled scanner on a slope is left as given: levelled by their own ground's normal, the
  stations of an uneven slope would disagree by its unevenness). Then, when the stem's axis is nearer
  z than the ground's normal by `level_stem_margin_deg` or more, the ground slopes under a tilted
  scanner: the stem's axis is the up; otherwise the ground's normal is;
- no stem traced under a ground tilted by less than 45 deg: a slope or a tilted scanner, which the
  data cannot tell apart: left as given (the verdict says so when the pair is not verified).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..scan import Scan
from .vertical import _SAMPLE, _deg, _ground_plane, _stem_axis

_Z = np.array([0.0, 0.0, 1.0])
#: Points the ground plane is searched among.
_PLANE_SAMPLE = 20_000


@dataclass(frozen=True)
class Levelling:
    """How a scan was levelled.

    R : 3x3 rotation taking the scan's up to z (levelled <- as given), or None (left as given).
    off_deg : how far the scan's up was from z (NaN when nothing could be said).
    how : what the up was found from ("ground and stem", "stem (sloping ground)", "ground", "file pose"),
        "" when not levelled.
    """

    R: np.ndarray | None
    off_deg: float
    how: str

    @property
    def T(self) -> np.ndarray | None:
        """4x4 of the levelling (about the scanner: no translation), or None."""
        if self.R is None:
            return None
        T = np.eye(4)
        T[:3, :3] = self.R
        return T


def rotation_to_z(up: np.ndarray) -> np.ndarray:
    """The smallest rotation taking the unit vector `up` to z (so the scan's heading is kept)."""
    u = np.asarray(up, dtype=float) / np.linalg.norm(up)
    axis = np.cross(u, _Z)
    s, c = float(np.linalg.norm(axis)), float(u @ _Z)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])  # upside down: turned about x
    k = axis / s
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


def find_levelling(points: np.ndarray, pose: np.ndarray | None = None, *, min_deg: float = 3.0,
                   stem_margin_deg: float = 3.0, seed: int = 0) -> Levelling:
    """The levelling of a scan, from its ground and stem, else its file's pose (see the module doc)."""
    pts = np.asarray(points, dtype=float)
    pts = pts[:: max(1, len(pts) // _SAMPLE)]
    # The plane is searched among fewer points (every scan pays for it; its hypotheses' distances are
    # a points x hypotheses array), the stem traced among them all.
    plane = _ground_plane(pts[:: max(1, len(pts) // _PLANE_SAMPLE)], np.random.default_rng(seed))
    if plane is None:
        return _from_pose(pose, min_deg)
    up, height = plane
    off = _deg(up, _Z)
    if off < min_deg:
        return Levelling(None, off, "")
    if off > 45.0:  # no slope explains it: the ground's normal is the up
        return Levelling(rotation_to_z(up), off, "ground")
    axis = _stem_axis(pts, up, height)
    if axis is None:  # a slope or a tilted scanner: the data cannot tell which
        return Levelling(None, off, "")
    stem_off = _deg(axis, _Z)
    if stem_off < min_deg:  # the stem stands plumb: a levelled scanner on a slope
        return Levelling(None, stem_off, "")
    if stem_off + stem_margin_deg > _deg(axis, up):  # the stem does not say slope: the ground is the up
        return Levelling(rotation_to_z(up), off, "ground and stem")
    return Levelling(rotation_to_z(axis), stem_off, "stem (sloping ground)")


def _from_pose(pose: np.ndarray | None, min_deg: float) -> Levelling:
    """The up the file's pose gives (T_user_scan: its z taken as up), when it tilts the scanner."""
    if pose is None:
        return Levelling(None, float("nan"), "")
    up = np.asarray(pose, dtype=float)[:3, :3].T @ _Z
    off = _deg(up / np.linalg.norm(up), _Z)
    if off < min_deg:
        return Levelling(None, off, "")
    return Levelling(rotation_to_z(up), off, "file pose")


def levelled(scan: Scan, R: np.ndarray) -> Scan:
    """`scan` turned by `R` about its scanner: the same station (steps, source), its pose kept
    pointing at the same place (T_user_levelled = T_user_scan @ R^T)."""
    out = scan.with_points(np.ascontiguousarray(scan.points @ R.T))
    if scan.pose is not None:
        T = np.eye(4)
        T[:3, :3] = R.T
        out = replace(out, pose=np.asarray(scan.pose, dtype=float) @ T)
    return out


def as_given(T: np.ndarray, L_ref: np.ndarray | None, L_tgt: np.ndarray | None) -> np.ndarray:
    """A transform between levelled scans as one between the scans as given:
    inv(L_ref) @ T @ L_tgt (either levelling None: not levelled)."""
    out = np.asarray(T, dtype=float)
    if L_tgt is not None:
        out = out @ L_tgt
    if L_ref is not None:
        out = np.linalg.inv(L_ref) @ out
    return out


def as_levelled(T: np.ndarray, L_ref: np.ndarray | None, L_tgt: np.ndarray | None) -> np.ndarray:
    """A transform between the scans as given as one between the levelled scans: L_ref @ T @ inv(L_tgt)."""
    out = np.asarray(T, dtype=float)
    if L_tgt is not None:
        out = out @ np.linalg.inv(L_tgt)
    if L_ref is not None:
        out = L_ref @ out
    return out
