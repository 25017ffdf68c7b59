"""The stem profile: how the target's stem stands against the reference's, height by height.

Each scan's stem is traced up from its base (a thin slab every `step_m`, the stem's points found
near where the slab below put it), then, at every height both scans reach, one circle with a
shared radius is fitted to the reference's stem points and the same circle shifted to the
target's (`joint.section_offsets`): the shift is the target's stem offset there. Partial arcs do not
bias it (the radius is shared), so it resolves millimetres.

In still air and at the right pose the profile is flat at zero. A pose that is off shifts it
(translation) or tilts it (a tilt of the scanner: offsets growing linearly with height from the
base); wind between the stations bends it (a cantilever: nothing at the base, the most at the top).
`fit_profile` separates the three (`StemModel`): the fine stage starts from it when the crown has
moved, and the verification reads from it whether the stem holds where it must and how far the
crown moved.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .bend import cantilever
from .fitting import fit_circle_taubin
from .joint import section_offsets

#: Points per scan and slab used in the fits (a seeded-free, even subsample).
_MAX_SLAB_POINTS = 300
#: Fewest points of a scan's stem in a slab.
_MIN_POINTS = 12
#: A trace stops after this many slabs in a row without its stem.
_MAX_GAP = 2
#: Thinnest stem traced (m): above it the stem is a twig among twigs.
_MIN_RADIUS_M = 0.012
#: A profile tells a bend from a tilt with this many slabs up to this share of the tree's height.
MIN_SLABS = 8
MIN_SPAN = 0.4
#: A slab's offset counts only when its noise std is below this (m).
_MAX_OFFSET_STD_M = 0.005


@dataclass(frozen=True, eq=False)
class StemTrace:
    """One scan's stem, slab by slab (reference frame): heights, centres (K x 2), radii, and the
    indices of the stem's points in each slab (into the points traced)."""

    heights_m: np.ndarray
    centres_m: np.ndarray
    radii_m: np.ndarray
    members: tuple[np.ndarray, ...]


def _even(idx: np.ndarray, n: int) -> np.ndarray:
    return idx if len(idx) <= n else idx[np.linspace(0, len(idx) - 1, n).astype(np.int64)]


def _centre_fixed_radius(xy: np.ndarray, c: np.ndarray, r: float, scale: float) -> np.ndarray:
    """The centre of a circle of radius `r` through `xy` (Gauss-Newton from `c`, Cauchy weights):
    with the radius held, a partial arc's centre does not slide along the view."""
    for _ in range(8):
        d = xy - c
        rho = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
        n = d / rho[:, None]
        res = rho - r
        w = 1.0 / (1.0 + (res / scale) ** 2)
        H = (n * w[:, None]).T @ n + 1e-12 * np.eye(2)
        step = np.linalg.solve(H, (n * (w * res)[:, None]).sum(axis=0))
        c = c + step
        if np.hypot(*step) < 1e-5:
            break
    return c


def trace_stem(points: np.ndarray, start_xy: np.ndarray, z_lo: float, z_hi: float, step_m: float = 0.25,
               thickness_m: float = 0.1, search_m: float = 0.6) -> StemTrace:
    """Follow a stem up through `points` (N x 3) from `start_xy` at the height `z_lo` to `z_hi`.

    The first slab's stem is the circle fitted to the points within `search_m` of `start_xy`; each
    next slab's is sought near where the two below put it (its radius as the one below, then
    re-measured, never growing: stems taper).
    """
    order = np.argsort(points[:, 2], kind="stable")
    zs = points[order, 2]
    heights, centres, radii, members = [], [], [], []
    c = np.asarray(start_xy, dtype=float)[:2].copy()
    c_prev: np.ndarray | None = None
    r = float("nan")
    gap = 0
    half = thickness_m / 2.0
    for h in np.arange(z_lo + half, z_hi - half, step_m):
        a, b = np.searchsorted(zs, [h - half, h + half])
        idx = order[a:b]
        xy = points[idx, :2]
        guess = c if c_prev is None else c + (c - c_prev)
        reach = search_m if not np.isfinite(r) else r * 1.5 + 0.05
        near = np.hypot(*(xy - guess).T) <= reach
        if near.sum() < _MIN_POINTS:
            gap += 1
            if gap > _MAX_GAP and heights:
                break
            continue
        sel = idx[near]
        if not np.isfinite(r):
            fit = fit_circle_taubin(points[sel, :2])
            if not fit.ok or not 0.02 <= fit.radius_m <= search_m:
                continue
            cen, rad = fit.centre_m, fit.radius_m
        else:
            cen = _centre_fixed_radius(points[sel, :2], guess, r, max(0.2 * r, 0.005))
            rad = r
        dist = np.hypot(*(points[sel, :2] - cen).T)
        inl = np.abs(dist - rad) <= max(0.2 * rad, 0.01)
        if inl.sum() < _MIN_POINTS:
            gap += 1
            if gap > _MAX_GAP and heights:
                break
            continue
        rad = float(np.clip(np.median(dist[inl]), 0.85 * rad, rad)) if np.isfinite(r) else float(rad)
        if rad < _MIN_RADIUS_M:
            break
        gap = 0
        c_prev, c, r = (c if heights else None), cen, rad
        heights.append(float(h))
        centres.append(cen)
        radii.append(rad)
        members.append(sel[inl])
    return StemTrace(np.array(heights), np.array(centres).reshape(-1, 2), np.array(radii), tuple(members))


@dataclass(frozen=True)
class StemModel:
    """The profile's offsets explained: d(z) = shift + tilt * (z - z_mid) + bend * shape(z).

    shift_m : the offset at `z_mid` (x, y) apart from the bend; tilt : offset per metre of height
    (x, y; a tilt of the scanner); bend_m : the offset at the top (x, y) from a cantilever bend;
    std : noise std of each of the six (shift x, y, tilt x, y, bend x, y); rms_m : what the model
    leaves unexplained; z_mid_m : the height the shift is measured at; hinge_m : how far below the
    profile's base the cantilever bends from (the root plate; 0 = at the base).
    """

    shift_m: np.ndarray
    tilt: np.ndarray
    bend_m: np.ndarray
    std: np.ndarray
    rms_m: float
    z_mid_m: float
    hinge_m: float = 0.0

    def offsets(self, z_m: np.ndarray, base_z_m: float, height_m: float) -> np.ndarray:
        z = np.asarray(z_m, dtype=float)
        base, H = base_z_m - self.hinge_m, height_m + self.hinge_m
        return (self.shift_m[None, :] + (z - self.z_mid_m)[:, None] * self.tilt[None, :]
                + cantilever((z - base) / H)[:, None] * self.bend_m[None, :])


@dataclass(frozen=True, eq=False)
class StemProfile:
    """The target's stem against the reference's, height by height (reference frame).

    heights_m : slab heights both stems reach; offsets_m : K x 2, target minus reference;
    std_m : each offset's noise std; radii_m : the shared radius; base_z_m, height_m : the tree's
    base and height (the bend's 0 and 1); model : the offsets explained (None with too few slabs);
    base_xy_m : where the reference's stem was traced from (x, y): what a tilt turns about;
    crown : whether the reference's tree holds a crown (`holds_crown`; True when no stem was traced
    to tell): without one a fitted bend is no crown's motion, and a bare stem cannot tell it from a
    pose that is off.
    """

    heights_m: np.ndarray
    offsets_m: np.ndarray
    std_m: np.ndarray
    radii_m: np.ndarray
    base_z_m: float
    height_m: float
    model: StemModel | None
    base_xy_m: np.ndarray
    crown: bool = True

    @property
    def n(self) -> int:
        return int(len(self.heights_m))

    @property
    def spans_bend(self) -> bool:
        """Traced high enough to tell a bend from a tilt (at least `MIN_SLABS` slabs, up to
        `MIN_SPAN` of the tree's height): lower, a tilt and a bend explain the offsets alike."""
        return self.n >= MIN_SLABS and (self.heights_m[-1] - self.base_z_m) >= MIN_SPAN * self.height_m

    def stable_height_m(self, tolerance_m: float) -> float:
        """Height above the base up to which the target's stem stands where the reference's did
        within `tolerance_m`, by the fitted model (the bend is what moves; a single slab traced onto
        a branch does not end it); the highest slab traced when the stem did not bend measurably,
        NaN when there is no model."""
        m = self.model
        if m is None:
            return float("nan")
        z = np.linspace(self.base_z_m, self.heights_m[-1], 200)
        off = np.hypot(*m.offsets(z, self.base_z_m, self.height_m).T)
        over = off > tolerance_m
        return float((z[np.argmax(over)] if over.any() else z[-1]) - self.base_z_m)

    def lined_up(self, max_tilt_deg: float, max_shift_m: float) -> bool | None:
        """Whether the two stems line up: the target's leans at most `max_tilt_deg` against the
        reference's and stands at most `max_shift_m` from it (or 3 times the profile's noise, when
        larger); None without a model."""
        m = self.model
        if m is None:
            return None
        tilt, tilt_std = np.degrees(np.hypot(*m.tilt)), np.degrees(np.hypot(*m.std[2:4]))
        shift, shift_std = np.hypot(*m.shift_m), np.hypot(*m.std[0:2])
        return bool(tilt <= max(max_tilt_deg, 3.0 * tilt_std) and shift <= max(max_shift_m, 3.0 * shift_std))

    @property
    def sway_m(self) -> float:
        """How far the target's stem top had moved from the reference's (the bend at the top)."""
        return float(np.hypot(*self.model.bend_m)) if self.model is not None else float("nan")

    @property
    def sway_std_m(self) -> float:
        return float(np.hypot(*self.model.std[4:6])) if self.model is not None else float("nan")


def fit_profile(heights_m: np.ndarray, offsets_m: np.ndarray, std_m: np.ndarray, base_z_m: float,
                height_m: float, scale_m: float = 0.003, hinge_m: float = 0.0) -> StemModel | None:
    """Shift, tilt and cantilever bend explaining the offsets (robust weighted least squares,
    Cauchy at `scale_m`; the cantilever bending from `hinge_m` below `base_z_m`); None with fewer
    than 5 slabs or heights too close to tell a tilt from a bend."""
    z = np.asarray(heights_m, dtype=float)
    if len(z) < 5 or np.ptp(z) < 0.2 * height_m:
        return None
    z_mid = float(np.median(z))
    A = np.c_[np.ones(len(z)), z - z_mid, cantilever((z - base_z_m + hinge_m) / (height_m + hinge_m))]
    sig = np.maximum(np.asarray(std_m, dtype=float), 1e-4)
    w = 1.0 / sig ** 2
    x = np.zeros((3, 2))
    for _ in range(10):
        Aw = A * w[:, None]
        x_new = np.linalg.lstsq(Aw.T @ A, Aw.T @ offsets_m, rcond=None)[0]
        res = np.hypot(*(offsets_m - A @ x_new).T)
        w = 1.0 / sig ** 2 / (1.0 + (res / scale_m) ** 2)
        done = np.abs(x_new - x).max() < 1e-6
        x = x_new
        if done:
            break
    res = np.hypot(*(offsets_m - A @ x).T)
    # A slab traced onto a branch is an outlier the weights have set aside: the scatter and the
    # unknowns' noise are those of the slabs the model keeps.
    keep = res <= 3.0 * max(scale_m, float(np.median(res)) * 1.4826)
    rms = float(np.sqrt(np.mean(res[keep] ** 2))) if keep.any() else float("nan")
    wk = np.where(keep, 1.0 / sig ** 2, 0.0)
    s2 = max(float(np.sum(wk * res ** 2) / max(np.sum(wk) * (1.0 - 3.0 / max(keep.sum(), 4)), 1e-300)) / 2.0,
             float(np.median(sig)) ** 2)
    cov = np.linalg.pinv((A * (wk / max(wk.max(), 1e-300))[:, None]).T @ A) * s2
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    return StemModel(x[0], x[1], x[2], np.repeat(std, 2), rms, z_mid, float(hinge_m))


def correction(model: StemModel, axis_xy: np.ndarray) -> np.ndarray:
    """4x4 that removes the profile's shift and tilt from target points in the reference frame (a
    small turn about horizontal axes through the stem at the model's mid height, then a shift)."""
    from ..geometry.rigid import make_transform, rotation_from_vector

    R = rotation_from_vector(np.array([model.tilt[1], -model.tilt[0], 0.0]))
    p0 = np.array([axis_xy[0], axis_xy[1], model.z_mid_m])
    return make_transform(R, p0 - R @ p0 - np.r_[model.shift_m, 0.0])


def stem_profile(ref_points: np.ndarray, tgt_points: np.ndarray, ref_xy: np.ndarray, tgt_xy: np.ndarray,
                 z_extent: tuple[float, float], loss_scale_m: float = 0.005, step_m: float = 0.25,
                 ref_trace: StemTrace | None = None, hinge_m: float = 0.0) -> StemProfile:
    """The profile of the target's stem (`tgt_points`, already in the reference frame) against the
    reference's, traced from `ref_xy` and `tgt_xy` at the tree's base (`z_extent`: its lowest and
    highest z in the reference frame). `ref_trace`: the reference's trace, when made already (it
    depends on the reference alone). `hinge_m`: the stem bends from this far below `z_extent`'s
    lowest (the fine stage's ground anchor finds it; 0 = from there)."""
    lo, hi = z_extent
    H = max(hi - lo, 1e-3)
    base = np.asarray(ref_xy, dtype=float)[:2].copy()
    a = ref_trace if ref_trace is not None else trace_stem(ref_points, ref_xy, lo, hi, step_m)
    b = trace_stem(tgt_points, tgt_xy, lo, hi, step_m)
    common, ia, ib = np.intersect1d(np.round(a.heights_m, 6), np.round(b.heights_m, 6), return_indices=True)
    if not len(common):
        return StemProfile(np.zeros(0), np.zeros((0, 2)), np.zeros(0), np.zeros(0), lo, H, None, base)
    pts, sec, mov = [], [], []
    for k, (i, j) in enumerate(zip(ia, ib)):
        p = ref_points[_even(a.members[i], _MAX_SLAB_POINTS)]
        q = tgt_points[_even(b.members[j], _MAX_SLAB_POINTS)]
        pts += [p, q]
        sec.append(np.full(len(p) + len(q), k))
        mov += [np.zeros(len(p), bool), np.ones(len(q), bool)]
    P, S, M = np.vstack(pts), np.concatenate(sec), np.concatenate(mov)
    centres = np.c_[a.centres_m[ia], a.heights_m[ia]]
    axes = np.tile([0.0, 0.0, 1.0], (len(ia), 1))
    radii = 0.5 * (a.radii_m[ia] + b.radii_m[ib])
    # The target's circle starts where its own trace put it, relative to the reference's.
    shift = np.c_[b.centres_m[ib] - a.centres_m[ia], np.zeros(len(ia))]
    P = P.copy()
    P[M] -= shift[S[M]]
    off, std = section_offsets(P, S, M, centres, axes, radii, loss_scale_m)
    off = off[:, :2] + shift[:, :2]
    # A slab whose circles the points hardly fix (a trace that strayed onto a branch) says nothing.
    ok = np.isfinite(std) & np.isfinite(off).all(axis=1) & (std <= _MAX_OFFSET_STD_M)
    h, off, std, radii = common[ok], off[ok], std[ok], radii[ok]
    return StemProfile(h, off, std, radii, lo, H, fit_profile(h, off, std, lo, H, hinge_m=hinge_m), base,
                       holds_crown(ref_points, lo, H, float(np.median(a.radii_m))))


#: A slab of a crown spreads wider than this (m), or than this many stem radii, across.
_CROWN_SPREAD_M, _CROWN_SPREAD_RADII = 1.0, 6.0
#: A tree holds a crown when at least this share of its slabs above the lowest third spread so.
_CROWN_SHARE = 0.25


def holds_crown(points: np.ndarray, base_z_m: float, height_m: float, stem_radius_m: float, step_m: float = 0.25) -> bool:
    """Whether `points` (one tree, z up) hold a crown: above the lowest third of its height, a slab
    in four at least spreads wider (5th to 95th percentile, across x or y) than a stem could (1 m,
    or 6 stem radii). A stem cut below its crown spreads no wider than itself: what a bend fitted
    to it says is not a crown's motion."""
    p = np.asarray(points, dtype=float)
    p = p[p[:, 2] >= base_z_m + height_m / 3.0]
    if not len(p):
        return False
    wide = max(_CROWN_SPREAD_M, _CROWN_SPREAD_RADII * stem_radius_m) if np.isfinite(stem_radius_m) else _CROWN_SPREAD_M
    k = np.floor((p[:, 2] - p[:, 2].min()) / step_m).astype(np.int64)
    order = np.argsort(k, kind="stable")
    bounds = np.searchsorted(k[order], np.arange(int(k.max()) + 2))
    spreads = [np.ptp(np.percentile(p[order[a:b], :2], [5, 95], axis=0), axis=0).max()
               for a, b in zip(bounds[:-1], bounds[1:]) if b - a >= _MIN_POINTS]
    return bool(spreads) and float(np.mean(np.asarray(spreads) > wide)) >= _CROWN_SHARE
