"""Rigid transforms: 4x4 helpers, SVD (Kabsch) fits, and errors against ground truth.

Naming follows small_gicp: `T_ref_scan` maps a point of `scan` into the frame of `ref`.
All transforms are 4x4 float64; units are metres and degrees.
"""

from __future__ import annotations

import numpy as np


def make_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def apply_transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map N x 3 `points` by the 4x4 `T`."""
    return points @ T[:3, :3].T + T[:3, 3]


def invert(T: np.ndarray) -> np.ndarray:
    R = T[:3, :3]
    return make_transform(R.T, -R.T @ T[:3, 3])


def rotation_z(angle_deg: float) -> np.ndarray:
    """3x3 rotation about +z by `angle_deg`."""
    a = np.radians(angle_deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of the rotation `R` in degrees (0..180)."""
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def kabsch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Least-squares rigid 4x4 mapping `src` onto `dst` (both N x 3), by SVD with the reflection guard.

    Needs N >= 3 non-collinear points; the caller checks degeneracy.
    """
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum()
    cs = w @ src
    cd = w @ dst
    H = (src - cs).T @ ((dst - cd) * w[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    D = np.diag([1.0, 1.0, d if d != 0 else 1.0])
    R = Vt.T @ D @ U.T
    return make_transform(R, cd - R @ cs)


def kabsch_yaw(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Least-squares yaw-about-z + 3-D translation (4 DOF) mapping `src` onto `dst`.

    For levelled scanners: the rotation is restricted to the vertical axis. Needs N >= 2 points
    that are not all on one vertical line.
    """
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum()
    cs = w @ src
    cd = w @ dst
    a = src[:, :2] - cs[:2]
    b = dst[:, :2] - cd[:2]
    s = np.sum(w * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))
    c = np.sum(w * (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]))
    R = rotation_z(np.degrees(np.arctan2(s, c)))
    return make_transform(R, cd - R @ cs)


def rotation_from_vector(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector `w` (axis times angle, rad; Rodrigues)."""
    th = float(np.linalg.norm(w))
    if th < 1e-15:
        return np.eye(3)
    k = w / th
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(th) * K + (1.0 - np.cos(th)) * (K @ K)


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis times angle, rad) of a rotation matrix.

    Through the unit quaternion (Shepperd's choice of its largest component, so every angle up to
    pi is exact), written out: scipy's `Rotation` costs half a millisecond a call, and the joint
    adjustment asks thousands of times."""
    m = np.asarray(R, dtype=float)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    k = int(np.argmax((m[0, 0], m[1, 1], m[2, 2], tr)))
    if k == 3:
        q = np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1], 1.0 + tr])
    else:
        i, j, l = k, (k + 1) % 3, (k + 2) % 3
        q = np.empty(4)
        q[i] = 1.0 - tr + 2.0 * m[i, i]
        q[j] = m[j, i] + m[i, j]
        q[l] = m[l, i] + m[i, l]
        q[3] = m[l, j] - m[j, l]
    q /= np.sqrt(q @ q)
    if q[3] < 0:
        q = -q
    v = q[:3]
    s = float(np.sqrt(v @ v))
    if s < 1e-12:  # the angle is 2 s: the series' first term
        return 2.0 * v
    return (2.0 * np.arctan2(s, q[3]) / s) * v


def rotation_error_deg(T_est: np.ndarray, T_true: np.ndarray) -> float:
    """Angle of the rotation between the estimated and the true transform, degrees."""
    return rotation_angle_deg(T_est[:3, :3] @ T_true[:3, :3].T)


def mean_displacement(T_est: np.ndarray, T_true: np.ndarray, points: np.ndarray) -> float:
    """Mean distance (m) between the scan's points mapped by the estimated and by the true transform."""
    d = apply_transform(T_est, points) - apply_transform(T_true, points)
    return float(np.linalg.norm(d, axis=1).mean())
