"""Circle and cylinder fits of separated arcs, and the checks that decide whether to trust them.

Paper 2.2.3: trunk sections get a Taubin circle fit (centre X0, Y0); branch sections a
least-squares cylinder fit (axis direction, a point on the axis, radius R). Paper 4.2: a part whose
radius exceeds that of the part below it on the same stem is a mis-separated arc and is dropped.

Every fit reports its RMS residual, the arc it covers about its centre (degrees) and whether it is
plausible, with the reason when not. A fit to a short, partial arc is poorly conditioned (its
centre slides along the viewing direction as the radius changes), so `judge_fit` marks fits with
too little arc, too large a residual or an absurd radius as implausible; callers keep them for
drawing but do not use them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from ..geometry.normals import pca_normals
from ..params import SectionsParams

#: Points used per cylinder fit; more only cost time (a subsample keeps the arc's shape).
MAX_FIT_POINTS = 400
#: Neighbours per point for the surface normals that seed the cylinder axis.
_NORMAL_K = 8
_NORMAL_SAMPLES = 48


@dataclass(frozen=True)
class CircleFit:
    """A circle in the xy plane.

    Attributes
    ----------
    ok
        False when the points cannot define a circle (too few, collinear); the rest is then NaN.
    centre_m
        (x0, y0).
    radius_m, rms_m
        Radius and RMS of the radial residuals.
    arc_deg
        Angle about the centre covered by the points (360 minus the largest empty gap).
    n_points
        Points fitted.
    plausible, reason
        Whether to trust the fit; when not, why (empty when plausible).
    """

    ok: bool
    centre_m: np.ndarray
    radius_m: float
    rms_m: float
    arc_deg: float
    n_points: int
    plausible: bool = True
    reason: str = ""


@dataclass(frozen=True)
class CylinderFit:
    """A cylinder: axis through `point_m` along `axis` (unit, pointing to +z), radius.

    Attributes
    ----------
    ok
        False when the fit failed; the rest is then NaN.
    point_m
        The point of the axis closest to the centroid of the fitted points.
    axis
        Unit axis direction with axis[2] >= 0 (paper: the positive direction increases z).
    radius_m, rms_m, arc_deg, n_points, plausible, reason
        As for `CircleFit`; the arc is measured about the axis.
    length_m
        Extent of the points along the axis.
    """

    ok: bool
    point_m: np.ndarray
    axis: np.ndarray
    radius_m: float
    rms_m: float
    arc_deg: float
    n_points: int
    length_m: float
    plausible: bool = True
    reason: str = ""

    def point_at_z(self, z: float) -> np.ndarray:
        """The axis point at height `z` (the closest point to `point_m` if the axis is horizontal)."""
        if abs(self.axis[2]) < 1e-6:
            return self.point_m.copy()
        return self.point_m + self.axis * (z - self.point_m[2]) / self.axis[2]


def _nan_circle(n: int, reason: str) -> CircleFit:
    return CircleFit(False, np.full(2, np.nan), np.nan, np.nan, 0.0, n, False, reason)


def _nan_cylinder(n: int, reason: str) -> CylinderFit:
    return CylinderFit(False, np.full(3, np.nan), np.full(3, np.nan), np.nan, np.nan, 0.0, n, 0.0, False, reason)


def arc_coverage_deg(angles_rad: np.ndarray) -> float:
    """Angle covered by points at `angles_rad` about a centre: 360 minus the largest empty gap."""
    if len(angles_rad) < 2:
        return 0.0
    a = np.sort(np.mod(angles_rad, 2 * np.pi))
    gaps = np.diff(np.concatenate([a, a[:1] + 2 * np.pi]))
    return float(np.degrees(2 * np.pi - gaps.max()))


def _taubin(xy: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Taubin's algebraic circle fit (Chernov's Newton formulation); None when degenerate."""
    m = xy.mean(axis=0)
    X, Y = xy[:, 0] - m[0], xy[:, 1] - m[1]
    Z = X * X + Y * Y
    # All six moments in one product (many small numpy calls cost more than the arithmetic).
    V = np.stack([X, Y, Z])
    M = (V @ V.T) / len(X)
    Mxx, Myy, Mxy, Mxz, Myz, Mzz = M[0, 0], M[1, 1], M[0, 1], M[0, 2], M[1, 2], M[2, 2]
    Mz = Mxx + Myy
    cov_xy = Mxx * Myy - Mxy * Mxy
    var_z = Mzz - Mz * Mz
    A3 = 4.0 * Mz
    A2 = -3.0 * Mz * Mz - Mzz
    A1 = var_z * Mz + 4.0 * cov_xy * Mz - Mxz * Mxz - Myz * Myz
    A0 = Mxz * (Mxz * Myy - Myz * Mxy) + Myz * (Myz * Mxx - Mxz * Mxy) - var_z * cov_xy
    x, y = 0.0, 1e20
    for _ in range(50):  # Newton on the characteristic polynomial, from x = 0 (converges monotonically)
        y_old, y = y, A0 + x * (A1 + x * (A2 + x * A3))
        if abs(y) > abs(y_old):
            x = 0.0
            break
        dy = A1 + x * (2 * A2 + x * 3 * A3)
        if dy == 0:
            break
        x_old, x = x, x - y / dy
        if x != 0 and abs((x - x_old) / x) < 1e-12:
            break
    x = max(x, 0.0)
    det = x * x - x * Mz + cov_xy
    if not np.isfinite(det) or abs(det) < 1e-300:
        return None
    c = np.array([Mxz * (Myy - x) - Myz * Mxy, Myz * (Mxx - x) - Mxz * Mxy]) / det / 2.0
    r2 = c @ c + Mz
    if not np.isfinite(r2) or r2 <= 0:
        return None
    return c + m, float(np.sqrt(r2))


def fit_circle_taubin(xy: np.ndarray) -> CircleFit:
    """Taubin circle fit to N x 2 points (paper 2.2.3, trunk sections).

    Examples
    --------
    >>> t = np.linspace(0, np.pi, 50)
    >>> fit = fit_circle_taubin(np.c_[1 + 0.3 * np.cos(t), 2 + 0.3 * np.sin(t)])
    >>> bool(np.allclose(fit.centre_m, [1, 2])), round(fit.radius_m, 6), round(fit.arc_deg)
    (True, 0.3, 180)
    """
    xy = np.asarray(xy, dtype=float)[:, :2]
    n = len(xy)
    if n < 3:
        return _nan_circle(n, "fewer than 3 points")
    res = _taubin(xy)
    if res is None:
        return _nan_circle(n, "points are collinear")
    centre, r = res
    d = xy - centre
    resid = np.hypot(d[:, 0], d[:, 1]) - r
    arc = arc_coverage_deg(np.arctan2(d[:, 1], d[:, 0]))
    return CircleFit(True, centre, r, float(np.sqrt(np.mean(resid ** 2))), arc, n)


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Cross product of two 3-vectors (np.cross costs ten times more on single vectors)."""
    return np.array([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]])


def _basis(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing `a` (unit) to a right-handed orthonormal frame."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = _cross(a, helper)
    e1 /= np.sqrt(e1 @ e1)
    return e1, _cross(a, e1)


def _normal_axis(xyz: np.ndarray) -> np.ndarray | None:
    """Cylinder axis as the direction most perpendicular to the local surface normals.

    Normals at up to `_NORMAL_SAMPLES` points (neighbours from all points) are plenty for one
    direction.
    """
    k = min(_NORMAL_K, len(xyz))
    if k < 5:
        return None
    at = xyz if len(xyz) <= _NORMAL_SAMPLES else xyz[np.linspace(0, len(xyz) - 1, _NORMAL_SAMPLES).astype(int)]
    normals = pca_normals(xyz, cKDTree(xyz), at, k)
    w, v = np.linalg.eigh(normals.T @ normals)
    return v[:, 0]


def _circle_about(xyz: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, float, float] | None:
    """Circle fit of the points projected on the plane normal to `a`: (axis point, radius, rms)."""
    e1, e2 = _basis(a)
    uva = xyz @ np.stack([e1, e2, a], axis=1)
    uv = uva[:, :2]
    res = _taubin(uv)
    if res is None:
        return None
    c, r = res
    d = uv - c
    rms = float(np.sqrt(np.mean((np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2) - r) ** 2)))
    return c[0] * e1 + c[1] * e2 + float(uva[:, 2].mean()) * a, r, rms


def fit_cylinder(xyz: np.ndarray, axis_hint: np.ndarray | None = None, loss_scale_m: float = 0.005,
                 refine: bool = True) -> CylinderFit:
    """Least-squares cylinder fit (paper 2.2.3, branch sections), started from PCA.

    The start axis is the best (lowest circle RMS) of: the principal direction of the points
    (PCA; right for long branch pieces), the direction most normal to the surface normals (right
    for short, wide slices of a stem, where PCA points across the stem), vertical, and `axis_hint`.
    Then `scipy.optimize.least_squares` refines axis, axis point and radius with a soft-L1 loss
    (analytic Jacobian).

    Parameters
    ----------
    xyz
        N x 3 points of one arc.
    axis_hint
        An optional extra start direction.
    loss_scale_m
        Residual scale of the robust loss.
    refine
        False skips the least-squares refinement and returns the best start (axis from the
        candidates, Taubin circle across it): about ten times faster, for callers that refine
        later anyway (the joint adjustment of `fine.py`).

    Returns
    -------
    CylinderFit
    """
    xyz = np.asarray(xyz, dtype=float)
    n = len(xyz)
    if n < 6:
        return _nan_cylinder(n, "fewer than 6 points")
    cap = MAX_FIT_POINTS if refine else MAX_FIT_POINTS // 2
    if n > cap:
        xyz = xyz[np.linspace(0, n - 1, cap).astype(int)]
    m = xyz.mean(axis=0)
    q = xyz - m
    evals, evecs = np.linalg.eigh(q.T @ q)
    if evals[-1] <= 0 or evals[-2] < 1e-12 * evals[-1]:
        return _nan_cylinder(n, "points are collinear")
    cands = [evecs[:, 2], np.array([0.0, 0.0, 1.0])]
    na = _normal_axis(q)
    if na is not None:
        cands.append(na)
    if axis_hint is not None:
        cands.append(np.asarray(axis_hint, dtype=float) / np.linalg.norm(axis_hint))
    best = None
    for a in cands:
        r = _circle_about(q, a)
        if r is not None and np.isfinite(r[2]) and (best is None or r[2] < best[3]):
            best = (a, r[0], r[1], r[2])
    if best is None:
        return _nan_cylinder(n, "no start for the cylinder fit")
    a0, c0, r0, _ = best
    e1, e2 = _basis(a0)

    def parts(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
        L = float(np.sqrt(1.0 + x[2] ** 2 + x[3] ** 2))
        a = (a0 + x[2] * e1 + x[3] * e2) / L
        d = q - (c0 + x[0] * e1 + x[1] * e2)
        along = d @ a
        perp = d - np.outer(along, a)
        return a, along, perp, np.sqrt(np.einsum("ij,ij->i", perp, perp)), L

    def resid(x: np.ndarray) -> np.ndarray:
        return parts(x)[3] - x[4]

    def jac(x: np.ndarray) -> np.ndarray:
        # r = |perp| - R; d r / d(axis point) = -n, d r / d(axis) = -(d . a) n (n = perp / |perp|, n . a = 0).
        _, along, perp, nrm, L = parts(x)
        n = perp / np.maximum(nrm, 1e-12)[:, None]
        ne1, ne2 = n @ e1, n @ e2
        return np.c_[-ne1, -ne2, -along * ne1 / L, -along * ne2 / L, -np.ones(len(q))]

    x = np.array([0.0, 0.0, 0.0, 0.0, r0])
    if refine:
        try:
            x = least_squares(resid, x, jac=jac, loss="soft_l1", f_scale=loss_scale_m,
                              x_scale=np.array([r0, r0, 0.1, 0.1, r0]), max_nfev=60).x
        except ValueError:
            return _nan_cylinder(n, "least squares failed")
    a = a0 + x[2] * e1 + x[3] * e2
    a /= np.linalg.norm(a)
    if a[2] < 0:
        a = -a
    c = c0 + x[0] * e1 + x[1] * e2
    c = c - a * (c @ a)  # axis point closest to the centroid (the origin of q)
    r = float(abs(x[4]))
    res = resid(x)
    f1, f2 = _basis(a)
    d = q - c
    arc = arc_coverage_deg(np.arctan2(d @ f2, d @ f1))
    along = q @ a
    return CylinderFit(True, c + m, a, r, float(np.sqrt(np.mean(res ** 2))), arc, n,
                       float(along.max() - along.min()))


def judge_fit(fit: CircleFit | CylinderFit, p: SectionsParams) -> CircleFit | CylinderFit:
    """The fit with `plausible` and `reason` set from the thresholds in `p`."""
    if not fit.ok:
        return fit
    reasons = []
    if not (fit.radius_m <= p.max_radius_m):
        reasons.append(f"radius {fit.radius_m:.3g} m > {p.max_radius_m} m")
    if not (fit.rms_m <= p.max_rms_m):
        reasons.append(f"RMS {fit.rms_m * 100:.2g} cm > {p.max_rms_m * 100:.2g} cm")
    if fit.arc_deg < p.min_arc_deg:
        reasons.append(f"arc {fit.arc_deg:.0f} deg < {p.min_arc_deg:.0f} deg")
    if reasons:
        return replace(fit, plausible=False, reason="; ".join(reasons))
    return replace(fit, plausible=True, reason="")


@dataclass(frozen=True)
class Section:
    """One fitted arc of one slice, in the reference frame.

    Attributes
    ----------
    slice_index, arc
        Which slice, and which arc of that slice's `ArcResult`.
    height_m
        The slice's height (reference frame).
    fit
        The circle or cylinder fit.
    centre_m
        The centre at the slice height: (x0, y0, h) for a circle, the axis point at z = h for a cylinder.
    axis
        Unit axis (vertical for a circle).
    radius_m
        Fitted radius.
    plausible, reason
        Whether the section may be used, and why not.
    """

    slice_index: int
    arc: int
    height_m: float
    fit: CircleFit | CylinderFit
    centre_m: np.ndarray
    axis: np.ndarray
    radius_m: float
    plausible: bool
    reason: str

    @property
    def kind(self) -> str:
        return "circle" if isinstance(self.fit, CircleFit) else "cylinder"


def fit_section(points: np.ndarray, slice_index: int, arc: int, height_m: float, circle: bool,
                p: SectionsParams) -> Section:
    """Fit one arc (points in the reference frame) by a circle or a cylinder and judge the fit.

    Cylinders are refined by least squares only when `p.refine_cylinders`."""
    if circle:
        fit = judge_fit(fit_circle_taubin(points[:, :2]), p)
        centre = np.array([fit.centre_m[0], fit.centre_m[1], height_m])
        axis = np.array([0.0, 0.0, 1.0])
    else:
        fit = judge_fit(fit_cylinder(points, refine=p.refine_cylinders), p)
        axis = fit.axis
        centre = fit.point_at_z(height_m) if fit.ok else np.full(3, np.nan)
        # A near-horizontal axis meets the slice plane far from the points: use the point nearest them.
        if fit.ok and np.linalg.norm(centre - fit.point_m) > max(1.0, 5 * fit.length_m):
            centre = fit.point_m.copy()
    return Section(slice_index, arc, float(height_m), fit, centre, axis, float(fit.radius_m),
                   bool(fit.plausible), fit.reason)


def unfitted_section(n_points: int, slice_index: int, arc: int, height_m: float, reason: str) -> Section:
    """A section left unfitted on purpose (implausible, with the reason)."""
    fit = _nan_cylinder(n_points, reason)
    return Section(slice_index, arc, float(height_m), fit, np.full(3, np.nan), np.full(3, np.nan), float("nan"),
                   False, reason)


def parts_below(sections: list[Section], gate_m: float, level: int | None = None) -> dict[int, int]:
    """Paper 4.2's "part below": for each plausible section, the index of the plausible section of
    the next lower slice whose centre is nearest to this section's axis extended down to that
    slice, when it lies within `gate_m` plus the radius (sections without one are left out).
    `level`: only the sections of that slice."""
    by_slice: dict[int, list[int]] = {}
    for i, s in enumerate(sections):
        by_slice.setdefault(s.slice_index, []).append(i)
    levels = sorted(by_slice)
    found: dict[int, int] = {}
    for lo_lvl, hi_lvl in zip(levels[:-1], levels[1:]):
        if level is not None and hi_lvl != level:
            continue
        below = [i for i in by_slice[lo_lvl] if sections[i].plausible]
        if not below:
            continue
        cb = np.array([sections[i].centre_m for i in below])
        h = sections[below[0]].height_m
        for i in by_slice[hi_lvl]:
            s = sections[i]
            if not s.plausible:
                continue
            a = s.axis
            pred = s.centre_m + a * (h - s.height_m) / a[2] if a[2] > 0.2 else s.centre_m
            d = np.linalg.norm((cb - pred)[:, :2], axis=1)
            j = int(np.argmin(d))
            if d[j] <= gate_m + s.radius_m:
                found[i] = below[j]
    return found


def check_taper(sections: list[Section], tolerance: float, gate_m: float) -> list[Section]:
    """Paper 4.2: drop a section whose radius exceeds that of the part below it on the same stem.

    The part below is found by `parts_below`. A section is dropped when its radius exceeds the one
    below by more than the fraction `tolerance` (paper: 0). Sections without a part below are kept.
    Levels are judged bottom-up, so a section dropped here no longer serves as the part below.
    """
    out = list(sections)
    levels = sorted({s.slice_index for s in out})
    for lvl in levels[1:]:
        # Only this level and the one below matter for this level's verdicts.
        for i, j in parts_below(out, gate_m, lvl).items():
            s = out[i]
            if s.radius_m > out[j].radius_m * (1.0 + tolerance):
                out[i] = replace(s, plausible=False,
                                 reason=f"radius {s.radius_m:.3g} m exceeds the part below "
                                        f"({out[j].radius_m:.3g} m), paper 4.2")
    return out
