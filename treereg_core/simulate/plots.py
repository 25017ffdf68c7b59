"""Simulated plots: full panoramic stations of a target tree among neighbours, shrubs and ground.

Real stations are not cut to one tree: a scanner on a tripod sees the whole plot around it, 360
degrees, from the ground at its feet to the crowns. `PlotSpec(seed).build()` grows a target tree
at the world origin, 6-10 neighbours 3-8 m from it (some nearer to a station than the target),
shrubs, a sloping ground, and ray-casts full panoramas (azimuth 360 deg, elevation -40..+60 deg
like a RIEGL VZ-400i) from stations around the target. `real_like=True` adds what the real station
in shared/data shows: coordinates rounded to the millimetre and second returns from thin branches
and leaves. Density falls with range by itself (an angular grid).

The result is a `cases.SimulatedCase`, so everything that measures cases measures plots; its
`trees[0]` is the target, and `tree_ids` says which tree (or shrub, or -1 for ground) each point
of each scan hit.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import Any, Callable, Protocol, Sequence

import numpy as np

from ..errors import ConfigError
from ..geometry.rigid import invert, make_transform, rotation_z
from ..results import Metric, Progress
from ..scan import Scan
from .cases import SimulatedCase, Station, _station_azimuths
from .scanner import scan_scene
from .tree import GroundPlane, Scene, TreeInfo, TreeShape, make_ground, make_tree, merge_scenes, tilt_rotation

#: Trunks start this far below the ground plane, so a slope leaves no gap at their base.
_SINK_M = 0.3
#: No trunk stands nearer than this to a station, or to another trunk (m).
_STATION_CLEARANCE_M = 1.5
_TRUNK_CLEARANCE_M = 2.0


@dataclass(frozen=True)
class PlotSpec:
    """Everything that defines a simulated plot; ranges (lo, hi) are drawn from the seed.

    seed, n_stations, angular_step_deg : as for `cases.CaseSpec`.
    target_height_m : the target tree's height; its DBH follows from it (about 2.5 cm per metre).
    n_neighbours, neighbour_distance_m, neighbour_height_ratio : how many other trees stand how
        far from the target, and how tall relative to it.
    n_shrubs, shrub_height_m, shrub_distance_m : small leafy bushes scattered over the plot.
    station_distance_m, separation_deg, instrument_height_m : stations around the target.
    elevation_deg : the instrument's vertical field of view (a full 360 deg in azimuth).
    plot_radius_m, ground_slope_deg : the ground reaches this far from the target, sloping up to this.
    leaves : leaves on the trees (shrubs always carry them).
    real_like : millimetre rounding of the coordinates and second returns (probability
        `second_returns`) from thin branches and leaves, like the real RIEGL station.
    tilt_deg, range_sigma_m, dropout : instrument tilt, range noise, lost returns.
    """

    seed: int = 0
    n_stations: int = 3
    angular_step_deg: tuple[float, float] = (0.1, 0.1)
    target_height_m: tuple[float, float] = (12.0, 18.0)
    n_neighbours: tuple[int, int] = (6, 10)
    neighbour_distance_m: tuple[float, float] = (3.0, 8.0)
    neighbour_height_ratio: tuple[float, float] = (0.6, 1.1)
    n_shrubs: tuple[int, int] = (8, 16)
    shrub_height_m: tuple[float, float] = (0.8, 2.5)
    shrub_distance_m: tuple[float, float] = (2.0, 15.0)
    station_distance_m: tuple[float, float] = (5.0, 9.0)
    separation_deg: tuple[float, float] = (90.0, 150.0)
    instrument_height_m: tuple[float, float] = (1.3, 1.7)
    elevation_deg: tuple[float, float] = (-40.0, 60.0)
    plot_radius_m: float = 25.0
    ground_slope_deg: float = 5.0
    leaves: bool = False
    real_like: bool = False
    second_returns: float = 0.3
    tilt_deg: float = 0.0
    range_sigma_m: float = 0.003
    dropout: float = 0.02

    def __post_init__(self) -> None:
        for name in ("target_height_m", "n_neighbours", "neighbour_distance_m", "neighbour_height_ratio",
                     "n_shrubs", "shrub_height_m", "shrub_distance_m", "station_distance_m", "separation_deg",
                     "instrument_height_m", "elevation_deg"):
            v = tuple(getattr(self, name))
            if len(v) != 2 or not v[0] <= v[1]:
                raise ConfigError(f"{name}: needs (low, high) with low <= high, got {getattr(self, name)!r}")
            object.__setattr__(self, name, v)
        step = self.angular_step_deg
        step = (step, step) if np.isscalar(step) else tuple(step)
        object.__setattr__(self, "angular_step_deg", (float(step[0]), float(step[1])))
        checks = [
            (self.n_stations >= 1, "n_stations: at least one station is needed"),
            (all(0.005 <= s <= 2 for s in self.angular_step_deg), f"angular_step_deg: {self.angular_step_deg} is outside 0.005-2 deg"),
            (self.n_neighbours[0] >= 0, "n_neighbours: must be >= 0"),
            (self.neighbour_distance_m[0] >= _TRUNK_CLEARANCE_M, f"neighbour_distance_m: neighbours stand at least {_TRUNK_CLEARANCE_M} m from the target"),
            (self.station_distance_m[0] > _STATION_CLEARANCE_M, f"station_distance_m: stations stand more than {_STATION_CLEARANCE_M} m from the target"),
            (-90 < self.elevation_deg[0] < self.elevation_deg[1] < 90, "elevation_deg: needs -90 < low < high < 90"),
            (0 <= self.second_returns <= 1, "second_returns: a probability in [0, 1]"),
            (0 <= self.tilt_deg <= 10, f"tilt_deg: {self.tilt_deg} is outside 0-10 deg"),
            (0 <= self.dropout < 1, f"dropout: {self.dropout} is outside [0, 1)"),
        ]
        for ok, msg in checks:
            if not ok:
                raise ConfigError(msg)

    def build(self, progress: Progress | None = None) -> SimulatedCase:
        """Simulate this plot (the same spec gives identical points)."""
        return _build(self, progress)

    def to_dict(self) -> dict[str, Any]:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @property
    def label(self) -> str:
        flags = [n for n in ("leaves", "real_like") if getattr(self, n)] + ([f"tilt {self.tilt_deg:g} deg"] if self.tilt_deg else [])
        step = "x".join(f"{v:g}" for v in sorted(set(self.angular_step_deg)))
        return f"plot seed {self.seed}: " + ", ".join([*flags, f"{step} deg"])

    @property
    def awkward(self) -> bool:
        return True


def place(n: int, draw: Callable[[np.random.Generator], np.ndarray], avoid: list[np.ndarray],
          clearance: list[float], rng: np.random.Generator) -> list[np.ndarray]:
    """Up to `n` positions drawn by `draw(rng)`, each at least the matching clearance from every
    point of `avoid` and `_TRUNK_CLEARANCE_M` from each other (by rejection; fewer if the plot is
    full). Plots draw around the target, surveys over a rectangle."""
    out: list[np.ndarray] = []
    pts = np.array(avoid, dtype=float).reshape(-1, 2)
    gaps = np.array(clearance, dtype=float)
    for _ in range(n):
        for _ in range(200):
            xy = draw(rng)
            if np.all(np.hypot(*(xy - pts).T) >= gaps):
                out.append(xy)
                pts = np.vstack([pts, xy])
                gaps = np.append(gaps, _TRUNK_CLEARANCE_M)
                break
    return out


def _around_target(distance: tuple[float, float]) -> Callable[[np.random.Generator], np.ndarray]:
    """A position `distance` from the origin (the target), at any azimuth."""
    def draw(rng: np.random.Generator) -> np.ndarray:
        a, d = rng.uniform(0, 2 * np.pi), rng.uniform(*distance)
        return d * np.array([np.cos(a), np.sin(a)])
    return draw


def grow_neighbour(height_m: float, xy: np.ndarray, ground: GroundPlane, leaves: bool,
                   rng: np.random.Generator) -> TreeInfo:
    """A tree of `height_m` standing on the ground at `xy`: DBH about 2.5 cm per metre, 2-3
    branching orders, a lean of up to 5 deg."""
    d = float(np.clip(0.025 * height_m * rng.uniform(0.7, 1.3), 0.1, 0.8))
    shape = TreeShape(height_m=round(height_m, 3), dbh_m=round(d, 4), orders=int(rng.integers(2, 4)), leaves=leaves,
                      lean_deg=float(rng.uniform(0, 5)))
    return make_tree(shape, rng, base=np.array([xy[0], xy[1], float(ground.height_at(xy))]), sink_m=_SINK_M)


def grow_shrub(height_m: tuple[float, float], xy: np.ndarray, ground: GroundPlane, rng: np.random.Generator) -> TreeInfo:
    """A small leafy bush on the ground at `xy`."""
    h = float(rng.uniform(*height_m))
    shape = TreeShape(height_m=round(h, 3), dbh_m=0.03, orders=2, leaves=True, leaves_per_m=40.0)
    return make_tree(shape, rng, base=np.array([xy[0], xy[1], float(ground.height_at(xy))]), sink_m=0.1)


def primitive_owners(trees: Sequence[TreeInfo]) -> np.ndarray:
    """Which tree each primitive of `merge_scenes` of these trees belongs to (cylinders, then
    spheres, then disks, as the scanner counts them)."""
    return np.concatenate([np.concatenate([np.full(len(getattr(t.scene, part)), k, dtype=np.int32)
                                           for k, t in enumerate(trees)])
                           for part in ("cylinders", "spheres", "disks")])


class Instrument(Protocol):
    """What a station's scan needs of a plot's or a survey's spec."""

    @property
    def angular_step_deg(self) -> tuple[float, float]: ...
    @property
    def elevation_deg(self) -> tuple[float, float]: ...
    @property
    def range_sigma_m(self) -> float: ...
    @property
    def dropout(self) -> float: ...
    @property
    def real_like(self) -> bool: ...
    @property
    def second_returns(self) -> float: ...


@dataclass(frozen=True, eq=False)
class StationScan:
    """One station's full panorama: the scan, each point's part label, tree (-1 ground) and return."""

    scan: Scan
    labels: np.ndarray
    tree_ids: np.ndarray
    return_index: np.ndarray
    n_rays: int


def scan_station(scene: Scene, owner: np.ndarray, station: Station, name: str, spec: Instrument,
                 rng: np.random.Generator, progress: Progress | None = None) -> StationScan:
    """Ray-cast a full panorama (360 deg by the spec's elevation window) of `scene` (world frame)
    from `station`; `owner` is `primitive_owners` of the scene's trees."""
    window = (-180.0, 180.0, spec.elevation_deg[0], spec.elevation_deg[1])
    rs = scan_scene(scene.transformed(invert(station.T_world_scan)), spec.angular_step_deg, rng,
                    spec.range_sigma_m, spec.dropout, window_deg=window, progress=progress,
                    second_returns=spec.second_returns if spec.real_like else 0.0)
    pts = np.round(rs.points, 3) if spec.real_like else rs.points
    ids = np.where(rs.primitive >= 0, owner[np.maximum(rs.primitive, 0)], -1).astype(np.int32)
    ret = rs.return_index if rs.return_index is not None else np.zeros(len(pts), dtype=np.int8)
    return StationScan(Scan.from_points(pts, name=name, angular_step_deg=spec.angular_step_deg), rs.labels, ids,
                       ret, rs.n_rays)


def _build(spec: PlotSpec, progress: Progress | None) -> SimulatedCase:
    t0 = time.perf_counter()
    say = progress or (lambda f, t: None)
    ss = np.random.SeedSequence([spec.seed, 11])
    s_tree, s_stations, s_ground, s_others, s_noise = ss.spawn(5)
    rng_tree, rng_st, rng_ground, rng_oth = (np.random.default_rng(s) for s in (s_tree, s_stations, s_ground, s_others))
    rng_noise = [np.random.default_rng(s) for s in s_noise.spawn(spec.n_stations)]
    say(0.0, "growing the plot")

    H = float(rng_tree.uniform(*spec.target_height_m))
    dbh = float(np.clip(0.025 * H * rng_tree.uniform(0.8, 1.25), 0.15, 0.8))
    ground = make_ground(rng_ground.uniform(0, spec.ground_slope_deg), rng_ground.uniform(0, 360), spec.plot_radius_m)
    target = make_tree(TreeShape(height_m=round(H, 3), dbh_m=round(dbh, 4), leaves=spec.leaves), rng_tree, sink_m=_SINK_M)

    # Stations first (around the target), then the neighbours keep clear of them.
    az = _station_azimuths(spec.n_stations, spec.separation_deg, rng_st)
    stations = []
    for a in az:
        d = rng_st.uniform(*spec.station_distance_m)
        xy = d * np.array([np.cos(np.radians(a)), np.sin(np.radians(a))])
        z = float(ground.height_at(xy)) + rng_st.uniform(*spec.instrument_height_m)
        heading = float(rng_st.uniform(0, 360))
        tilt = float(spec.tilt_deg * rng_st.uniform(0.5, 1.0))
        tilt_axis = float(rng_st.uniform(0, 360))
        R = rotation_z(heading) @ tilt_rotation(tilt, tilt_axis)
        pos = np.array([xy[0], xy[1], z])
        stations.append(Station(pos, heading, tilt, tilt_axis, make_transform(R, pos)))
    st_xy = [s.position_m[:2] for s in stations]

    n_nb = int(rng_oth.integers(spec.n_neighbours[0], spec.n_neighbours[1] + 1))
    nb_xy = place(n_nb, _around_target(spec.neighbour_distance_m), [np.zeros(2)] + st_xy,
                  [_TRUNK_CLEARANCE_M] + [_STATION_CLEARANCE_M] * len(st_xy), rng_oth)
    trees: list[TreeInfo] = [target]
    for xy in nb_xy:
        trees.append(grow_neighbour(H * rng_oth.uniform(*spec.neighbour_height_ratio), xy, ground, spec.leaves, rng_oth))
    n_sh = int(rng_oth.integers(spec.n_shrubs[0], spec.n_shrubs[1] + 1))
    sh_xy = place(n_sh, _around_target(spec.shrub_distance_m), [np.zeros(2)] + st_xy + nb_xy,
                  [1.0] + [1.0] * len(st_xy) + [1.0] * len(nb_xy), rng_oth)
    trees += [grow_shrub(spec.shrub_height_m, xy, ground, rng_oth) for xy in sh_xy]
    scene = merge_scenes([t.scene for t in trees], ground)
    owner = primitive_owners(trees)

    scans, labels, ids, rets = [], [], [], []
    n_rays = 0
    for k, st in enumerate(stations):
        name = f"scan{k + 1}.ply"

        def sub(f: float, text: str, k: int = k) -> None:
            say((k + f) / len(stations), f"{name}: {text}")

        one = scan_station(scene, owner, st, name, spec, rng_noise[k], sub)
        n_rays += one.n_rays
        scans.append(one.scan)
        labels.append(one.labels)
        ids.append(one.tree_ids)
        rets.append(one.return_index)
    T_world_ref = stations[0].T_world_scan
    T_ref_scan = (np.eye(4),) + tuple(invert(T_world_ref) @ st.T_world_scan for st in stations[1:])
    seconds = time.perf_counter() - t0
    say(1.0, "done")
    metrics = tuple([Metric(f"points in {s.name}", "", s.n_points) for s in scans] + [
        Metric("trees", "", 1 + len(nb_xy)), Metric("shrubs", "", len(sh_xy)),
        Metric("target height", "m", target.shape.height_m), Metric("target DBH", "m", target.shape.dbh_m),
        Metric("rays cast", "", n_rays), Metric("simulation time", "s", round(seconds, 3))])
    return SimulatedCase(spec, tuple(scans), T_ref_scan, tuple(stations), tuple(trees), scene, None,  # type: ignore[arg-type]
                         tuple(labels), seconds, metrics, tree_ids=tuple(ids), return_index=tuple(rets))


def target_in_scan(case: SimulatedCase, k: int = 0) -> np.ndarray:
    """The target stem's base (x, y) in scan `k`'s frame (the target stands at the world origin)."""
    return (invert(case.stations[k].T_world_scan) @ np.r_[0.0, 0.0, 0.0, 1.0])[:2]


def plot_cases(n: int = 12, seed: int = 0, small: bool = False) -> list[PlotSpec]:
    """The seeded plot set the benchmark measures: every other plot real-like (millimetre rounding,
    second returns), every third with leaves. Steps give 0.5-2 M points per station (`small`:
    coarser steps and smaller plots for tests, ~0.1-0.2 M points)."""
    out = []
    for k in range(n):
        step = 0.1 if not small else 0.2
        out.append(PlotSpec(seed=seed * 1000 + k, angular_step_deg=(step, step), real_like=k % 2 == 1,
                            leaves=k % 3 == 2, plot_radius_m=25.0 if not small else 15.0))
    return out
