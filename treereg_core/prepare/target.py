"""Which tree of a plot is registered: stems at breast height, matched across stations, and the target.

A real station is a whole plot: the target tree, its neighbours (some nearer to the scanner than
the target), shrubs and ground, 360 degrees round. Fed whole to the rotating projection, the
neighbours swamp it. So before projection each station is cut to a disc around the target stem.

1. **Stems.** In a band at breast height (`target.stem_band_m`, 1.0-1.6 m above the ground) the points are
   gridded, connected cells grouped, and a circle fitted to each group: a group is a stem when its
   circle is plausible (3-80 cm radius, small residual, enough arc, centre behind the points as
   seen from the scanner, which sees the near side of a trunk).
2. **Stem maps.** Every station's stems form a map; maps of two stations differ by a turn about
   the vertical and a shift. Two stems of one map and two of the other, equally far apart, give
   such a transform; the one under which most stems land on a stem of similar radius wins (RANSAC
   over stem pairs). It places every station in the reference's frame, roughly (centimetres).
3. **The target.** Given by the user (`tree_at`, x y in the reference's frame: the nearest stem;
   a point with no stem near it while the reference holds stems elsewhere is refused, naming them),
   or by default the stem the stations surround: among the stems no gap between the stations'
   directions wider than a half turn leaves open, the one whose farthest station is nearest
   (stations stand round the target at similar distances). Each station is then cut to
   `radius_m` around its own view of that stem.

A station whose stem map cannot be matched keeps all its points (and says so); a scan that holds
fewer than `min_stems` stems (already cut to one tree) is left as it is.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..errors import ConfigError
from ..fine.fitting import fit_circle_taubin
from ..geometry.rigid import kabsch_yaw
from ..params import TargetParams

# The thresholds of the stem search, the stem maps and `tree_at` are fields of `TargetParams`
# (stem_band_m, stem_cell_m, ..., pick_radius_m): a plot with undergrowth or thin stems may need them.


@dataclass(frozen=True, eq=False)
class Stems:
    """Stems found in one station at breast height: centres `xy` (K x 2, m), `radius_m` (K,)."""

    xy: np.ndarray
    radius_m: np.ndarray

    def __len__(self) -> int:
        return len(self.radius_m)

    def as_array(self) -> np.ndarray:
        """K x 3 (x, y, radius)."""
        return np.column_stack([self.xy, self.radius_m]) if len(self) else np.zeros((0, 3))


@dataclass(frozen=True)
class TargetChoice:
    """The target of one station: where its stem is in that station's frame (None = no crop).

    how : a sentence: how the target was chosen, or why the station keeps all its points.
    T_ref_scan : the stem-map transform (4 x 4, yaw and horizontal shift) of the station onto the
        reference, when its stem map matched (None for the reference and unmatched stations).
    matched : stems matched with the reference's map.
    """

    xy: tuple[float, float] | None
    how: str
    T_ref_scan: np.ndarray | None = None
    matched: int = 0


def find_stems(points: np.ndarray, heights: np.ndarray, target: TargetParams = TargetParams()) -> Stems:
    """Stems in the breast-height band of one station (points N x 3, heights above the ground N)."""
    band, (r_lo, r_hi), min_points = target.stem_band_m, target.stem_radius_m, target.stem_min_points
    sel = (heights > band[0]) & (heights < band[1]) & (np.hypot(points[:, 0], points[:, 1]) < target.stem_max_range_m)
    xy = points[sel, :2]
    empty = Stems(np.zeros((0, 2)), np.zeros(0))
    if len(xy) < min_points:
        return empty
    ij = np.floor(xy / target.stem_cell_m).astype(np.int64)
    ij -= ij.min(axis=0)
    shape = tuple(ij.max(axis=0) + 1)
    if shape[0] * shape[1] > 64_000_000:  # a station spanning kilometres: not a plot
        return empty
    occ = np.zeros(shape, dtype=bool)
    occ[ij[:, 0], ij[:, 1]] = True
    # One cell of dilation joins the sparse points of a far stem; 8-connectivity follows its arc.
    lab, n = ndimage.label(ndimage.binary_dilation(occ), structure=np.ones((3, 3)))
    plab = lab[ij[:, 0], ij[:, 1]]
    order = np.argsort(plab, kind="stable")
    bounds = np.searchsorted(plab[order], np.arange(1, n + 2))
    centres, radii = [], []
    for k in range(n):
        idx = order[bounds[k]:bounds[k + 1]]
        if len(idx) < min_points:
            continue
        g = xy[idx]
        if np.ptp(g, axis=0).max() > 2 * r_hi:
            continue  # a hedge, a wall, a fallen log: not one stem
        fit = fit_circle_taubin(g)
        if not fit.ok or not (r_lo <= fit.radius_m <= r_hi):
            continue
        if fit.rms_m > max(0.01, 0.2 * fit.radius_m) or fit.arc_deg < target.stem_min_arc_deg:
            continue
        # The scanner sees a trunk's near side: the centre lies farther than the points.
        if np.hypot(*fit.centre_m) <= np.median(np.hypot(g[:, 0], g[:, 1])):
            continue
        centres.append(fit.centre_m)
        radii.append(fit.radius_m)
    if not centres:
        return empty
    return Stems(np.array(centres), np.array(radii))


def _pairs(s: Stems, max_m: float = 40.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    i, j = np.triu_indices(len(s), 1)
    d = np.linalg.norm(s.xy[i] - s.xy[j], axis=1)
    ok = (d > 1.0) & (d < max_m)
    return i[ok], j[ok], d[ok]


def _radius_ok(ra: np.ndarray, rb: np.ndarray, tolerance: float) -> np.ndarray:
    return np.abs(ra - rb) <= tolerance * np.maximum(ra, rb) + 0.02


def match_stem_maps(ref: Stems, tgt: Stems, tol_m: float = 0.2,
                    target: TargetParams = TargetParams()) -> tuple[np.ndarray | None, np.ndarray]:
    """The 4 x 4 (yaw + horizontal shift) mapping `tgt`'s stems onto `ref`'s, and the matched pairs
    (M x 2 indices ref, tgt); (None, empty) when fewer than `target.min_matched` stems agree.

    Hypotheses come from a pair of stems in each map equally far apart (within `tol_m`), tried both
    ways round; each is scored by the stems landing within `target.match_gate_m` of a stem of
    similar radius (`target.match_radius_tolerance`), the best refitted on its matches.
    """
    found = stem_map_hypotheses(ref, tgt, tol_m=tol_m, target=target, n=1)
    return found[0] if found else (None, np.zeros((0, 2), dtype=np.int64))


def stem_map_hypotheses(ref: Stems, tgt: Stems, *, tol_m: float = 0.2, target: TargetParams = TargetParams(),
                        n: int = 1, distinct_m: float = 1.0, max_hypotheses: int | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Up to `n` distinct stem-map transforms, best first (see `match_stem_maps`), each with its
    matched pairs; a later one moves the target's stems at least `distinct_m` from every earlier
    one's (a regular planting fits its stem map shifted by a row as well). At most `max_hypotheses`
    (None: all, as the prepare stage scores them) are scored, a fixed random draw of them (RANSAC's): a plot of a few dozen stems gives a few
    thousand, a regular planting of fifty hundreds of thousands (112 s for nine stations' pairs)."""
    gate, tolerance = target.match_gate_m, target.match_radius_tolerance
    if len(ref) < 2 or len(tgt) < 2:
        return []
    ai, aj, ad = _pairs(ref)
    bi, bj, bd = _pairs(tgt)
    if len(ad) == 0 or len(bd) == 0:
        return []
    order = np.argsort(ad)
    ad_s = ad[order]
    lo = np.searchsorted(ad_s, bd - tol_m)
    hi = np.searchsorted(ad_s, bd + tol_m)
    cnt = hi - lo
    hb = np.repeat(np.arange(len(bd)), cnt)
    ha = order[np.concatenate([np.arange(a, b) for a, b in zip(lo, hi)])] if cnt.sum() else np.zeros(0, dtype=np.int64)
    if len(ha) == 0:
        return []
    # Both orientations of each pair: (i -> p, j -> q) and (i -> q, j -> p).
    A0 = np.concatenate([ai[ha], ai[ha]])
    A1 = np.concatenate([aj[ha], aj[ha]])
    B0 = np.concatenate([bi[hb], bj[hb]])
    B1 = np.concatenate([bj[hb], bi[hb]])
    keep = (_radius_ok(ref.radius_m[A0], tgt.radius_m[B0], tolerance)
            & _radius_ok(ref.radius_m[A1], tgt.radius_m[B1], tolerance))
    A0, A1, B0, B1 = A0[keep], A1[keep], B0[keep], B1[keep]
    if len(A0) == 0:
        return []
    if max_hypotheses is not None and len(A0) > max_hypotheses:  # a planting's rows repeat their distances
        pick = np.sort(np.random.default_rng(0).choice(len(A0), max_hypotheses, replace=False))
        A0, A1, B0, B1 = A0[pick], A1[pick], B0[pick], B1[pick]
    va = ref.xy[A1] - ref.xy[A0]
    vb = tgt.xy[B1] - tgt.xy[B0]
    yaw = np.arctan2(va[:, 1], va[:, 0]) - np.arctan2(vb[:, 1], vb[:, 0])
    c, s = np.cos(yaw), np.sin(yaw)
    mid_b = 0.5 * (tgt.xy[B0] + tgt.xy[B1])
    mid_a = 0.5 * (ref.xy[A0] + ref.xy[A1])
    t = mid_a - np.stack([c * mid_b[:, 0] - s * mid_b[:, 1], s * mid_b[:, 0] + c * mid_b[:, 1]], axis=1)
    radius_ok = _radius_ok(ref.radius_m[None, :], tgt.radius_m[:, None], tolerance)  # K_t x K_r

    def moved(k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (c[k, None] * tgt.xy[None, :, 0] - s[k, None] * tgt.xy[None, :, 1] + t[k, 0:1],
                s[k, None] * tgt.xy[None, :, 0] + c[k, None] * tgt.xy[None, :, 1] + t[k, 1:2])

    def nearest_ref(k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Under hypotheses `k`: per target stem, the distance to and index of the nearest
        reference stem of similar radius."""
        mx, my = moved(k)
        d = np.hypot(mx[:, :, None] - ref.xy[None, None, :, 0], my[:, :, None] - ref.xy[None, None, :, 1])
        d = np.where(radius_ok[None], d, np.inf)
        return d.min(axis=2), d.argmin(axis=2)

    # Hypotheses in chunks: a plot of 60 stems gives tens of thousands.
    chunk = max(1, 4_000_000 // max(len(tgt) * len(ref), 1))
    score = np.empty(len(yaw))
    for k0 in range(0, len(yaw), chunk):
        near, _ = nearest_ref(np.arange(k0, min(k0 + chunk, len(yaw))))
        hit = near < gate
        score[k0:k0 + len(near)] = hit.sum(axis=1) - 1e-3 * np.where(hit, near, 0.0).sum(axis=1)
    out: list[tuple[np.ndarray, np.ndarray]] = []
    taken: list[np.ndarray] = []  # where each kept hypothesis puts the target's stems
    for h in np.argsort(-score, kind="stable"):
        if len(out) == n or score[h] < target.min_matched - 1:
            break
        mx, my = moved(np.array([h]))
        at = np.column_stack([mx[0], my[0]])
        if any(np.linalg.norm(at - a, axis=1).max() < distinct_m for a in taken):
            continue
        taken.append(at)
        nearest, which = (a[0] for a in nearest_ref(np.array([h])))
        inl = np.flatnonzero(nearest < gate)
        if len(inl) < target.min_matched:
            break  # the hypotheses after it score no more matches
        pairs = np.column_stack([which[inl], inl])
        # Refit yaw + shift on the matched stems (as 3-D points at z = 0).
        src = np.column_stack([tgt.xy[pairs[:, 1]], np.zeros(len(pairs))])
        dst = np.column_stack([ref.xy[pairs[:, 0]], np.zeros(len(pairs))])
        out.append((kabsch_yaw(src, dst), pairs))
    return out


def _surrounded(xy: np.ndarray, stations: np.ndarray) -> tuple[float, float]:
    """(largest gap between the stations' azimuths seen from `xy`, degrees; farthest station, m)."""
    v = stations - xy
    az = np.sort(np.degrees(np.arctan2(v[:, 1], v[:, 0])))
    gaps = np.diff(np.r_[az, az[0] + 360.0]) if len(az) > 1 else np.array([360.0])
    return float(gaps.max()), float(np.linalg.norm(v, axis=1).max())


def _off_the_stems(at: np.ndarray, ref: Stems, ref_label: str, pick_radius_m: float) -> ConfigError:
    """`tree_at` names a point with no stem near it, though the reference holds stems: say where they are."""
    order = np.argsort(np.hypot(*(ref.xy - at).T))[:5]  # the nearest few: enough to pick from
    where = "; ".join(f"{x:.2f} {y:.2f} (r {r * 100:.0f} cm)" for x, y, r in ref.as_array()[order])
    more = f" and {len(ref) - len(order)} more" if len(ref) > len(order) else ""
    return ConfigError(f"--tree-at {at[0]:g} {at[1]:g}: no stem within {pick_radius_m:g} m of that point in {ref_label}; "
                       f"the stems found at breast height are at {where}{more} (x y in m); give one of those, "
                       "or leave --tree-at out to take the stem the stations surround")


def choose_targets(stems: list[Stems], *, target: TargetParams, ref_label: str = "the reference scan") -> list[TargetChoice]:
    """The target stem in every station's frame (station 0 = the reference, named `ref_label` in
    messages), see the module doc. Raises ConfigError when `tree_at` is off every stem found."""
    n = len(stems)
    keep_all = [TargetChoice(None, "fewer stems than a plot holds: all points kept")] * n
    if target.select == "off":
        return [TargetChoice(None, "target selection off: all points kept")] * n
    ref = stems[0]
    if target.tree_at is None and len(ref) < target.min_stems:
        return keep_all
    maps = [match_stem_maps(ref, s, target=target) for s in stems[1:]]
    # Station positions in the reference's frame (origins of the matched stations).
    origins = [np.zeros(2)] + [T[:2, 3] for T, _ in maps if T is not None]
    if target.tree_at is not None:
        at = np.asarray(target.tree_at, dtype=float)
        near = np.hypot(*(ref.xy - at).T) if len(ref) else np.zeros(0)
        if len(near) and near.min() <= target.pick_radius_m:
            k_ref, t_xy = int(near.argmin()), ref.xy[int(near.argmin())]
            how = f"the stem nearest to --tree-at {at[0]:g} {at[1]:g}"
        elif len(ref):
            raise _off_the_stems(at, ref, ref_label, target.pick_radius_m)
        else:  # no stem found at all (a trunk the search missed): crop at the user's point
            k_ref, t_xy = None, at
            how = f"--tree-at {at[0]:g} {at[1]:g} (no stem found in the reference: cut at that point)"
    else:
        # Stems seen from at least two stations (one station's stray "stem" is not a tree; a trunk
        # may hide from one station, or its partial arc give another radius there) ...
        seen = np.ones(len(ref), dtype=int)
        for T, pairs in maps:
            if T is not None:
                seen[pairs[:, 0]] += 1
        cand = np.flatnonzero(seen >= min(2, int(seen.max())))
        scores = np.array([_surrounded(ref.xy[k], np.array(origins)) for k in cand])
        # ... surrounded: no gap between the stations' directions wider than a half turn (two stations:
        # the stems between them). Of those, the one no station is far from (stations stand around
        # the target at similar distances; a neighbour is much farther from the opposite station).
        inside = np.flatnonzero(scores[:, 0] <= 180.0 + 1e-6)
        pool = inside if len(inside) else np.arange(len(cand))
        best = int(pool[np.argmin(scores[pool, 1])])
        k_ref, t_xy = int(cand[best]), ref.xy[int(cand[best])]
        how = (f"the stem the stations surround (largest gap between their directions {scores[best][0]:.0f} deg, "
               f"farthest station {scores[best][1]:.1f} m; {len(origins)} of {n} stations placed by their stem maps)")
    out = [TargetChoice((float(t_xy[0]), float(t_xy[1])), how)]
    for (T, pairs), s in zip(maps, stems[1:]):
        if T is None:
            out.append(TargetChoice(None, f"its stems ({len(s)}) did not match the reference's ({len(ref)}): all points kept"))
            continue
        hit = pairs[pairs[:, 0] == k_ref] if k_ref is not None else np.zeros((0, 2), dtype=np.int64)
        if len(hit):
            xy = s.xy[int(hit[0, 1])]
        else:  # the target stem is hidden from this station: where the stem map puts it
            p = np.linalg.solve(T, np.r_[t_xy, 0.0, 1.0])
            xy = p[:2]
        out.append(TargetChoice((float(xy[0]), float(xy[1])), f"{how}; matched {len(pairs)} stems", T, len(pairs)))
    return out
