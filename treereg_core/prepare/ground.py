"""Preparing the scans before projection: height crop, ground removal, the target tree of a plot
(`prepare.target`), radius crop around the target's stem.

The ground matters for the coarse stage: it fills the lower part of every projection image, where
it carries no structure ORB can match, and it drags the rotation centre (x_mean, y_mean) of the
image sequence away from the tree. It is found as a robust plane through the lowest point of each
horizontal grid cell; points within a band above that plane (and any below it) are removed.

A scan without ground (a tree cut out of a larger cloud) must come through untouched: the plane is
accepted only when it is nearly level, holds many cells, and has almost no points below it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..params import PrepareParams, TargetParams, set_flag
from ..results import Metric
from ..scan import MIN_POINTS, Scan
from .target import Stems, TargetChoice, choose_targets, find_stems

# The plane's acceptance thresholds (slope, cells, points below) are fields of `PrepareParams`
# (ground_max_slope_deg, ground_min_cells, ground_min_cell_share, ground_max_below_share).
#: Points used to find the ground plane (internal: ~100k lowest-point candidates are as good as all).
GROUND_SAMPLE = 100_000


@dataclass(frozen=True, eq=False, kw_only=True)
class PreparedScan:
    """A scan ready for projection.

    Attributes
    ----------
    ok, message, metrics : as every stage result.
    scan : the prepared scan (kept points only; same station, steps and source).
    kept_mask : (N,) bool over the original points: kept in `scan`.
    ground_mask : (N,) bool over the original points: removed as ground.
    plane : (a, b, c, d) with a x + b y + c z + d = 0, (a, b, c) unit and c > 0, or None (no ground found
        or ground removal off).
    stem_xy : horizontal position of the stem used for the radius crop (the target's, in a plot), or
        None when not cropped.
    stems : K x 3 (x, y, radius) of the stems found at breast height (empty when none were looked for).
    target : how the target tree was chosen (or why the scan keeps all its points), or "".
    T_stem_map : 4 x 4 placing this station's stems onto the reference's (yaw + horizontal shift),
        when its stem map matched; None otherwise (and for the reference).
    station : the whole station at the working resolution, before ground removal and crops, its
        mixed pixels removed (what the masks index; the free-space test needs everything the scanner
        saw); None = as read.
    mixed_points : M x 3, the mixed pixels the prepare stage removed from the station (its frame):
        drawn in the Scans stage; the free-space test is blind where they were.
    mixed_not_filtered : why the mixed-pixel filter stood down on this scan ("" when it ran or is off).
    reason, hint : when not `ok`, why the scan could not be prepared (without its name: the reason of
        its verdict) and what to do; `message` is both, after its name.
    T_level : 4 x 4 rotation about the scanner (levelled <- as given) when the scan's up was not its z
        (`prepare.level`): then `scan`, `station`, `mixed_points`, `plane`, `stems` and `stem_xy` are of
        the levelled scan, and so is every later stage's transform; None = the scan as given.
    """

    ok: bool
    message: str
    metrics: tuple[Metric, ...]
    scan: Scan
    kept_mask: np.ndarray
    ground_mask: np.ndarray
    plane: tuple[float, float, float, float] | None
    stem_xy: tuple[float, float] | None
    stems: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    target: str = ""
    T_stem_map: np.ndarray | None = None
    station: Scan | None = None
    mixed_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    mixed_not_filtered: str = ""
    reason: str = ""
    hint: str = ""
    T_level: np.ndarray | None = None

    def ground_z(self, xy: np.ndarray, default: float) -> np.ndarray:
        """Height of the ground plane below the points `xy` (K x 2, the scan's frame); `default`
        everywhere when no plane was found."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        if self.plane is None:
            return np.full(len(xy), default)
        a, b, c, d = self.plane
        return -(a * xy[:, 0] + b * xy[:, 1] + d) / c


def cell_minima(points: np.ndarray, cell_m: float) -> np.ndarray:
    """Indices of the lowest point of every occupied `cell_m` x `cell_m` horizontal cell."""
    ij = np.floor(points[:, :2] / cell_m).astype(np.int64)
    ij -= ij.min(axis=0)
    key = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    order = np.lexsort((points[:, 2], key))
    k = key[order]
    first = np.r_[True, k[1:] != k[:-1]]
    return order[first]


def fit_plane_ransac(
    pts: np.ndarray, tol_m: float, iterations: int = 300, seed: int = 0
) -> tuple[np.ndarray, np.ndarray] | None:
    """Robust plane (unit normal with n_z >= 0, offset d) through `pts`, and its inlier mask.

    Hypotheses from random triples, the one with most points within `tol_m` wins, then a least-squares
    refit (SVD) on its inliers.
    """
    n = len(pts)
    if n < 3:
        return None
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, n, size=(iterations, 3))
    a, b, c = pts[idx[:, 0]], pts[idx[:, 1]], pts[idx[:, 2]]
    nrm = np.cross(b - a, c - a)
    length = np.linalg.norm(nrm, axis=1)
    good = length > 1e-9
    if not good.any():
        return None
    nrm = nrm[good] / length[good, None]
    d = -(nrm * a[good]).sum(axis=1)
    counts = (np.abs(pts @ nrm.T + d) < tol_m).sum(axis=0)
    h = int(np.argmax(counts))
    inl = np.abs(pts @ nrm[h] + d[h]) < tol_m
    centre = pts[inl].mean(axis=0)
    _, _, vt = np.linalg.svd(pts[inl] - centre, full_matrices=False)
    normal = vt[2] if vt[2, 2] >= 0 else -vt[2]
    d0 = -float(normal @ centre)
    return np.r_[normal, d0], np.abs(pts @ normal + d0) < tol_m


def find_ground(points: np.ndarray, prepare: PrepareParams) -> tuple[np.ndarray | None, str]:
    """The ground plane (a, b, c, d) of a scan, or None with the reason it was rejected (the `ground_*`
    fields of `prepare`)."""
    cell_m, band_m = prepare.ground_cell_m, prepare.ground_band_m
    # A plane needs no more than ~100k points: lowest points of a strided subset are as good.
    sub = points[:: max(1, len(points) // GROUND_SAMPLE)]
    low = sub[cell_minima(sub, cell_m)]
    tol = max(band_m / 2.0, 0.05)
    fitted = fit_plane_ransac(low, tol)
    if fitted is None:
        return None, "too few cells for a ground plane"
    plane, inl = fitted
    slope = float(np.degrees(np.arccos(min(abs(plane[2]), 1.0))))
    if slope > prepare.ground_max_slope_deg:
        return None, f"lowest points lie on a plane tilted {slope:.0f} deg: not ground"
    n_in = int(inl.sum())
    if n_in < prepare.ground_min_cells or n_in < prepare.ground_min_cell_share * len(low):
        return None, f"only {n_in} of {len(low)} cells have their lowest point on one plane"
    height = points @ plane[:3] + plane[3]
    below = float(np.mean(height < -band_m))
    if below > prepare.ground_max_below_share:
        return None, f"{below:.1%} of the points lie below the candidate plane: not ground"
    return plane, ""


def stem_position(points: np.ndarray, heights: np.ndarray, cell_m: float = 0.25) -> np.ndarray:
    """Horizontal stem position: the densest cell among the lowest 2 m of points (or lowest 20%)."""
    cut = max(float(np.quantile(heights, 0.2)), float(heights.min()) + 2.0)
    low = points[heights <= cut, :2]
    ij = np.floor(low / cell_m).astype(np.int64)
    ij -= ij.min(axis=0)
    key = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    best = np.bincount(key).argmax()
    return np.median(low[key == best], axis=0)


@dataclass(frozen=True, eq=False, kw_only=True)
class _Ground:
    """The first step of preparation: the points kept by the height crop and ground removal."""

    kept: np.ndarray
    ground: np.ndarray
    plane: np.ndarray | None
    note: str

    def heights(self, points: np.ndarray) -> np.ndarray:
        """Height above the ground plane (above the lowest points without one)."""
        if self.plane is not None:
            return points @ self.plane[:3] + self.plane[3]
        return points[:, 2] - (float(np.quantile(points[:, 2], 0.001)) if len(points) else 0.0)


def _remove_ground(scan: Scan, p: PrepareParams) -> _Ground:
    pts = scan.points
    n = len(pts)
    kept = np.ones(n, dtype=bool)
    if p.crop_z_min_m is not None:
        kept &= pts[:, 2] >= p.crop_z_min_m
    if p.crop_z_max_m is not None:
        kept &= pts[:, 2] <= p.crop_z_max_m
    ground = np.zeros(n, dtype=bool)
    plane: np.ndarray | None = None
    note = "ground removal off"
    if p.remove_ground and kept.sum() >= MIN_POINTS:
        plane, why = find_ground(pts[kept], p)
        if plane is not None:
            height = pts @ plane[:3] + plane[3]
            ground = kept & (height < p.ground_band_m)
            kept &= ~ground
            note = f"ground plane found, slope {np.degrees(np.arccos(min(abs(plane[2]), 1.0))):.1f} deg"
        else:
            note = f"no ground removed ({why})"
    return _Ground(kept=kept, ground=ground, plane=plane, note=note)


def prepare_scan(scan: Scan, *, prepare: PrepareParams, target: TargetParams | None = None) -> PreparedScan:
    """Prepare one scan on its own (see `prepare_scans`; a single station can only pick its target
    with `target.tree_at`, or as the stem nearest the scanner)."""
    return prepare_scans([scan], prepare=prepare, target=target or TargetParams(select="off"))[0]


def prepare_scans(scans: list[Scan], *, prepare: PrepareParams, target: TargetParams) -> list[PreparedScan]:
    """Crop every scan by height, remove its ground, find the target tree, crop to it.

    Parameters
    ----------
    scans : the stations as read; the first is the reference (its frame holds `target.tree_at`).
    prepare : ground removal, crops.
    target : target selection (`prepare.target`): in a plot, each scan is cut to `target.radius_m`
        (or `prepare.crop_radius_m` when set) around its view of the target stem.

    Returns
    -------
    One PreparedScan per scan; `ok` is False (with the scan left as it was) when fewer than
    MIN_POINTS points would remain.
    """
    grounds = [_remove_ground(s, prepare) for s in scans]
    if target.select == "off":
        stems = [Stems(np.zeros((0, 2)), np.zeros(0)) for _ in scans]
        choices = [TargetChoice(None, "") for _ in scans]
    else:
        stems = [find_stems(s.points[g.kept], g.heights(s.points[g.kept]), target) for s, g in zip(scans, grounds)]
        choices = choose_targets(stems, target=target, ref_label=scans[0].label)
    radius = prepare.crop_radius_m if prepare.crop_radius_m is not None else target.radius_m
    return [_finish(s, g, st, ch, prepare, radius) for s, g, st, ch in zip(scans, grounds, stems, choices)]


def _finish(scan: Scan, g: _Ground, stems: Stems, choice: TargetChoice, p: PrepareParams, radius_m: float) -> PreparedScan:
    pts = scan.points
    n = len(pts)
    kept = g.kept.copy()
    stem = None
    if choice.xy is not None:
        stem = np.asarray(choice.xy)
        kept &= np.hypot(pts[:, 0] - stem[0], pts[:, 1] - stem[1]) <= radius_m
    elif p.crop_radius_m is not None and kept.sum() >= MIN_POINTS:
        stem = stem_position(pts[kept], g.heights(pts[kept]))
        kept &= np.hypot(pts[:, 0] - stem[0], pts[:, 1] - stem[1]) <= p.crop_radius_m
    n_kept = int(kept.sum())
    metrics = [
        Metric("points in", "", n),
        Metric("points kept", "", n_kept),
        Metric("ground points removed", "", int(g.ground.sum())),
        Metric("ground", "", g.note),
        Metric("angular step", "deg", scan.step.describe()),
    ]
    if choice.how:
        metrics += [Metric("stems at breast height", "", len(stems)), Metric("target", "", choice.how)]
        if stem is not None:
            metrics.append(Metric("target stem x, y", "m", f"{stem[0]:.2f}, {stem[1]:.2f}"))
    plane_t = None if g.plane is None else tuple(float(v) for v in g.plane)
    stem_t = None if stem is None else (float(stem[0]), float(stem[1]))
    common = dict(metrics=tuple(metrics), plane=plane_t, stem_xy=stem_t, stems=stems.as_array(), target=choice.how,
                  T_stem_map=choice.T_ref_scan)
    if n_kept < MIN_POINTS:
        reason, hint = _too_few(n, n_kept, g, p)
        return PreparedScan(
            ok=False, message=f"{scan.label}: {reason}; {hint}", reason=reason, hint=hint,
            scan=scan, kept_mask=np.ones(n, dtype=bool), ground_mask=np.zeros(n, dtype=bool), **common,
        )
    return PreparedScan(ok=True, message="", scan=scan.with_points(pts[kept]), kept_mask=kept, ground_mask=g.ground,
                        **common)


def _too_few(n: int, n_kept: int, g: _Ground, p: PrepareParams) -> tuple[str, str]:
    """Why a scan kept too few points to register, and what to do. A scan whose points all lie on its
    ground plane (a crop that missed the tree) is said to hold only ground: no crop around a stem
    could help it."""
    n_ground, n_above = int(g.ground.sum()), int(g.kept.sum())
    crop = "prepare.crop_z_min_m" if p.crop_z_min_m is not None else ""
    crop = " and ".join(c for c in (crop, "prepare.crop_z_max_m" if p.crop_z_max_m is not None else "") if c)
    if g.plane is not None and n_above < MIN_POINTS and n_ground >= MIN_POINTS:
        after = f" after the height crop ({crop})" if crop else ""
        reason = (f"it holds only ground: {n_ground} of its {n} points lie on its ground plane (within prepare.ground_band_m "
                  f"= {p.ground_band_m:g} m of it) and {n_above} above it{after}, so it shows no stem to register")
        hint = ("leave it out, or give the scan of the tree (the whole station, or a crop reaching up the stem)"
                + (f"; widen the height crop ({crop})" if crop else "")
                + ("; if a short stem is there, a thinner ground band keeps more of it "
                   f"({set_flag('prepare.ground_band_m', round(p.ground_band_m / 3.0, 3))})" if p.ground_band_m > 0 else ""))
        return reason, hint
    return (f"only {n_kept} of {n} points left after cropping and ground removal",
            "widen the crop (target.radius_m, or prepare.crop_radius_m when set; prepare.crop_z_min_m, prepare.crop_z_max_m) "
            f"or lower the ground band (prepare.ground_band_m, e.g. {set_flag('prepare.ground_band_m', 0.1)})")
