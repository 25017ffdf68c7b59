"""Simulated surveys: a whole plot scanned from a grid of stations (issue 31).

Forest plots are surveyed from a grid of stations, 9 to 60 and more, not from three stations round
one tree. `SurveySpec(seed, grid=(3, 3)).build()` lays stations on a `cols x rows` grid
`spacing_m` apart (each moved a little, `jitter_m`, and turned to a heading of its own), spreads
trees and a few shrubs over the plot (the grid's extent plus `margin_m`) clear of the stations and
of each other, on a ground that slopes by `ground_slope_deg`, and ray-casts a full panorama from
every station as `plots` does (`plots.scan_station`). `orchard=True` clones one tree on a 4 x 3 m
grid instead, each copy turned about its vertical: every stem looks like its neighbours, so a
shift by one row looks right.

The result is a `cases.SimulatedCase` (stations st01.ply, st02.ply, ... in grid order, row by
row; truth onto st01.ply; `tree_ids` per point), so everything that measures cases measures
surveys. `SurveySpec.world()` and `scan_station` give one station at a time, so a large survey can
be written station by station without holding every scan (`write_survey`).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from ..errors import ConfigError
from ..geometry.rigid import invert, make_transform, rotation_z
from ..io import atomic
from ..io.cases import TRUTH_NAME
from ..io.scans import write_scan
from ..io.transforms import TransformFile, write_transforms
from ..params import ANGULAR_STEP_RANGE_DEG
from ..results import Metric, Progress
from .cases import SimulatedCase, Station
from .plots import (_STATION_CLEARANCE_M, StationScan, grow_neighbour, grow_shrub, place, primitive_owners,
                    scan_station)
from .tree import GroundPlane, Scene, TreeInfo, make_ground, merge_scenes, tilt_rotation

#: Most stations a simulated survey may have (each a full panorama of ~0.6 M points).
MAX_SURVEY_STATIONS = 100
#: The orchard's grid: rows this far apart (y), trees this far apart along a row (x).
ORCHARD_ROW_M = 4.0
ORCHARD_TREE_M = 3.0
#: Shrubs keep this far from stations, trees and each other's stems (m).
_SHRUB_CLEARANCE_M = 1.0
_SHRUB_HEIGHT_M = (0.8, 2.5)


@dataclass(frozen=True)
class SurveySpec:
    """Everything that defines a simulated survey; ranges (lo, hi) are drawn from the seed.

    grid : (cols, rows) of stations, `spacing_m` apart, each moved by up to `jitter_m` in x and y.
    margin_m : the plot (where trees stand, and the ground) reaches this far beyond the outer stations.
    n_trees : how many trees; None = `trees_per_ha` over the plot's area (a 3 x 3 grid 10 m apart:
        a 30 m plot, 22-30 trees).
    tree_height_m : each tree's height (its DBH about 2.5 cm per metre, as `plots`' neighbours).
    shrubs_per_ha : small leafy bushes over the plot (none in an orchard).
    orchard : one tree (`orchard_height_m`) cloned on a 4 x 3 m grid, each copy turned about its
        vertical by its own random angle; copies within reach of a station left out.
    ground_slope_deg : the ground plane rises by exactly this angle, towards a drawn azimuth.
    angular_step_deg, elevation_deg, instrument_height_m, tilt_deg, range_sigma_m, dropout,
    real_like, second_returns : the instrument, as in `plots.PlotSpec` (a full 360 deg in azimuth).
    """

    seed: int = 0
    grid: tuple[int, int] = (3, 3)
    spacing_m: float = 10.0
    jitter_m: float = 1.0
    margin_m: float = 5.0
    n_trees: tuple[int, int] | None = None
    trees_per_ha: tuple[float, float] = (220.0, 290.0)
    tree_height_m: tuple[float, float] = (10.0, 20.0)
    shrubs_per_ha: tuple[float, float] = (30.0, 60.0)
    leaves: bool = False
    orchard: bool = False
    orchard_height_m: tuple[float, float] = (4.0, 6.0)
    ground_slope_deg: float = 2.0
    angular_step_deg: tuple[float, float] = (0.17, 0.17)
    elevation_deg: tuple[float, float] = (-40.0, 60.0)
    instrument_height_m: tuple[float, float] = (1.3, 1.7)
    tilt_deg: float = 0.0
    range_sigma_m: float = 0.003
    dropout: float = 0.02
    real_like: bool = False
    second_returns: float = 0.3

    def __post_init__(self) -> None:
        _normalise(self)
        for ok, msg in _checks(self):
            if not ok:
                raise ConfigError(msg)

    @property
    def n_stations(self) -> int:
        return self.grid[0] * self.grid[1]

    @property
    def half_extent_m(self) -> tuple[float, float]:
        """Half the plot's size in x and y (the plot is centred on the world origin)."""
        cols, rows = self.grid
        return (self._half(cols), self._half(rows))

    def _half(self, n: int) -> float:
        return (n - 1) / 2 * self.spacing_m + self.jitter_m + self.margin_m

    @property
    def names(self) -> tuple[str, ...]:
        return station_names(self.n_stations)

    def world(self) -> "SurveyWorld":
        """The plot and its stations, before any ray is cast (the same spec gives the same world)."""
        return _world(self)

    def build(self, progress: Progress | None = None) -> SimulatedCase:
        """Simulate this survey (the same spec gives identical points)."""
        return _build(self, progress)

    def to_dict(self) -> dict[str, Any]:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @property
    def label(self) -> str:
        cols, rows = self.grid
        what = ["orchard" if self.orchard else ("leafy" if self.leaves else "leaf-off")]
        what += [f"slope {self.ground_slope_deg:g} deg"] if self.ground_slope_deg >= 5 else []
        what += ["real-like"] if self.real_like else []
        step = "x".join(f"{v:g}" for v in sorted(set(self.angular_step_deg)))
        return f"survey {cols}x{rows} seed {self.seed}: " + ", ".join([*what, f"{self.spacing_m:g} m", f"{step} deg"])

    @property
    def awkward(self) -> bool:
        return True


def _pair(spec: SurveySpec, name: str) -> None:
    v = getattr(spec, name)
    v = (v, v) if np.isscalar(v) else tuple(v)
    if len(v) != 2 or not all(isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool)
                              and np.isfinite(x) for x in v) or not v[0] <= v[1]:
        raise ConfigError(f"{name}: needs (low, high), finite numbers with low <= high, got {getattr(spec, name)!r}")
    object.__setattr__(spec, name, (v[0], v[1]))


def _normalise(spec: SurveySpec) -> None:
    """Tuples of numbers where ranges are given (lists from JSON, one number for both)."""
    grid = tuple(spec.grid) if not np.isscalar(spec.grid) else ()
    if len(grid) != 2 or not all(isinstance(n, (int, np.integer)) and not isinstance(n, bool) for n in grid):
        raise ConfigError(f"grid: needs (cols, rows), two whole numbers, got {spec.grid!r}")
    object.__setattr__(spec, "grid", (int(grid[0]), int(grid[1])))
    for name in ("trees_per_ha", "tree_height_m", "shrubs_per_ha", "orchard_height_m", "angular_step_deg",
                 "elevation_deg", "instrument_height_m") + (("n_trees",) if spec.n_trees is not None else ()):
        _pair(spec, name)
    object.__setattr__(spec, "angular_step_deg", tuple(float(v) for v in spec.angular_step_deg))
    if spec.n_trees is not None:
        lo, hi = spec.n_trees
        if lo != int(lo) or hi != int(hi):
            raise ConfigError(f"n_trees: needs whole numbers, got {spec.n_trees!r}")
        object.__setattr__(spec, "n_trees", (int(lo), int(hi)))
    for name in ("spacing_m", "jitter_m", "margin_m", "ground_slope_deg", "tilt_deg", "range_sigma_m", "dropout",
                 "second_returns"):
        v = getattr(spec, name)
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not np.isfinite(v):
            raise ConfigError(f"{name}: {v!r} is not a finite number")


def _checks(spec: SurveySpec) -> list[tuple[bool, str]]:
    cols, rows = spec.grid
    lo, hi = ANGULAR_STEP_RANGE_DEG
    n_trees = spec.n_trees or (0, 0)
    return [
        (isinstance(spec.seed, (int, np.integer)) and not isinstance(spec.seed, bool) and spec.seed >= 0,
         f"seed: {spec.seed!r} is not a non-negative whole number"),
        (cols >= 1 and rows >= 1 and 2 <= cols * rows <= MAX_SURVEY_STATIONS,
         f"grid: {cols}x{rows} is not 2 to {MAX_SURVEY_STATIONS} stations"),
        (2.0 <= spec.spacing_m <= 100.0, f"spacing_m: {spec.spacing_m:g} m is outside 2-100 m"),
        (0.0 <= spec.jitter_m <= spec.spacing_m / 4, f"jitter_m: {spec.jitter_m:g} m is outside 0 to a quarter of the spacing"),
        (0.0 <= spec.margin_m <= 50.0, f"margin_m: {spec.margin_m:g} m is outside 0-50 m"),
        (0 <= n_trees[0] and n_trees[1] <= 2000,
         f"n_trees: {_range_text(n_trees)} is outside 0-2000 trees"),
        (0.0 <= spec.trees_per_ha[0] and spec.trees_per_ha[1] <= 2000, f"trees_per_ha: {spec.trees_per_ha} is outside 0-2000"),
        (0.0 <= spec.shrubs_per_ha[0] and spec.shrubs_per_ha[1] <= 2000, f"shrubs_per_ha: {spec.shrubs_per_ha} is outside 0-2000"),
        (2.0 <= spec.tree_height_m[0] and spec.tree_height_m[1] <= 60.0, f"tree_height_m: {spec.tree_height_m} is outside 2-60 m"),
        (2.0 <= spec.orchard_height_m[0] and spec.orchard_height_m[1] <= 15.0,
         f"orchard_height_m: {spec.orchard_height_m} is outside 2-15 m"),
        (0.0 <= spec.ground_slope_deg <= 30.0, f"ground_slope_deg: {spec.ground_slope_deg:g} is outside 0-30 deg"),
        (all(lo <= s <= hi for s in spec.angular_step_deg),
         f"angular_step_deg: {spec.angular_step_deg[0]:g} x {spec.angular_step_deg[1]:g} deg is outside the allowed range ({lo:g} to {hi:g} deg)"),
        (-90 < spec.elevation_deg[0] < spec.elevation_deg[1] < 90, "elevation_deg: needs -90 < low < high < 90"),
        (0.5 <= spec.instrument_height_m[0] and spec.instrument_height_m[1] <= 5.0,
         f"instrument_height_m: {spec.instrument_height_m} is outside 0.5-5 m"),
        (0.0 <= spec.tilt_deg <= 10.0, f"tilt_deg: {spec.tilt_deg:g} is outside 0-10 deg"),
        (0.0 <= spec.range_sigma_m <= 1.0, f"range_sigma_m: {spec.range_sigma_m:g} is outside 0-1 m"),
        (0.0 <= spec.dropout < 1.0, f"dropout: {spec.dropout:g} is outside [0, 1)"),
        (0.0 <= spec.second_returns <= 1.0, f"second_returns: {spec.second_returns:g} is not a probability in [0, 1]"),
    ]


def _range_text(v: tuple[float, float]) -> str:
    return f"{v[0]:g}" if v[0] == v[1] else f"{v[0]:g}-{v[1]:g}"


def station_names(n: int) -> tuple[str, ...]:
    """st01.ply, st02.ply, ... (three digits from 100 stations on, so names sort in grid order)."""
    width = max(2, len(str(n)))
    return tuple(f"st{k + 1:0{width}d}.ply" for k in range(n))


@dataclass(frozen=True, eq=False)
class SurveyWorld:
    """The plot before any ray is cast: stations in grid order, trees (then shrubs), the scene with
    its ground, which tree owns each primitive, and each orchard copy's turn about its vertical."""

    spec: SurveySpec
    stations: tuple[Station, ...]
    trees: tuple[TreeInfo, ...]
    n_trees: int
    scene: Scene
    owner: np.ndarray
    turns_deg: tuple[float, ...]
    noise_seeds: tuple[np.random.SeedSequence, ...]

    def scan(self, k: int, progress: Progress | None = None) -> StationScan:
        """Station `k`'s full panorama (its own noise stream: any order, the same points)."""
        rng = np.random.default_rng(self.noise_seeds[k])
        return scan_station(self.scene, self.owner, self.stations[k], self.spec.names[k], self.spec, rng, progress)

    def truth(self) -> tuple[np.ndarray, ...]:
        """True T_ref_scan of every station onto the first (exactly the identity for the first)."""
        T_ref_world = invert(self.stations[0].T_world_scan)
        return (np.eye(4),) + tuple(T_ref_world @ st.T_world_scan for st in self.stations[1:])


def _grid_stations(spec: SurveySpec, ground: GroundPlane, rng: np.random.Generator) -> list[Station]:
    """Stations on the grid (row by row), each jittered, on the ground, turned to its own heading."""
    cols, rows = spec.grid
    out = []
    for j in range(rows):
        for i in range(cols):
            xy = np.array([(i - (cols - 1) / 2) * spec.spacing_m, (j - (rows - 1) / 2) * spec.spacing_m])
            xy = xy + rng.uniform(-spec.jitter_m, spec.jitter_m, 2)
            z = float(ground.height_at(xy)) + rng.uniform(*spec.instrument_height_m)
            heading = float(rng.uniform(0, 360))
            tilt = float(spec.tilt_deg * rng.uniform(0.5, 1.0))  # drawn either way: a tilt keeps the rest
            tilt_axis = float(rng.uniform(0, 360))
            R = rotation_z(heading) @ tilt_rotation(tilt, tilt_axis)
            pos = np.array([xy[0], xy[1], z])
            out.append(Station(pos, heading, tilt, tilt_axis, make_transform(R, pos)))
    return out


def _in_plot(half: tuple[float, float]) -> Callable[[np.random.Generator], np.ndarray]:
    """A position drawn uniformly over the plot's rectangle."""
    def draw(rng: np.random.Generator) -> np.ndarray:
        return rng.uniform([-half[0], -half[1]], [half[0], half[1]])
    return draw


def _count(n: tuple[int, int] | None, per_ha: tuple[float, float], area_m2: float, rng: np.random.Generator) -> int:
    lo, hi = n if n is not None else (per_ha[0] * area_m2 / 1e4, per_ha[1] * area_m2 / 1e4)
    return int(rng.integers(int(round(lo)), int(round(hi)) + 1))


def _forest(spec: SurveySpec, ground: GroundPlane, st_xy: list[np.ndarray], area: float,
            rng: np.random.Generator) -> list[TreeInfo]:
    """Trees over the plot, each clear of the stations and of the other trees."""
    n = _count(spec.n_trees, spec.trees_per_ha, area, rng)
    xy = place(n, _in_plot(spec.half_extent_m), st_xy, [_STATION_CLEARANCE_M] * len(st_xy), rng)
    return [grow_neighbour(float(rng.uniform(*spec.tree_height_m)), p, ground, spec.leaves, rng) for p in xy]


def _orchard(spec: SurveySpec, ground: GroundPlane, st_xy: list[np.ndarray],
             rng: np.random.Generator) -> tuple[list[TreeInfo], list[float]]:
    """One tree cloned on the orchard grid over the plot, each copy turned by its own angle; copies
    nearer a station than the clearance are left out (a scanner does not stand in a trunk)."""
    hx, hy = spec.half_extent_m
    one = grow_neighbour(float(rng.uniform(*spec.orchard_height_m)), np.zeros(2), ground, spec.leaves, rng)
    offset = rng.uniform(0, [ORCHARD_TREE_M, ORCHARD_ROW_M])  # the grid's phase against the stations'
    xs = np.arange(-hx + offset[0], hx, ORCHARD_TREE_M)
    ys = np.arange(-hy + offset[1], hy, ORCHARD_ROW_M)
    stations = np.array(st_xy).reshape(-1, 2)
    trees, turns = [], []
    for y in ys:
        for x in xs:
            turn = float(rng.uniform(0, 360))  # drawn for every grid place: the stations do not shift the rest
            p = np.array([x, y])
            if np.min(np.hypot(*(stations - p).T)) < _STATION_CLEARANCE_M:
                continue
            base = np.array([x, y, float(ground.height_at(p))])
            T = make_transform(rotation_z(turn), base - rotation_z(turn) @ one.base_m)
            trees.append(replace(one, base_m=base, scene=one.scene.transformed(T),
                                 lean_axis_deg=(one.lean_axis_deg + turn) % 360.0))
            turns.append(turn)
    return trees, turns


def _world(spec: SurveySpec) -> SurveyWorld:
    ss = np.random.SeedSequence([spec.seed, 31])
    s_stations, s_ground, s_trees, s_shrubs, s_noise = ss.spawn(5)
    rng_st, rng_ground, rng_trees, rng_shrubs = (np.random.default_rng(s) for s in (s_stations, s_ground, s_trees, s_shrubs))
    hx, hy = spec.half_extent_m
    ground = make_ground(spec.ground_slope_deg, float(rng_ground.uniform(0, 360)), float(np.hypot(hx, hy)) + 1.0)
    stations = _grid_stations(spec, ground, rng_st)
    st_xy = [s.position_m[:2] for s in stations]
    area = 4 * hx * hy
    turns: list[float] = []
    if spec.orchard:
        trees, turns = _orchard(spec, ground, st_xy, rng_trees)
        shrubs: list[TreeInfo] = []
    else:
        trees = _forest(spec, ground, st_xy, area, rng_trees)
        n_sh = _count(None, spec.shrubs_per_ha, area, rng_shrubs)
        taken = st_xy + [t.base_m[:2] for t in trees]
        sh_xy = place(n_sh, _in_plot((hx, hy)), taken, [_SHRUB_CLEARANCE_M] * len(taken), rng_shrubs)
        shrubs = [grow_shrub(_SHRUB_HEIGHT_M, p, ground, rng_shrubs) for p in sh_xy]
    everything = trees + shrubs
    scene = merge_scenes([t.scene for t in everything], ground)
    return SurveyWorld(spec, tuple(stations), tuple(everything), len(trees), scene, primitive_owners(everything),
                       tuple(turns), tuple(s_noise.spawn(len(stations))))


def _sub(say: Progress, k: int, n: int, name: str) -> Progress:
    def sub(f: float, text: str) -> None:
        say((k + f) / n, f"{name}: {text}")
    return sub


def scans(world: SurveyWorld, progress: Progress | None = None) -> Iterator[StationScan]:
    """Every station's panorama in grid order, one at a time."""
    say = progress or (lambda f, t: None)
    n = len(world.stations)
    for k in range(n):
        yield world.scan(k, _sub(say, k, n, world.spec.names[k]))


def _metrics(world: SurveyWorld, points: list[int], n_rays: int, seconds: float) -> tuple[Metric, ...]:
    return tuple([Metric(f"points in {name}", "", p) for name, p in zip(world.spec.names, points)] + [
        Metric("stations", "", len(world.stations)), Metric("trees", "", world.n_trees),
        Metric("shrubs", "", len(world.trees) - world.n_trees), Metric("rays cast", "", n_rays),
        Metric("simulation time", "s", round(seconds, 3))])


def _build(spec: SurveySpec, progress: Progress | None) -> SimulatedCase:
    t0 = time.perf_counter()
    say = progress or (lambda f, t: None)
    say(0.0, "growing the plot")
    world = spec.world()
    done = list(scans(world, say))
    seconds = time.perf_counter() - t0
    say(1.0, "done")
    metrics = _metrics(world, [s.scan.n_points for s in done], sum(s.n_rays for s in done), seconds)
    return SimulatedCase(spec, tuple(s.scan for s in done), world.truth(), world.stations, world.trees,  # type: ignore[arg-type]
                         world.scene, None, tuple(s.labels for s in done), seconds, metrics,
                         tree_ids=tuple(s.tree_ids for s in done), return_index=tuple(s.return_index for s in done))


def survey_paths(out_dir: str | Path, spec: SurveySpec) -> list[Path]:
    """The files `write_survey` writes (checked before simulating)."""
    out = Path(out_dir)
    return [out / n for n in spec.names] + [out / TRUTH_NAME]


def write_survey(spec: SurveySpec, out_dir: str | Path, dtype: str = "float64",
                 progress: Progress | None = None) -> tuple[Path, tuple[Metric, ...]]:
    """Simulate and write a survey folder station by station (one scan in memory at a time): one PLY
    per station and truth.json, as `cases.write_case` writes a case (all files or none). Returns
    the truth file's path and the simulation's metrics."""
    t0 = time.perf_counter()
    say = progress or (lambda f, t: None)
    out = Path(out_dir)
    say(0.0, "growing the plot")
    world = spec.world()
    points, n_rays = [], 0
    with atomic.batch():  # all files or, on an error or Ctrl-C, none replace what was there
        for one in scans(world, say):
            write_scan(out / one.scan.name, one.scan.points, dtype=dtype)
            points.append(one.scan.n_points)
            n_rays += one.n_rays
        tf = TransformFile(
            reference=spec.names[0],
            transforms=dict(zip(spec.names, world.truth())),
            extra={
                "angular_step_deg": list(spec.angular_step_deg),
                "stations": {n: st.to_dict() for n, st in zip(spec.names, world.stations)},
                "trees": [t.to_dict() for t in world.trees],
                "points": dict(zip(spec.names, points)),
                "simulation": {"survey": spec.to_dict()},
            },
        )
        path = write_transforms(out / TRUTH_NAME, tf)
    say(1.0, f"wrote {out}")
    return path, _metrics(world, points, n_rays, time.perf_counter() - t0)


def survey_cases(small: bool = False, seed: int = 0) -> dict[str, SurveySpec]:
    """The benchmark surveys by label: 3x3 leaf-off, 3x3 leafy, 4x4, 6x6, 3x3 sloped (12 deg),
    orchard 3x3 and a 60-station 10x6, each station 0.5-0.8 M points. `small=True`: tiny versions for
    tests (2x2 to 4x3 grids of 8 m, coarse steps, few trees, ~50 k points per station).

    `build()` holds every station: ~1.4 GB at its peak for the 6x6 (22 M points); a 60-station survey
    is better taken a station at a time (`spec.world().scan(k)`, as `write_survey` does: under 1 GB)."""
    if small:
        base = SurveySpec(seed=seed, grid=(2, 2), spacing_m=8.0, margin_m=3.0, n_trees=(6, 8), shrubs_per_ha=(20.0, 40.0),
                          tree_height_m=(6.0, 10.0), angular_step_deg=(0.5, 0.5))
        return {
            "3x3 leaf-off": base,
            "3x3 leafy": replace(base, seed=seed + 1, leaves=True),
            "4x4": replace(base, seed=seed + 2, grid=(3, 2)),
            "6x6": replace(base, seed=seed + 3, grid=(3, 3), n_trees=(8, 10)),
            "3x3 sloped": replace(base, seed=seed + 4, ground_slope_deg=12.0),
            "orchard 3x3": replace(base, seed=seed + 5, orchard=True),
            "10x6": replace(base, seed=seed + 6, grid=(4, 3), n_trees=(10, 12)),
        }
    base = SurveySpec(seed=seed)
    return {
        "3x3 leaf-off": base,
        "3x3 leafy": replace(base, seed=seed + 1, leaves=True),
        "4x4": replace(base, seed=seed + 2, grid=(4, 4)),
        # The 6x6 stand is sparser (71 trees on a 50 m grid): the same density on the 60-station one.
        "6x6": replace(base, seed=seed + 3, grid=(6, 6), trees_per_ha=(185.0, 210.0)),
        "3x3 sloped": replace(base, seed=seed + 4, ground_slope_deg=12.0),
        # Its small trees leave more sky: a finer step keeps ~0.6 M points a station.
        "orchard 3x3": replace(base, seed=seed + 5, orchard=True, spacing_m=8.0, angular_step_deg=(0.15, 0.15)),
        "10x6": replace(base, seed=seed + 6, grid=(10, 6), trees_per_ha=(185.0, 210.0)),
    }
