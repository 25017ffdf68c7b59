"""A simulated terrestrial laser scanner: ray casting on a regular angular grid, and stations made
from an existing point cloud.

The instrument sits at the origin of its own frame. Ray (i, j) leaves at azimuth i*phi and
elevation j*varphi, measured in that frame (so a tilted instrument's grid is regular in its own
frame, as in a real one). A ray returns the nearest surface it meets over all primitives of the
scene: occlusion is real.

Speed comes from never testing a ray against a primitive it cannot hit: each primitive's angular
bounding box (from the station) selects the rays inside it, all (ray, primitive) candidate pairs
of a chunk are intersected at once with numpy, and the nearest hit per ray is kept by sorting.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..results import Progress
from .tree import Cylinders, Disks, GroundPlane, Scene, Spheres

#: Upper bound on (ray, primitive) pairs intersected at once: bounds memory (~40 floats per pair).
_CHUNK_PAIRS = 1_500_000


@dataclass(frozen=True, eq=False)
class RayScan:
    """What one station returned, in the instrument frame.

    points: N x 3 (metres, noise included); labels: N part labels (`simulate_tree.LABEL_NAMES`);
    primitive: N indices of the primitive hit (cylinders, then spheres, then disks; -1 = ground);
    grid_ij: N x 2 integer ray indices (azimuth i, elevation j; angles i*phi, j*varphi);
    n_rays: rays cast over the window; window_ij: (i0, i1, j0, j1) inclusive ray index ranges;
    return_index: N, 0 for the first return of a ray, 1 for a second one (`second_returns`).
    mixed: N bools, True for a mixed pixel (an edge return pushed back along its ray, `mixed_pixels`).
    """

    points: np.ndarray
    labels: np.ndarray
    primitive: np.ndarray
    grid_ij: np.ndarray
    n_rays: int
    window_ij: tuple[int, int, int, int]
    return_index: np.ndarray | None = None
    mixed: np.ndarray | None = None


#: Mixed pixels: a return is at an edge when a grid neighbour has no return or one this much farther.
MIXED_EDGE_JUMP_M = 0.3
#: A mixed pixel lies 2 cm to this far behind its edge (never beyond what lies behind it).
MIXED_MAX_M = 0.8
MIXED_MIN_M = 0.02


def _mixed_pixels(key: np.ndarray, t: np.ndarray, first: np.ndarray, n_rows: int, share: float,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Edge returns moved back along their rays, as a beam straddling an edge returns a range between
    the edge and what lies behind it. `key` (sorted), `t`: the returns kept (ray key col*n_rows+row,
    range); `first`: which are first returns. An edge return is a first return with a grid
    neighbour (4-connected) that has no return or one farther by `MIXED_EDGE_JUMP_M`; each is
    mixed with probability `share`, moved back by 2 cm up to `MIXED_MAX_M` (at most to the farther
    neighbour). Returns (new ranges, mixed mask)."""
    fk, ft = key[first], t[first]
    gap = np.zeros(len(key))
    for dk in (-1, 1, -n_rows, n_rows):  # rows within a column, then the neighbouring columns
        nk = key + dk
        i = np.minimum(np.searchsorted(fk, nk), max(len(fk) - 1, 0))
        found = (fk[i] == nk) if len(fk) else np.zeros(len(key), bool)
        if dk in (-1, 1):  # no wrap from the top of one column to the bottom of the next
            found &= (nk // n_rows) == (key // n_rows)
        behind = np.where(found, ft[i] - t, np.inf)
        gap = np.maximum(gap, behind)
    edge = first & (gap > MIXED_EDGE_JUMP_M)
    mixed = edge & (rng.random(len(key)) < share)
    cap = np.minimum(MIXED_MAX_M, gap[mixed])
    out = t.copy()
    out[mixed] += rng.uniform(0.0, 1.0, int(mixed.sum())) * (cap - MIXED_MIN_M) + MIXED_MIN_M
    return out, mixed


def _angles(p: np.ndarray, alpha_c: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Azimuth (unwrapped to within 180 deg of `alpha_c`), elevation (radians), horizontal and 3-D
    distance of points `p` (... x 3)."""
    rho = np.hypot(p[..., 0], p[..., 1])
    alpha = np.arctan2(p[..., 1], p[..., 0])
    alpha = alpha_c + (alpha - alpha_c + np.pi) % (2 * np.pi) - np.pi
    beta = np.arctan2(p[..., 2], rho)
    return alpha, beta, rho, np.linalg.norm(p, axis=-1)


def _segment_distance(p0: np.ndarray, p1: np.ndarray, dims: int) -> np.ndarray:
    """Distance from the origin to the segments p0-p1, in the first `dims` coordinates."""
    a, b = p0[:, :dims], p1[:, :dims]
    ab = b - a
    t = np.clip(-np.sum(a * ab, axis=1) / np.maximum(np.sum(ab * ab, axis=1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(a + t[:, None] * ab, axis=1)


def _boxes(scene: Scene, alpha_c: float, wrap: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Conservative angular boxes (alpha_lo, alpha_hi, beta_lo, beta_hi, radians) of every primitive:
    cylinders first, then spheres, then disks.

    A segment's azimuth varies monotonically along it, so the hull of its end points' angles plus the
    angle its radius subtends at its closest approach bounds it. Its elevation can peak between the
    ends; the mid point's elevation is included, which for segments under half a metre seen from
    metres away leaves an error far below a ray step (a step of margin is added by the caller).
    """
    c, s, d = scene.cylinders, scene.spheres, scene.disks
    a0, b0, _, _ = _angles(c.p0, alpha_c)
    a1, b1, _, _ = _angles(c.p1, alpha_c)
    _, bm, _, _ = _angles(0.5 * (c.p0 + c.p1), alpha_c)
    r = np.maximum(c.r0, c.r1)
    rho_min = _segment_distance(c.p0, c.p1, 2)
    dist_min = _segment_distance(c.p0, c.p1, 3)
    da = np.arcsin(np.clip(r / np.maximum(rho_min, 1e-9), 0.0, 1.0))
    db = np.arcsin(np.clip(r / np.maximum(dist_min, 1e-9), 0.0, 1.0))
    # A segment whose azimuths straddle the cut behind the scanner, or one that passes over the
    # instrument, spans all azimuths: let the window clip it. In a full panorama (`wrap`) the
    # straddling segment keeps a narrow box that runs past the cut (ray columns wrap around).
    if wrap:
        a1 = a0 + (a1 - a0 + np.pi) % (2 * np.pi) - np.pi
    full = (np.abs(a1 - a0) > np.pi) | (r >= rho_min)
    ca_lo = np.where(full, -np.inf, np.minimum(a0, a1) - da)
    ca_hi = np.where(full, np.inf, np.maximum(a0, a1) + da)
    cb_lo = np.minimum(np.minimum(b0, b1), bm) - db
    cb_hi = np.maximum(np.maximum(b0, b1), bm) + db

    cen = np.vstack([s.centre, d.centre])
    rad = np.concatenate([s.radius, d.radius])  # a disk lies inside the sphere of its radius
    a, b, rho, dist = _angles(cen, alpha_c)
    da = np.arcsin(np.clip(rad / np.maximum(rho, 1e-9), 0.0, 1.0))
    db = np.arcsin(np.clip(rad / np.maximum(dist, 1e-9), 0.0, 1.0))
    full = rad >= rho
    sa_lo = np.where(full, -np.inf, a - da)
    sa_hi = np.where(full, np.inf, a + da)
    return (np.concatenate([ca_lo, sa_lo]), np.concatenate([ca_hi, sa_hi]),
            np.concatenate([cb_lo, b - db]), np.concatenate([cb_hi, b + db]))


def _intersect_cylinders(scene: Scene, prim: np.ndarray, dx: np.ndarray, dy: np.ndarray,
                         dz: np.ndarray, pre: dict[str, np.ndarray]) -> np.ndarray:
    """Ray parameter t of the entry into the lateral surface of cone frusta `prim` (inf: no hit).

    With the ray x = t d (origin at the scanner), axis point p0, unit axis a, s = (x - p0).a and
    radius r(s) = r0 + k s, the surface |x - p0|^2 - s^2 = r(s)^2 is quadratic in t. Only the near
    root on the frustum's length counts: a ray entering through an open end meets the neighbouring
    segment or the joint sphere first.
    """
    ax, ay, az = pre["ax"][prim], pre["ay"][prim], pre["az"][prim]
    da = dx * ax + dy * ay + dz * az
    p0 = scene.cylinders.p0
    dp = dx * p0[prim, 0] + dy * p0[prim, 1] + dz * p0[prim, 2]
    pa, m, k = pre["pa"][prim], pre["m"][prim], pre["k"][prim]
    n = k * da
    A = 1.0 - da * da - n * n
    half_b = -(dp - da * pa + m * n)
    C = pre["C"][prim]
    disc = half_b * half_b - A * C
    ok = (disc >= 0.0) & (A > 1e-9)
    t = np.where(ok, (-half_b - np.sqrt(np.where(ok, disc, 0.0))) / np.where(ok, A, 1.0), np.inf)
    t = np.where(ok, t, 0.0)  # keeps the products below finite
    s = t * da - pa
    ok &= (t > 0.0) & (s >= 0.0) & (s <= pre["L"][prim]) & (m + n * t >= 0.0)
    return np.where(ok, t, np.inf)


def _intersect_spheres(centre: np.ndarray, radius: np.ndarray, dx: np.ndarray, dy: np.ndarray,
                       dz: np.ndarray) -> np.ndarray:
    dc = dx * centre[:, 0] + dy * centre[:, 1] + dz * centre[:, 2]
    disc = dc * dc - (np.sum(centre * centre, axis=1) - radius * radius)
    ok = disc >= 0.0
    t = dc - np.sqrt(np.where(ok, disc, 0.0))
    return np.where(ok & (t > 0.0), t, np.inf)


def _intersect_disks(centre: np.ndarray, normal: np.ndarray, radius: np.ndarray, dx: np.ndarray,
                     dy: np.ndarray, dz: np.ndarray) -> np.ndarray:
    dn = dx * normal[:, 0] + dy * normal[:, 1] + dz * normal[:, 2]
    cn = np.sum(centre * normal, axis=1)
    ok = np.abs(dn) > 1e-9
    t = cn / np.where(ok, dn, 1.0)
    ex = t * dx - centre[:, 0]
    ey = t * dy - centre[:, 1]
    ez = t * dz - centre[:, 2]
    ok &= (t > 0.0) & (ex * ex + ey * ey + ez * ez <= radius * radius)
    return np.where(ok, t, np.inf)


def _intersect_ground(g: GroundPlane, dx: np.ndarray, dy: np.ndarray, dz: np.ndarray) -> np.ndarray:
    dn = dx * g.normal[0] + dy * g.normal[1] + dz * g.normal[2]
    ok = dn < -1e-9  # only rays going down towards the plane (the scanner stands above it)
    t = g.offset / np.where(ok, dn, -1.0)
    ex = t * dx - g.centre[0]
    ey = t * dy - g.centre[1]
    ez = t * dz - g.centre[2]
    ok &= (t > 0.0) & (ex * ex + ey * ey + ez * ez <= g.radius_m ** 2)
    return np.where(ok, t, np.inf)


# Twelve parameters: the instrument's settings (step, noise, dropout, window, returns, mixed
# pixels, ...), each with the default of a typical TLS; a simulation names only what it varies.
def scan_scene(
    scene: Scene,
    angular_step_deg: tuple[float, float],
    rng: np.random.Generator,
    range_sigma_m: float = 0.003,
    dropout: float = 0.02,
    window_deg: tuple[float, float, float, float] | None = None,
    ground_near_m: float | None = None,
    progress: Progress | None = None,
    second_returns: float = 0.0,
    second_return_labels: tuple[int, ...] = (3, 4, 5),
    second_return_gap_m: float = 0.8,
    mixed_pixels: float = 0.0,
) -> RayScan:
    """Ray-cast `scene`, given in the instrument frame (scanner at the origin).

    Parameters
    ----------
    scene : the primitives, already in the instrument frame.
    angular_step_deg : (phi, varphi), the horizontal and vertical steps of the ray grid.
    rng : source of the range noise and of the dropouts.
    range_sigma_m : standard deviation of the Gaussian range noise, along the ray.
    dropout : fraction of returns lost at random (a real scanner misses some pulses).
    window_deg : (alpha_lo, alpha_hi, beta_lo, beta_hi) to scan; default the angular hull of the
        tree primitives (ground excluded).
    ground_near_m : with a ground plane and no `window_deg`, the window's lower edge is lowered to
        see the ground from this horizontal distance on (towards the ground plane's centre, the
        tree; default 2 m before it).
    progress : called with (fraction, text) as chunks complete.
    second_returns : probability that a ray whose first hit is on a part in `second_return_labels`
        (thin branches and leaves, which a beam's footprint only partly covers) also returns the
        next surface at least `second_return_gap_m` behind it, as a real multi-return scanner does.
    mixed_pixels : share of the edge returns (a grid neighbour empty or 0.3 m farther) that are
        mixed pixels: the beam straddles the edge and the range lands 2-80 cm behind it, between the
        edge and what lies behind (`RayScan.mixed` marks them).

    A window spanning 360 deg of azimuth is a full panorama: ray columns wrap around, so objects
    behind the scanner (across the cut) are scanned whole.
    """
    phi, vphi = (np.radians(float(v)) for v in angular_step_deg)
    c = scene.cylinders
    lo_all, hi_all = scene.points_bounds()
    centre = 0.5 * (lo_all + hi_all)
    alpha_c = float(np.arctan2(centre[1], centre[0]))
    wrap = window_deg is not None and window_deg[1] - window_deg[0] >= 360.0 - float(angular_step_deg[0])
    a_lo, a_hi, b_lo, b_hi = _boxes(scene, alpha_c, wrap)

    if window_deg is not None and wrap:
        wb0, wb1 = (np.radians(v) for v in window_deg[2:])
        wa0, wa1 = alpha_c - np.pi, alpha_c + np.pi - phi
    elif window_deg is not None:
        wa0, wa1, wb0, wb1 = (np.radians(v) for v in window_deg)
        wa0 = alpha_c + (wa0 - alpha_c + np.pi) % (2 * np.pi) - np.pi
        wa1 = wa0 + (wa1 - wa0) % (2 * np.pi)
    else:
        finite = np.isfinite(a_lo) & np.isfinite(a_hi)
        wa0, wa1 = float(np.min(a_lo[finite])), float(np.max(a_hi[finite]))
        wb0, wb1 = float(np.min(b_lo)), float(np.max(b_hi))
        if wa1 - wa0 > 2 * np.pi:
            wa0, wa1 = alpha_c - np.pi, alpha_c + np.pi - phi
        if scene.ground is not None:
            g = scene.ground
            # The ground point below the place `ground_near_m` from the scanner towards the tree.
            base = g.centre
            dist = np.hypot(base[0], base[1])
            near = max(dist - 2.0, 0.0) if ground_near_m is None else min(float(ground_near_m), dist)
            q = base * (near / max(dist, 1e-9))
            q = q - (q @ g.normal - g.offset) * g.normal
            wb0 = min(wb0, float(np.arctan2(q[2], np.hypot(q[0], q[1]))))
    wb0, wb1 = max(wb0, np.radians(-89.0)), min(wb1, np.radians(89.0))
    i0, i1 = int(np.ceil(wa0 / phi)), int(np.floor(wa1 / phi))
    if wrap:
        i1 = i0 + int(round(2 * np.pi / phi)) - 1
    j0, j1 = int(np.ceil(wb0 / vphi)), int(np.floor(wb1 / vphi))
    n_cols, n_rows = i1 - i0 + 1, j1 - j0 + 1
    n_rays = n_cols * n_rows
    alpha = (i0 + np.arange(n_cols)) * phi
    beta = (j0 + np.arange(n_rows)) * vphi
    ca, sa, cb, sb = np.cos(alpha), np.sin(alpha), np.cos(beta), np.sin(beta)

    # Ray index ranges of every primitive, clipped to the window; one step of margin.
    pi0 = np.ceil(np.where(np.isfinite(a_lo), a_lo / phi - 1, i0)).astype(np.int64)
    pi1 = np.floor(np.where(np.isfinite(a_hi), a_hi / phi + 1, i1)).astype(np.int64)
    if wrap:  # columns wrap around: a box may run past either end, but never more than once round
        pi1 = np.minimum(pi1, pi0 + n_cols - 1)
    else:
        pi0, pi1 = np.maximum(pi0, i0), np.minimum(pi1, i1)
    pj0 = np.maximum(np.ceil(b_lo / vphi - 1), j0).astype(np.int64)
    pj1 = np.minimum(np.floor(b_hi / vphi + 1), j1).astype(np.int64)
    w = np.maximum(pi1 - pi0 + 1, 0)
    h = np.maximum(pj1 - pj0 + 1, 0)
    counts = w * h

    # Per-cylinder constants of the intersection quadratic.
    axis = c.p1 - c.p0
    L = np.linalg.norm(axis, axis=1)
    a = axis / np.maximum(L, 1e-12)[:, None]
    k = (c.r1 - c.r0) / np.maximum(L, 1e-12)
    pa = np.sum(c.p0 * a, axis=1)
    m = c.r0 - k * pa
    pre = {"ax": a[:, 0], "ay": a[:, 1], "az": a[:, 2], "L": L, "k": k, "pa": pa, "m": m,
           "C": np.sum(c.p0 * c.p0, axis=1) - pa * pa - m * m}
    n_cyl, n_sph = len(c), len(scene.spheres)
    labels_all = np.concatenate([c.label, scene.spheres.label, scene.disks.label])

    hit_ray: list[np.ndarray] = []
    hit_t: list[np.ndarray] = []
    hit_lab: list[np.ndarray] = []
    hit_prim: list[np.ndarray] = []

    if scene.ground is not None:
        jj, ii = np.divmod(np.arange(n_rays), n_cols)
        t = _intersect_ground(scene.ground, cb[jj] * ca[ii], cb[jj] * sa[ii], sb[jj])
        good = np.isfinite(t)
        hit_ray.append(np.flatnonzero(good))
        hit_t.append(t[good])
        hit_lab.append(np.zeros(int(good.sum()), dtype=np.int8))
        hit_prim.append(np.full(int(good.sum()), -1, dtype=np.int64))

    # Chunks of consecutive primitives holding at most _CHUNK_PAIRS candidate pairs each.
    cum = np.cumsum(counts)
    total = int(cum[-1]) if cum.size else 0
    bounds = np.searchsorted(cum, np.arange(_CHUNK_PAIRS, total, _CHUNK_PAIRS), side="left")
    edges = np.unique(np.concatenate([[0], bounds + 1, [len(counts)]]))
    for e0, e1 in zip(edges[:-1], edges[1:]):
        cnt = counts[e0:e1]
        n_pairs = int(cnt.sum())
        if n_pairs == 0:
            continue
        prim = np.repeat(np.arange(e0, e1), cnt)
        start = np.repeat(np.cumsum(cnt) - cnt, cnt)
        off = np.arange(n_pairs) - start
        q, r = np.divmod(off, h[prim])
        col = pi0[prim] - i0 + q
        if wrap:
            col %= n_cols
        row = pj0[prim] - j0 + r
        dx, dy, dz = cb[row] * ca[col], cb[row] * sa[col], sb[row]
        t = np.full(n_pairs, np.inf)
        sel = prim < n_cyl
        if sel.any():
            t[sel] = _intersect_cylinders(scene, prim[sel], dx[sel], dy[sel], dz[sel], pre)
        sel = (prim >= n_cyl) & (prim < n_cyl + n_sph)
        if sel.any():
            p = prim[sel] - n_cyl
            t[sel] = _intersect_spheres(scene.spheres.centre[p], scene.spheres.radius[p], dx[sel], dy[sel], dz[sel])
        sel = prim >= n_cyl + n_sph
        if sel.any():
            p = prim[sel] - n_cyl - n_sph
            d = scene.disks
            t[sel] = _intersect_disks(d.centre[p], d.normal[p], d.radius[p], dx[sel], dy[sel], dz[sel])
        good = np.isfinite(t)
        hit_ray.append((row * n_cols + col)[good])
        hit_t.append(t[good])
        hit_lab.append(labels_all[prim[good]])
        hit_prim.append(prim[good])
        if progress is not None:
            progress(float(e1) / len(counts), "casting rays")

    ray = np.concatenate(hit_ray) if hit_ray else np.zeros(0, dtype=np.int64)
    tt = np.concatenate(hit_t) if hit_t else np.zeros(0)
    lab = np.concatenate(hit_lab) if hit_lab else np.zeros(0, dtype=np.int8)
    pid = np.concatenate(hit_prim) if hit_prim else np.zeros(0, dtype=np.int64)
    # Nearest hit per ray; rays ordered column by column (azimuth-major), as a TLS sweeps.
    row, col = np.divmod(ray, n_cols)
    key = col.astype(np.int64) * n_rows + row
    order = np.lexsort((tt, key))
    key, tt, lab, pid = key[order], tt[order], lab[order], pid[order]
    first = np.ones(key.size, dtype=bool)
    first[1:] = key[1:] != key[:-1]
    ret = np.zeros(key.size, dtype=np.int8)
    if second_returns > 0:
        # The next surface behind a partly covered first hit: the first entry of each ray that lies
        # at least the gap behind that ray's first hit.
        group = np.cumsum(first) - 1
        t_first = tt[first][group]
        partial = np.isin(lab[first], second_return_labels)[group]
        behind = (tt > t_first + second_return_gap_m) & partial
        b_idx = np.flatnonzero(behind)
        second = np.zeros(key.size, dtype=bool)
        if b_idx.size:
            b_first = np.r_[True, group[b_idx][1:] != group[b_idx][:-1]]
            chosen = b_idx[b_first]
            second[chosen[rng.random(chosen.size) < second_returns]] = True
        ret[second] = 1
        first |= second
    key, tt, lab, pid, ret = key[first], tt[first], lab[first], pid[first], ret[first]
    mixed = np.zeros(key.size, dtype=bool)
    if mixed_pixels > 0:
        tt, mixed = _mixed_pixels(key, tt, ret == 0, n_rows, mixed_pixels, rng)

    keep = rng.random(key.size) >= dropout
    key, tt, lab, pid, ret, mixed = key[keep], tt[keep], lab[keep], pid[keep], ret[keep], mixed[keep]
    rng_m = tt + rng.normal(0.0, range_sigma_m, tt.size)
    col, row = np.divmod(key, n_rows)
    pts = np.stack([cb[row] * ca[col], cb[row] * sa[col], sb[row]], axis=1) * rng_m[:, None]
    grid = np.stack([col + i0, row + j0], axis=1)
    return RayScan(pts, lab.astype(np.int8), pid, grid, n_rays, (i0, i1, j0, j1), ret, mixed)


def visible_points(
    points: np.ndarray,
    angular_step_deg: tuple[float, float],
    rng: np.random.Generator,
    range_sigma_m: float = 0.003,
    dropout: float = 0.02,
) -> tuple[np.ndarray, np.ndarray]:
    """A station from a point cloud given in the instrument frame: the nearest point of each
    (azimuth, elevation) cell of the angular step, with range noise along its ray and dropouts.

    Returns (points N x 3 with noise, indices of the chosen input points), ordered cell by cell,
    column by column.
    """
    phi, vphi = (np.radians(float(v)) for v in angular_step_deg)
    r = np.linalg.norm(points, axis=1)
    alpha = np.arctan2(points[:, 1], points[:, 0])
    # Unwrap around the cloud's mean direction so its cells never straddle the cut at +-180 deg.
    alpha_c = float(np.arctan2(np.sum(np.sin(alpha)), np.sum(np.cos(alpha))))
    alpha = alpha_c + (alpha - alpha_c + np.pi) % (2 * np.pi) - np.pi
    beta = np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1]))
    ci = np.round(alpha / phi).astype(np.int64)
    cj = np.round(beta / vphi).astype(np.int64)
    key = (ci - ci.min()) * (cj.max() - cj.min() + 1) + (cj - cj.min())
    order = np.lexsort((r, key))
    first = np.ones(order.size, dtype=bool)
    first[1:] = key[order][1:] != key[order][:-1]
    idx = order[first]
    idx = idx[rng.random(idx.size) >= dropout]
    scale = (r[idx] + rng.normal(0.0, range_sigma_m, idx.size)) / np.maximum(r[idx], 1e-12)
    return points[idx] * scale[:, None], idx


def visible_points_splat(
    points: np.ndarray,
    angular_step_deg: tuple[float, float],
    radius_m: float,
    rng: np.random.Generator,
    range_sigma_m: float = 0.003,
    dropout: float = 0.02,
) -> tuple[np.ndarray, np.ndarray]:
    """Like `visible_points`, but each point occludes as a small sphere of `radius_m`.

    A cloud sparser than the scanner's angular cells lets plain binning see through a trunk to its
    back; as spheres of about the point spacing the points form closed surfaces, so the far side
    is hidden as from a real station. Each ray returns the point whose sphere it meets first; a
    point met by several rays is returned once (its own position, noise along its own ray).
    """
    e3, e1 = np.zeros((0, 3)), np.zeros(0)
    scene = Scene(
        Cylinders(e3, e3, e1, e1, np.zeros(0, dtype=np.int8)),
        Spheres(points, np.full(len(points), float(radius_m)), np.full(len(points), -1, dtype=np.int8)),
        Disks(e3, e3, e1, np.zeros(0, dtype=np.int8)),
    )
    rs = scan_scene(scene, angular_step_deg, rng, range_sigma_m=0.0, dropout=0.0)
    _, first = np.unique(rs.primitive, return_index=True)
    idx = rs.primitive[np.sort(first)]  # in scan order: by the first ray that met each point
    idx = idx[rng.random(idx.size) >= dropout]
    r = np.linalg.norm(points[idx], axis=1)
    scale = (r + rng.normal(0.0, range_sigma_m, idx.size)) / np.maximum(r, 1e-12)
    return points[idx] * scale[:, None], idx
