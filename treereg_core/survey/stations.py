"""One station of a survey, reduced to what its pairs need: its stems, traced up section by section,
its ground and a thinned cloud.

A survey station is a whole plot seen from one place (0.5-3 M points). Its pairs need far less of
it: the points round each stem at the section heights (`survey.heights_m` above the ground), the
ground near it, and a voxel-thinned cloud (the check that crowns agree, the joint placement's
samples). Those are kept; the station's own points are not, so a survey's memory grows with the
stations' summaries, not their points.

A stem is found at breast height (`prepare.target.find_stems`) and traced up: each section's points
within the stem's radius plus `survey.margin_m` of the centre the section below gave, a Taubin
circle fitted to them, its points within a few centimetres of the circle kept (a branch leaving
the stem is not the stem). Tracing stops where two sections in a row give no plausible circle (the
crown, an occluded stretch).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from ..fine.fitting import fit_circle_taubin
from ..geometry.normals import pca_normals, voxel_downsample
from ..params import Params, SurveyParams
from ..prepare.ground import find_ground
from ..scan import MIN_POINTS
from ..prepare.level import find_levelling, levelled
from ..prepare.mixed import remove_mixed
from ..prepare.target import Stems, find_stems
from ..scan import Scan

#: A section's points lie within this of their circle (a branch leaving the stem is dropped).
_ON_CIRCLE_M = 0.02
#: A stem's section radius may differ this much (fraction) from its breast-height radius.
_RADIUS_TOLERANCE = 0.35
#: Tracing stops after this many sections in a row without a plausible circle.
_MISSES = 2
#: Ground points kept per station (a voxel-thinned subset of its ground).
_MAX_GROUND = 40_000


@dataclass(frozen=True, kw_only=True, eq=False)
class StemColumn:
    """One stem of one station: its sections' points and circles (levelled station frame).

    points : M x 3, the points of every section that gave a plausible circle.
    section : M, the index into `survey.heights_m` of each point's section.
    centres : S x 2 and radii : S, each section's circle (NaN where none was plausible).
    """

    xy: np.ndarray
    radius_m: float
    points: np.ndarray
    section: np.ndarray
    centres: np.ndarray
    radii: np.ndarray

    @property
    def n_sections(self) -> int:
        return int(np.isfinite(self.radii).sum())


@dataclass(frozen=True, kw_only=True, eq=False)
class SurveyStation:
    """What a survey keeps of one station (levelled frame: `T_level` turns the scan as given into it).

    plane : the ground plane (a, b, c, d), None when none was found.
    stems : the stems at breast height (as the stem maps use them); columns : each traced up.
    ground : ground points, voxel-thinned; cloud : every point, voxel-thinned (`survey.cloud_voxel_m`).
    reason : why it cannot be registered ("" when it can).
    """

    name: str
    n_points: int
    T_level: np.ndarray | None
    plane: np.ndarray | None
    stems: Stems
    columns: tuple[StemColumn, ...]
    ground: np.ndarray
    cloud: np.ndarray
    reason: str = ""
    notes: tuple[str, ...] = field(default=())

    # Indexes a station's pairs all ask for: made once, on first use (each pair reads its reference's).
    @cached_property
    def ground_tree(self) -> cKDTree:
        return cKDTree(self.ground)

    @cached_property
    def ground_normals(self) -> np.ndarray:
        """Each ground point's normal from its 8 nearest ground points, pointing up."""
        n = pca_normals(self.ground, self.ground_tree, self.ground, k=8)
        return n * np.sign(n[:, 2:3] + 1e-12)

    @cached_property
    def cloud_tree(self) -> cKDTree:
        return cKDTree(self.cloud)

    def ground_z(self, xy: np.ndarray) -> np.ndarray:
        """The ground's height under the points `xy` (K x 2): on its plane, else the lowest points'."""
        xy = np.atleast_2d(xy)
        if self.plane is not None:
            a, b, c, d = self.plane
            return -(a * xy[:, 0] + b * xy[:, 1] + d) / c
        low = float(np.quantile(self.cloud[:, 2], 0.01)) if len(self.cloud) else 0.0
        return np.full(len(xy), low)


def survey_station(scan: Scan, params: Params) -> SurveyStation:
    """`scan` as a survey station: mixed pixels removed, levelled, ground, stems traced up."""
    pp, sv = params.prepare, params.survey
    # A stand-in sharing the points: the angles the mixed-pixel search caches on it (16 bytes a
    # point) go with it, not onto the caller's scan (60 stations: 0.6 GB held to the end).
    mixed = remove_mixed(scan.with_points(scan.points), enabled=pp.mixed_pixels, tolerance_m=pp.mixed_tolerance_m, slope=pp.mixed_slope,
                         dense_share=pp.mixed_dense_share, max_share=pp.mixed_max_share).scan
    lv = find_levelling(mixed.points, mixed.pose, min_deg=pp.level_min_deg, stem_margin_deg=pp.level_stem_margin_deg) \
        if pp.level else None
    st = levelled(mixed, lv.R) if lv is not None and lv.R is not None else mixed
    pts = st.points
    # The ground plane as the prepare stage finds it, without its copy of the points above it.
    plane = find_ground(pts, pp)[0] if pp.remove_ground and len(pts) >= MIN_POINTS else None
    heights = pts @ plane[:3] + plane[3] if plane is not None else pts[:, 2] - float(np.quantile(pts[:, 2], 0.001))
    on_ground = heights < pp.ground_band_m if plane is not None else np.zeros(len(pts), dtype=bool)
    above_pts, above_h = pts[~on_ground], heights[~on_ground]
    stems = find_stems(above_pts, above_h, params.target)
    columns = trace_stems(above_pts, above_h, stems, sv)
    del above_pts, above_h, heights
    ground = voxel_downsample(pts[on_ground], sv.ground_voxel_m)
    if len(ground) > _MAX_GROUND:
        ground = ground[np.random.default_rng(0).choice(len(ground), _MAX_GROUND, replace=False)]
    reason = ""
    if len(stems) < sv.min_stems:
        reason = (f"it shows {len(stems)} stem{'s' if len(stems) != 1 else ''} at breast height, fewer than "
                  f"survey.min_stems = {sv.min_stems} a survey pair is registered on")
    return SurveyStation(name=scan.name, n_points=scan.n_points, T_level=None if lv is None else lv.T, plane=plane,
                         stems=stems, columns=columns, ground=ground,
                         cloud=voxel_downsample(pts, sv.cloud_voxel_m).astype(np.float32),  # half the memory; mm-exact
                         reason=reason)


def trace_stems(points: np.ndarray, heights: np.ndarray, stems: Stems, sv: SurveyParams) -> tuple[StemColumn, ...]:
    """Every stem of `stems` traced up through the sections at `sv.heights_m` (see the module doc)."""
    if not len(stems):
        return ()
    hs = np.asarray(sv.heights_m, dtype=float)
    reach = float(stems.radius_m.max()) + sv.margin_m + 0.5
    near = (heights > hs.min() - sv.slab_m) & (heights < hs.max() + sv.slab_m)
    idx = np.flatnonzero(near)
    d, which = cKDTree(stems.xy).query(points[idx, :2], distance_upper_bound=reach)
    idx, which = idx[np.isfinite(d)], which[np.isfinite(d)]
    order = np.argsort(which, kind="stable")
    bounds = np.searchsorted(which[order], np.arange(len(stems) + 1))
    rng = np.random.default_rng(0)
    out = []
    for k in range(len(stems)):
        mine = idx[order[bounds[k]:bounds[k + 1]]]
        out.append(_trace(points[mine], heights[mine], stems.xy[k], float(stems.radius_m[k]), hs, sv, rng))
    return tuple(out)


def _trace(pts: np.ndarray, h: np.ndarray, xy0: np.ndarray, r0: float, hs: np.ndarray, sv: SurveyParams,
           rng: np.random.Generator) -> StemColumn:
    """One stem's sections, from breast height up and then down (each starts at its neighbour's centre)."""
    S = len(hs)
    centres = np.full((S, 2), np.nan)
    radii = np.full(S, np.nan)
    keep: list[np.ndarray] = [np.zeros(0, dtype=np.int64)] * S
    start = int(np.argmin(np.abs(hs - 1.3)))
    for direction in (range(start, S), range(start - 1, -1, -1)):
        c, misses = np.asarray(xy0, dtype=float), 0
        for s in direction:
            slab = np.flatnonzero(np.abs(h - hs[s]) <= sv.slab_m / 2)
            slab = slab[np.hypot(*(pts[slab, :2] - c).T) <= r0 * (1 + _RADIUS_TOLERANCE) + sv.margin_m]
            fit = fit_circle_taubin(pts[slab, :2]) if len(slab) >= 8 else None
            if fit is not None and fit.ok:
                on = np.abs(np.hypot(*(pts[slab, :2] - fit.centre_m).T) - fit.radius_m) <= _ON_CIRCLE_M
                if on.sum() >= 8:
                    fit = fit_circle_taubin(pts[slab[on], :2])
                    slab = slab[on]
            good = (fit is not None and fit.ok and abs(fit.radius_m - r0) <= _RADIUS_TOLERANCE * r0 + 0.01
                    and fit.rms_m <= sv.max_fit_rms_m and float(np.hypot(*(fit.centre_m - c))) <= r0 + sv.margin_m)
            if not good:
                misses += 1
                if misses >= _MISSES:
                    break
                continue
            assert fit is not None
            misses = 0
            c = np.asarray(fit.centre_m, dtype=float)
            centres[s], radii[s] = c, fit.radius_m
            if len(slab) > sv.max_section_points:
                slab = rng.choice(slab, sv.max_section_points, replace=False)
            keep[s] = slab
    sec = np.concatenate([np.full(len(k), s) for s, k in enumerate(keep)]).astype(np.int64)
    allk = np.concatenate(keep).astype(np.int64)
    return StemColumn(xy=np.asarray(xy0, dtype=float), radius_m=r0, points=pts[allk], section=sec, centres=centres, radii=radii)
