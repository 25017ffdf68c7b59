"""Cross-sections for inspecting a registration: thin slabs of every scan, under each registration.

The paper explains and judges its method with cross-sections: a slice of one scan separates into
arcs on the scan's own angular grid (Fig. 6); the arcs of the stem and the branches are fitted by
circles (2.2.3); in a well registered tree the sections of all scans make one ring, in a poorly
registered one several separate arcs (Figs. 11c/d, 12b, 19). `cross_sections` cuts such slabs at
any heights, for every scan and every registration given (coarse, fine, ICP), separates each
scan's slab into arcs exactly as the arcs stage does, fits a circle to each arc in the section
plane, judges it like the sections stage (`SectionsParams`) and applies the paper's 4.2 taper check
against the slab below.

A slab holds the points with |z - height| <= thickness / 2 in the reference frame (after the
scan's transform). For the stem the section plane is horizontal (the top view); for a branch it is
normal to the branch axis and the slab keeps only the points within `reach_m` of that axis.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Mapping, Sequence

import numpy as np

from ..fine.arcs import angular_cells, separate_arcs
from ..fine.fitting import Section, check_taper, fit_circle_taubin, judge_fit, parts_below
from ..geometry.rigid import apply_transform
from ..params import ArcParams, SectionsParams
from ..results import Metric
from ..scan import Scan


@dataclass(frozen=True)
class ScanCut:
    """One scan's slab at one height under one registration.

    Attributes
    ----------
    scan
        The scan's name; `index` its position (0 = reference).
    indices
        Indices into the scan's points of the slab's points.
    uv
        N x 2 coordinates in the section plane (metres, relative to the cross-section's origin).
    cells
        N x 2 (column, row) of each point in the scan's own angular grid (paper Fig. 6).
    labels
        Arc of each point (0 = largest), -1 for points of arcs smaller than `arcs.min_points`.
    sections
        One per arc: a circle fitted in the section plane (centre in the reference frame), judged
        by the fit thresholds and by the 4.2 taper check against the slab below.
    below
        Per section, the index of its "part below" in the slab below's `sections` (-1: none).
    """

    scan: str
    index: int
    indices: np.ndarray
    uv: np.ndarray
    cells: np.ndarray
    labels: np.ndarray
    sections: tuple[Section, ...]
    below: tuple[int, ...]

    @property
    def n_arcs(self) -> int:
        return len(self.sections)


@dataclass(frozen=True)
class Layer:
    """Every scan's slab at one height under one registration."""

    height_m: float
    scans: tuple[ScanCut, ...]


@dataclass(frozen=True)
class PoseCuts:
    """The layers under one registration ("coarse", "fine", "icp"), lowest first."""

    pose: str
    layers: tuple[Layer, ...]
    offsets_m: tuple[dict[str, float], ...]  # per layer: each target's main-section centre offset from the reference's

    def spread_m(self, layer: int = -1) -> float:
        """The largest offset of a target's section centre from the reference's in `layer` (NaN: none)."""
        vals = list(self.offsets_m[layer].values())
        return float(max(vals)) if vals else float("nan")


@dataclass(frozen=True)
class RingProfile:
    """Points unrolled along a circle: per scan name, each point's angle around the centre (degrees,
    from the section plane's u axis) and its distance from the circle (m, positive outside)."""

    centre_m: np.ndarray
    radius_m: float
    angle_deg: dict[str, np.ndarray]
    offset_m: dict[str, np.ndarray]


@dataclass(frozen=True)
class CrossSection:
    """Cross-sections at one or more heights, every scan, every registration given.

    Attributes
    ----------
    ok, message, metrics
        As every result; `ok` is False when no slab holds points.
    heights_m, thickness_m
        Layer heights (reference frame, ascending) and slab thickness.
    origin, axis, e1, e2
        The section plane: a point on it (the view's centre), its normal (vertical for the stem, the
        branch axis for a branch) and two in-plane unit vectors (u, v).
    poses
        One `PoseCuts` per registration, in the order given.
    """

    ok: bool
    message: str
    metrics: tuple[Metric, ...]
    heights_m: tuple[float, ...]
    thickness_m: float
    origin: np.ndarray
    axis: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    poses: tuple[PoseCuts, ...]

    def pose(self, name: str) -> PoseCuts | None:
        return next((p for p in self.poses if p.pose == name), None)

    def ring(self, pose: str, layer: int, band: float = 0.5) -> RingProfile | None:
        """Every scan's points of one layer unrolled along the reference's main section (the plausible
        fit nearest the view's centre): the angle around its centre and the distance from its
        circle. Registered well, every scan lies near 0; poorly, a target's arc lies off it, by up to
        the misalignment. Only points within `band` radii of the circle count (not other branches).
        None when the reference has no plausible section in that layer."""
        pc = self.pose(pose)
        if pc is None:
            return None
        lay = pc.layers[layer]
        ref = next((sc for sc in lay.scans if sc.index == 0), None)
        good = [s for s in ref.sections if s.plausible] if ref is not None else []
        if not good:
            return None
        h = lay.height_m
        at = self.origin + self.axis * (h - self.origin[2]) / self.axis[2] if abs(self.axis[2]) > 1e-6 else self.origin
        main = min(good, key=lambda s: float(np.linalg.norm(s.centre_m - at)))
        c = self.to_uv(main.centre_m)[0]
        angles, offsets = {}, {}
        for sc in lay.scans:
            d = sc.uv - c
            r = np.hypot(d[:, 0], d[:, 1])
            keep = np.abs(r - main.radius_m) <= band * main.radius_m
            angles[sc.scan] = np.degrees(np.arctan2(d[keep, 1], d[keep, 0]))
            offsets[sc.scan] = r[keep] - main.radius_m
        return RingProfile(main.centre_m.copy(), float(main.radius_m), angles, offsets)

    def to_uv(self, xyz: np.ndarray) -> np.ndarray:
        """Reference-frame points -> section-plane coordinates (metres)."""
        d = np.atleast_2d(np.asarray(xyz, dtype=float)) - self.origin
        return np.c_[d @ self.e1, d @ self.e2]


def plane_axes(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two in-plane unit vectors for a section normal to `axis`: x and y for a vertical axis."""
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    if abs(a[2]) > 0.999:
        return np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    e1 = np.cross([0.0, 0.0, 1.0], a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(a, e1)


# Eleven parameters: private; one slab's points, their in-plane coordinates and arc labels, and the
# slab's frame (origin, axis, e1, e2) to put each fitted centre back in 3-D.
def _fit_arcs(pts: np.ndarray, uv: np.ndarray, labels: np.ndarray, n: int, k_level: int, height: float,
              origin: np.ndarray, axis: np.ndarray, e1: np.ndarray, e2: np.ndarray, sections: SectionsParams) -> list[Section]:
    out = []
    for j in range(n):
        fit = judge_fit(fit_circle_taubin(uv[labels == j]), sections)
        centre = origin + fit.centre_m[0] * e1 + fit.centre_m[1] * e2 if fit.ok else np.full(3, np.nan)
        # The centre at the layer's height (the plane through origin may be tilted for a branch).
        out.append(Section(k_level, j, float(height), fit, centre, axis.copy(), float(fit.radius_m),
                           bool(fit.plausible), fit.reason))
    return out


def _offsets(layer: list[ScanCut], centre: np.ndarray, gate_m: float) -> dict[str, float]:
    """How far each target's section lies from the reference's main section (the plausible one
    nearest the view's centre: the stem, or the branch) in one layer: its nearest plausible section
    within the gate plus the radius. Targets without one are left out."""
    ref = next((sc for sc in layer if sc.index == 0), None)
    good = [s for s in ref.sections if s.plausible] if ref is not None else []
    if not good:
        return {}
    main = min(good, key=lambda s: float(np.linalg.norm(s.centre_m - centre)))
    out = {}
    for sc in layer:
        cand = [s for s in sc.sections if s.plausible]
        if sc.index == 0 or not cand:
            continue
        d = [float(np.linalg.norm(s.centre_m - main.centre_m)) for s in cand]
        k = int(np.argmin(d))
        if d[k] <= gate_m + main.radius_m:
            out[sc.scan] = d[k]
    return out


# Nine parameters: the scans, their poses and the heights, then by keyword the slab's thickness and
# the arcs/sections sections the fits follow, as the pipeline's.
def cross_sections(
    scans: Sequence[Scan],
    poses: Mapping[str, Sequence[np.ndarray | None]],
    heights_m: Sequence[float],
    *,
    thickness_m: float,
    arcs: ArcParams,
    sections: SectionsParams,
    origin: np.ndarray | None = None,
    axis: np.ndarray | None = None,
    reach_m: float | None = None,
) -> CrossSection:
    """Slabs of every scan at `heights_m` under each registration in `poses`.

    Parameters
    ----------
    scans
        The (prepared) scans, reference first, each in its scanner frame.
    poses
        Registration name -> one `T_ref_scan` per scan (the reference's is the identity; None for a
        scan without that registration, which is then left out).
    heights_m
        Layer heights in the reference frame.
    thickness_m
        Slab thickness.
    arcs, sections
        How slabs are separated into arcs (as the arcs stage) and how fits are judged (as the
        sections stage; `taper_check` and `taper_tolerance` decide the 4.2 check).
    origin, axis, reach_m
        The section plane's centre and normal (default: vertical, through the median point of the
        reference's slab at the middle height), and for a branch the distance from that axis within
        which points belong to it (None: the whole slab).
    """
    heights = np.sort(np.asarray(heights_m, dtype=float))
    half = thickness_m / 2.0
    axis = np.array([0.0, 0.0, 1.0]) if axis is None else np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    e1, e2 = plane_axes(axis)
    ref_pts = scans[0].points
    if origin is None:
        z_mid = float(heights[len(heights) // 2])
        near = np.abs(ref_pts[:, 2] - z_mid) <= half
        xy = np.median(ref_pts[near, :2], axis=0) if near.any() else np.median(ref_pts[:, :2], axis=0)
        origin = np.array([xy[0], xy[1], z_mid])
    origin = np.asarray(origin, dtype=float)

    def axis_point(z: float) -> np.ndarray:
        return origin + axis * (z - origin[2]) / axis[2] if abs(axis[2]) > 1e-6 else origin

    out_poses: list[PoseCuts] = []
    total = 0
    for pose_name, Ts in poses.items():
        per_scan_levels: dict[int, list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[Section]]]] = {}
        for i, scan in enumerate(scans):
            T = Ts[i] if i < len(Ts) else None
            if T is None:
                continue
            pts = apply_transform(np.asarray(T, dtype=float), scan.points)
            levels = []
            for k, h in enumerate(heights):
                idx = np.flatnonzero(np.abs(pts[:, 2] - h) <= half)
                if reach_m is not None and len(idx):
                    c = axis_point(h)
                    d = pts[idx] - c
                    perp = d - np.outer(d @ axis, axis)
                    idx = idx[np.einsum("ij,ij->i", perp, perp) <= reach_m * reach_m]
                p = pts[idx]
                uv = np.c_[(p - origin) @ e1, (p - origin) @ e2] if len(idx) else np.empty((0, 2))
                if len(idx):
                    ar = separate_arcs(scan, idx, arcs)
                    labels, n = ar.labels, ar.n_arcs
                    cells = np.c_[angular_cells(scan, idx)]
                else:
                    labels, n, cells = np.empty(0, dtype=np.int64), 0, np.empty((0, 2), dtype=np.int64)
                secs = _fit_arcs(p, uv, labels, n, k, float(h), axis_point(h), axis, e1, e2, sections)
                levels.append((idx, uv, cells, labels, secs))
                total += len(idx)
            per_scan_levels[i] = levels
        layers: list[list[ScanCut]] = [[] for _ in heights]
        for i, levels in per_scan_levels.items():
            flat = [s for lv in levels for s in lv[4]]
            partners = parts_below(flat, sections.gate_m)
            if sections.taper_check:
                flat = check_taper(flat, sections.taper_tolerance, sections.gate_m)
            pos = 0
            offsets = []
            for lv in levels:
                offsets.append(pos)
                pos += len(lv[4])
            for k, (idx, uv, cells, labels, secs) in enumerate(levels):
                mine = tuple(flat[offsets[k]:offsets[k] + len(secs)])
                below = tuple(partners.get(offsets[k] + j, -1) - (offsets[k - 1] if k else 0)
                              if partners.get(offsets[k] + j, -1) >= 0 else -1 for j in range(len(secs)))
                layers[k].append(ScanCut(scans[i].name, i, idx, uv, cells, labels, mine, below))
        offsets = tuple(_offsets(lay, axis_point(h), sections.gate_m) for lay, h in zip(layers, heights))
        out_poses.append(PoseCuts(pose_name, tuple(Layer(float(h), tuple(lay)) for h, lay in zip(heights, layers)),
                                  offsets))
    ok = total > 0
    msg = "" if ok else (f"no points within {half * 100:.0f} cm of {', '.join(f'{h:.2f}' for h in heights)} m "
                         "in any scan: pick a height inside the tree")
    metrics = tuple(Metric(f"{p.pose}: largest centre offset at {lay.height_m:.2f} m", "m", p.spread_m(k))
                    for p in out_poses for k, lay in enumerate(p.layers))
    return CrossSection(ok, msg, metrics, tuple(float(h) for h in heights), float(thickness_m), origin, axis, e1, e2,
                        tuple(out_poses))


def stem_section(scans: Sequence[Scan], poses: Mapping[str, Sequence[np.ndarray | None]], height_m: float, *,
                 thickness_m: float, below_m: float, arcs: ArcParams, sections: SectionsParams) -> CrossSection:
    """The horizontal cross-section at `height_m` (the top view), with the slab `below_m` lower for
    the 4.2 check (layer 0 is the part below, layer 1 the section asked for)."""
    return cross_sections(scans, poses, [height_m - below_m, height_m], thickness_m=thickness_m, arcs=arcs,
                          sections=sections)


# Ten parameters: the scans and poses, then by keyword the branch (point, axis, radius), its layers
# (heights, thickness, margin) and the arcs/sections sections.
def branch_section(scans: Sequence[Scan], poses: Mapping[str, Sequence[np.ndarray | None]], *, point_m: np.ndarray,
                   axis: np.ndarray, radius_m: float, layer_z_m: Sequence[float], thickness_m: float, margin_m: float,
                   arcs: ArcParams, sections: SectionsParams) -> CrossSection:
    """The evaluation layers of one branch (paper Fig. 12b): each slab keeps the points within the
    branch radius plus `margin_m` of its axis, seen along the axis."""
    # Branch arcs are small: a few points make an arc (as the evaluation separates them).
    arc_p = replace(arcs, min_points=min(arcs.min_points, 12))
    return cross_sections(scans, poses, layer_z_m, thickness_m=thickness_m, arcs=arc_p, sections=sections,
                          origin=np.asarray(point_m, dtype=float), axis=axis, reach_m=radius_m + margin_m)
