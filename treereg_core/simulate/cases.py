"""Simulated multi-station TLS cases with ground truth: the yardstick of every later stage.

`simulate_case(seed, ...)` grows a procedural tree (`simulate_tree`), places stations around it,
ray-casts each station (`simulate_scanner`) and returns a `SimulatedCase`: the scans in their own
scanner frames, the true 4x4 of each scan onto scan 1, the stations and the tree. The same seed
gives identical points. `write_case` writes it as a case folder (scan1.ply, ..., truth.json).
Stations can also be made from any point cloud (`spec.from_points`), e.g. a real tree.

`benchmark_cases(n, seed)` is the seeded test set the coarse and fine stages are measured on.

Examples
--------
>>> case = simulate_case(seed=1, angular_step_deg=(0.3, 0.3), height_m=6.0)
>>> [s.name for s in case.scans]
['scan1.ply', 'scan2.ply', 'scan3.ply']
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError
from ..params import ANGULAR_STEP_RANGE_DEG

#: Most stations a simulated case may have (each is a full scan).
MAX_STATIONS = 32
from ..io import atomic
from ..io.cases import TRUTH_NAME
from ..io.scans import read_points, write_scan
from ..results import Metric, Progress
from ..geometry.rigid import apply_transform, invert, make_transform, rotation_z
from ..scan import Scan
from .scanner import scan_scene, visible_points, visible_points_splat
from .wind import Sway, draw_sway, sway_tree
from .tree import (
    LABEL_OTHER_TREE,
    Scene,
    TreeInfo,
    TreeShape,
    make_ground,
    make_tree,
    merge_scenes,
    tilt_rotation,
)
from ..io.transforms import TransformFile, write_transforms

#: The truth file of a case folder (a transform file, plus the steps and stations).
#: With a ground plane, trunks start this far below it: a sloped ground then leaves no gap.
_GROUND_SINK_M = 0.3


@dataclass(frozen=True)
class CaseSpec:
    """Everything that defines a simulated case; `build()` makes it. Lengths in metres, angles in
    degrees. Ranges (lo, hi) are drawn uniformly from the seed.

    seed : the random seed; everything below is reproducible from it.
    n_stations : number of scans.
    angular_step_deg : (phi, varphi), horizontal and vertical steps of the instrument.
    height_m, dbh_m : the tree's height and diameter at breast height; None = drawn (the height
        from `height_range_m`, the DBH from the height, 0.15-0.8 m).
    orders : branching orders (1-3).
    bent, lean_deg : a trunk bent along its length; a whole tree leaning by this angle.
    leaves : small disks (3-6 cm across) on the outer two branch orders.
    ground, ground_slope_deg, ground_radius_m : a ground plane sloping by up to this angle, kept
        within this radius of the tree.
    ground_front_m : each scan's window reaches down to the ground this far in front of the trunk
        (the ground nearer the scanner is not scanned: it would be most of the points).
    second_tree : a smaller tree 3.5-6 m from the first, in the scans' view.
    tilt_deg : instruments tilted by half to all of this angle (not perfectly levelled; up to 15 deg:
        scanners without a tilt compensator stand several degrees off level).
    tilt_exact : every instrument tilted by exactly `tilt_deg` (about an axis of its own).
    tilt_mount : 0, or k: one more scan (the last) taken at station k's position (0.15 m higher) with
        the scanner turned `tilt_mount_deg` about a horizontal axis, as a tilt mount turns it to see the
        canopy; its window is the tree and the ground in front of it.
    range_sigma_m, dropout : range noise (along the ray) and fraction of lost returns.
    station_distance_m, separation_deg, instrument_height_m : stations at this horizontal distance
        from the trunk, this azimuth apart (scan 2 one way from scan 1, scan 3 the other way), with
        the instrument this high above the ground.
    from_points : a point-cloud file (x y z ...) to make the stations from instead of a procedural
        tree; the cloud is moved so that its base is at z = 0 and its trunk at x = y = 0. Each
        station keeps the nearest point of each angular cell.
    splat_radius_m : with `from_points`, let each point also hide what lies behind it as a sphere
        of this radius (about the cloud's point spacing), so that a station does not see the back
        of a sparse trunk through the gaps between its points; None = cells only.
    wind_m : wind between the stations (`simulate.wind`): before each station scans, every tree's
        stem bends as a cantilever with this top sway, in a direction of the station's own (drawn);
        the stem base and the ground stay put. 0 = still air.
    flutter : with wind, small branches (order 2 and up) flutter on their own by up to this times
        the top sway at their tips; leaves follow them and flutter a little more.
    mixed_pixels : share of the edge returns (a grid neighbour empty or 0.3 m farther) that are
        mixed pixels, strung out 2-80 cm behind the edge along their ray (`scanner.scan_scene`).
    """

    seed: int = 0
    n_stations: int = 3
    angular_step_deg: tuple[float, float] = (0.1, 0.1)
    height_m: float | None = None
    height_range_m: tuple[float, float] = (5.0, 25.0)
    dbh_m: float | None = None
    orders: int = 3
    bent: bool = False
    lean_deg: float = 0.0
    leaves: bool = False
    ground: bool = False
    ground_slope_deg: float = 3.0
    ground_radius_m: float = 20.0
    ground_front_m: float = 2.0
    second_tree: bool = False
    tilt_deg: float = 0.0
    tilt_exact: bool = False
    tilt_mount: int = 0
    tilt_mount_deg: float = 90.0
    range_sigma_m: float = 0.003
    dropout: float = 0.02
    station_distance_m: tuple[float, float] = (8.0, 15.0)
    separation_deg: tuple[float, float] = (90.0, 150.0)
    instrument_height_m: tuple[float, float] = (1.3, 1.7)
    from_points: str | None = None
    splat_radius_m: float | None = None
    wind_m: float = 0.0
    flutter: float = 0.5
    mixed_pixels: float = 0.0

    def __post_init__(self) -> None:
        def pair(name: str) -> tuple[float, float]:
            v = getattr(self, name)
            if np.isscalar(v):
                v = (v, v)
            v = tuple(float(x) for x in v)
            if len(v) != 2 or not v[0] <= v[1]:
                raise ConfigError(f"{name}: needs (low, high) with low <= high, got {getattr(self, name)!r}")
            object.__setattr__(self, name, v)
            return v

        step = self.angular_step_deg
        step = (step, step) if np.isscalar(step) else tuple(step)
        if len(step) != 2:
            raise ConfigError(f"angular_step_deg: needs (phi, varphi), got {self.angular_step_deg!r}")
        object.__setattr__(self, "angular_step_deg", (float(step[0]), float(step[1])))
        for name in ("height_range_m", "station_distance_m", "separation_deg", "instrument_height_m"):
            pair(name)
        phi, vphi = self.angular_step_deg
        step_lo, step_hi = ANGULAR_STEP_RANGE_DEG
        for name in ("range_sigma_m", "dropout", "lean_deg", "tilt_deg", "tilt_mount_deg", "ground_slope_deg", "ground_radius_m",
                     "ground_front_m", "wind_m", "flutter", "mixed_pixels"):
            if not np.isfinite(getattr(self, name)):
                raise ConfigError(f"{name}: {getattr(self, name)} is not a finite number")
        checks = [
            (1 <= self.n_stations <= MAX_STATIONS, f"n_stations: {self.n_stations} is outside 1-{MAX_STATIONS} stations"),
            (self.seed >= 0, f"seed: {self.seed} is not a non-negative whole number"),
            (all(step_lo <= x <= step_hi for x in (phi, vphi)),
             f"angular_step_deg: {phi:g} x {vphi:g} deg is outside the allowed range ({step_lo:g} to {step_hi:g} deg)"),
            (self.orders in (1, 2, 3), f"orders: {self.orders} is not 1, 2 or 3"),
            (self.height_m is None or 1.0 <= self.height_m <= 60.0, f"height_m: {self.height_m} is outside 1-60 m"),
            (self.dbh_m is None or 0.02 <= self.dbh_m <= 3.0, f"dbh_m: {self.dbh_m} is outside 0.02-3 m"),
            (self.height_range_m[0] >= 1.0, "height_range_m: heights below 1 m are not trees"),
            (0 <= self.lean_deg <= 45, f"lean_deg: {self.lean_deg} is outside 0-45 deg"),
            (0 <= self.ground_slope_deg <= 30, f"ground_slope_deg: {self.ground_slope_deg} is outside 0-30 deg"),
            (0 <= self.tilt_deg <= 15, f"tilt_deg: {self.tilt_deg} is outside 0-15 deg"),
            (0 <= self.tilt_mount <= self.n_stations, f"tilt_mount: {self.tilt_mount} is not 0 or a station (1-{self.n_stations})"),
            (self.n_stations + (self.tilt_mount > 0) <= MAX_STATIONS, f"tilt_mount: one more scan than {MAX_STATIONS}"),
            (0 <= self.tilt_mount_deg <= 180, f"tilt_mount_deg: {self.tilt_mount_deg} is outside 0-180 deg"),
            (0 <= self.range_sigma_m <= 1, f"range_sigma_m: {self.range_sigma_m} is outside 0-1 m"),
            (0 <= self.dropout < 1, f"dropout: {self.dropout} is outside [0, 1)"),
            (self.station_distance_m[0] > 0.5, "station_distance_m: stations must stand more than 0.5 m from the trunk"),
            (self.station_distance_m[1] <= 200.0, "station_distance_m: stations farther than 200 m from the trunk see no tree"),
            (1.0 <= self.ground_radius_m <= 500.0, f"ground_radius_m: {self.ground_radius_m} is outside 1-500 m"),
            (0.0 <= self.ground_front_m <= 500.0, f"ground_front_m: {self.ground_front_m} is outside 0-500 m"),
            (0.0 <= self.wind_m <= 5.0, f"wind_m: a top sway of {self.wind_m} m is outside 0-5 m"),
            (0.0 <= self.flutter <= 2.0, f"flutter: {self.flutter} is outside 0-2 (times the top sway)"),
            (0.0 <= self.mixed_pixels <= 1.0, f"mixed_pixels: {self.mixed_pixels} is outside 0-1 (share of the edge returns)"),
        ]
        checks.append((self.splat_radius_m is None or (self.from_points is not None and 0 < self.splat_radius_m <= 1),
                       "splat_radius_m: needs from_points and a radius in (0, 1] m"))
        for ok, msg in checks:
            if not ok:
                raise ConfigError(msg)
        if self.from_points is not None:
            procedural = [n for n, v in (("height_m", self.height_m), ("dbh_m", self.dbh_m), ("bent", self.bent),
                                         ("lean_deg", self.lean_deg), ("leaves", self.leaves),
                                         ("ground", self.ground), ("second_tree", self.second_tree),
                                         ("wind_m", self.wind_m), ("mixed_pixels", self.mixed_pixels)) if v]
            if procedural:
                raise ConfigError(f"from_points: {', '.join(procedural)} only apply to procedural trees")

    def build(self, progress: Progress | None = None) -> "SimulatedCase":
        """Simulate this case (see `simulate_case`)."""
        return _build(self, progress)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready options."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @property
    def label(self) -> str:
        """A short description, e.g. 'seed 3: 12.0 m, leaves, ground, 0.05 deg'."""
        flags = [n for n in ("bent", "leaves", "ground", "second_tree") if getattr(self, n)]
        if self.lean_deg:
            flags.append(f"lean {self.lean_deg:g} deg")
        if self.tilt_deg:
            flags.append(f"tilt {self.tilt_deg:g} deg" if self.tilt_exact else f"tilt up to {self.tilt_deg:g} deg")
        if self.tilt_mount:
            flags.append(f"tilt mount {self.tilt_mount_deg:g} deg at station {self.tilt_mount}")
        if self.wind_m:
            flags.append(f"wind {self.wind_m * 100:g} cm")
        if self.mixed_pixels:
            flags.append(f"mixed pixels {self.mixed_pixels:.0%}")
        what = Path(self.from_points).name if self.from_points else (
            f"{self.height_m:g} m" if self.height_m else f"{self.height_range_m[0]:g}-{self.height_range_m[1]:g} m")
        step = "x".join(f"{v:g}" for v in sorted(set(self.angular_step_deg)))
        return f"seed {self.seed}: " + ", ".join([what, *flags, f"{step} deg"])

    @property
    def awkward(self) -> bool:
        """Leaves, a bent trunk, ground or a tilted instrument: the harder cases."""
        return bool(self.leaves or self.bent or self.ground or self.tilt_deg > 0 or self.second_tree or self.tilt_mount)


@dataclass(frozen=True, eq=False)
class Station:
    """One instrument set-up, in the world frame of the simulation (main tree base at the origin).

    position_m: instrument centre; heading_deg: world azimuth of the scan frame's x axis;
    tilt_deg / tilt_axis_deg: how far the instrument is off level, about which horizontal axis;
    T_world_scan: 4x4 mapping the scan's points into the world; sway: the main tree's wind as this
    station found it (None in still air).
    """

    position_m: np.ndarray
    heading_deg: float
    tilt_deg: float
    tilt_axis_deg: float
    T_world_scan: np.ndarray
    sway: Sway | None = None

    @property
    def distance_m(self) -> float:
        """Horizontal distance to the main trunk."""
        return float(np.hypot(self.position_m[0], self.position_m[1]))

    @property
    def azimuth_deg(self) -> float:
        """World azimuth of the station seen from the main trunk."""
        return float(np.degrees(np.arctan2(self.position_m[1], self.position_m[0])))

    def to_dict(self) -> dict[str, Any]:
        out = {
            "T_world_scan": [[float(v) for v in row] for row in self.T_world_scan],
            "position_m": [round(float(v), 6) for v in self.position_m],
            "heading_deg": round(self.heading_deg, 6),
            "tilt_deg": round(self.tilt_deg, 6),
            "tilt_axis_deg": round(self.tilt_axis_deg, 6),
            "distance_m": round(self.distance_m, 6),
            "azimuth_deg": round(self.azimuth_deg, 6),
        }
        if self.sway is not None:
            out["wind"] = self.sway.to_dict()
        return out


@dataclass(frozen=True, eq=False)
class SimulatedCase:
    """A simulated case: scans with their true transforms.

    scans: the scans (scan1.ply, scan2.ply, ...) in their scanner frames, steps known.
    T_ref_scan: true 4x4 of each scan onto scan 1's frame (identity for scan 1).
    stations: where each scan was taken. trees: the procedural trees (empty for point clouds).
    scene: all primitives in the world frame (None for point clouds); cloud: the input point cloud
        in the world frame (None for procedural trees).
    labels: per scan, a part label per point (`simulate_tree.LABEL_NAMES`; -1 for point clouds).
    tree_ids: per scan, the index into `trees` of the tree each point hit (-1 = ground); plots only.
    return_index: per scan, 0 for first returns, 1 for second returns; plots only.
    mixed: per scan, True for the mixed pixels (`spec.mixed_pixels`); empty when there are none.
    """

    spec: CaseSpec
    scans: tuple[Scan, ...]
    T_ref_scan: tuple[np.ndarray, ...]
    stations: tuple[Station, ...]
    trees: tuple[TreeInfo, ...]
    scene: Scene | None
    cloud: np.ndarray | None
    labels: tuple[np.ndarray, ...]
    seconds: float
    metrics: tuple[Metric, ...]
    tree_ids: tuple[np.ndarray, ...] = ()
    return_index: tuple[np.ndarray, ...] = ()
    mixed: tuple[np.ndarray, ...] = ()

    def relative_sway_m(self, k: int, ref: int = 0) -> np.ndarray:
        """How far the main tree's top had moved at station `k` from where station `ref` saw it: a
        horizontal 3-vector in scan `ref`'s frame (zeros in still air)."""
        s0, sk = self.stations[ref].sway, self.stations[k].sway
        if s0 is None or sk is None:
            return np.zeros(3)
        d = np.array([sk.top_m[0] - s0.top_m[0], sk.top_m[1] - s0.top_m[1], 0.0])
        return self.stations[ref].T_world_scan[:3, :3].T @ d

    @property
    def angular_step_deg(self) -> tuple[float, float]:
        return self.spec.angular_step_deg

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.scans)

    def truth(self) -> dict[str, np.ndarray]:
        """{scan name: T_ref_scan}, the reference (scan 1) included as the identity."""
        return {s.name: T for s, T in zip(self.scans, self.T_ref_scan)}

    def world_points(self, k: int) -> np.ndarray:
        """Scan `k`'s points in the world frame (where the tree stands at the origin)."""
        return apply_transform(self.stations[k].T_world_scan, self.scans[k].points)


def write_case(case: SimulatedCase, out_dir: str | Path, dtype: str = "float64",
               progress: Progress | None = None) -> Path:
    """Write a case folder: one PLY per scan (scan1.ply, ...) and truth.json.

    truth.json is a transform file (`transform_io`): reference scan1.ply, the true `T_ref_scan` of
    every scan (scan1.ply maps by the identity), plus "angular_step_deg": [phi, varphi], the
    "stations" (world pose of each scan), the "trees" drawn and the "simulation" options.
    `dtype="float32"` halves the PLY sizes (about a micrometre of rounding at 10 m).
    Every file is written atomically. Returns the path of truth.json.
    """
    out = Path(out_dir)
    say = progress or (lambda f, t: None)
    with atomic.batch():  # all files or, on an error or Ctrl-C, none replace what was there
        for k, scan in enumerate(case.scans):
            say(k / (len(case.scans) + 1), f"writing {scan.name}")
            write_scan(out / scan.name, scan.points, dtype=dtype)
        path = _write_truth(case, out)
    say(1.0, f"wrote {out}")
    return path


def case_paths(out_dir: str | Path, n_stations: int) -> list[Path]:
    """The files `write_case` writes for `n_stations` scans (checked before simulating)."""
    out = Path(out_dir)
    return [out / f"scan{k + 1}.ply" for k in range(n_stations)] + [out / TRUTH_NAME]


def _write_truth(case: SimulatedCase, out: Path) -> Path:
    tf = TransformFile(
        reference=case.scans[0].name,
        transforms=case.truth(),
        extra={
            "angular_step_deg": list(case.angular_step_deg),
            "stations": {s.name: st.to_dict() for s, st in zip(case.scans, case.stations)},
            "trees": [t.to_dict() for t in case.trees],
            "points": {s.name: s.n_points for s in case.scans},
            "simulation": case.spec.to_dict(),
        },
    )
    return write_transforms(out / TRUTH_NAME, tf)


def simulate_case(seed: int = 0, n_stations: int = 3, progress: Progress | None = None,
                  **options: Any) -> SimulatedCase:
    """Simulate `n_stations` scans of a procedural tree (or of a point cloud) with ground truth.

    `options` are the fields of `CaseSpec` (angular_step_deg, height_m, leaves, bent, ground, tilt_deg,
    from_points, ...). Same arguments, identical points.
    """
    return CaseSpec(seed=seed, n_stations=n_stations, **options).build(progress)


def _station_azimuths(n: int, separation: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
    """World azimuths (deg) of the stations around the tree.

    Scan 2 lies `separation` one way from scan 1 and scan 3 the same range the other way, so that
    both registered pairs (2->1, 3->1) are that far apart; four or more stations are spread evenly
    with some jitter.
    """
    a1 = rng.uniform(0, 360)
    if n <= 3:
        out = [a1, a1 + rng.uniform(*separation), a1 - rng.uniform(*separation)][:n]
        return np.array(out)
    gap = 360.0 / n
    return a1 + gap * np.arange(n) + rng.uniform(-0.15, 0.15, n) * gap


def _make_stations(spec: CaseSpec, ground_height, rng: np.random.Generator) -> list[Station]:
    az = _station_azimuths(spec.n_stations, spec.separation_deg, rng)
    out = []
    for a in az:
        d = rng.uniform(*spec.station_distance_m)
        xy = d * np.array([np.cos(np.radians(a)), np.sin(np.radians(a))])
        z = float(ground_height(xy)) + rng.uniform(*spec.instrument_height_m)
        heading = float(rng.uniform(0, 360))
        # Drawn whether or not there is a tilt, so that switching it on keeps the other draws.
        tilt = float(spec.tilt_deg * (1.0 if spec.tilt_exact else rng.uniform(0.5, 1.0)))
        if spec.tilt_exact:
            rng.uniform(0.5, 1.0)  # the same draws either way
        tilt_axis = float(rng.uniform(0, 360))
        # The instrument's frame: turned by its heading, then tipped slightly off level.
        R = rotation_z(heading) @ tilt_rotation(tilt, tilt_axis)
        pos = np.array([xy[0], xy[1], z])
        out.append(Station(pos, heading, tilt, tilt_axis, make_transform(R, pos)))
    if spec.tilt_mount:
        # Drawn after every station's: a tilt mount leaves the other stations as they were.
        base = out[spec.tilt_mount - 1]
        heading = float(rng.uniform(0, 360))
        # Turned about a horizontal axis within 30 deg of the way to the tree, so the tree stays off the
        # scanner's poles (a real tilt-mount scan is a full sphere; the simulated one is a window).
        axis = float(base.azimuth_deg + 180.0 + rng.uniform(-30.0, 30.0))
        R = tilt_rotation(spec.tilt_mount_deg, axis) @ rotation_z(heading)
        pos = base.position_m + np.array([0.0, 0.0, 0.15])
        out.append(Station(pos, heading, spec.tilt_mount_deg, axis, make_transform(R, pos)))
    return out


def _mount_window(scene: Scene, st: Station, T_scan_world: np.ndarray, front_m: float) -> tuple[float, float, float, float]:
    """The window (deg: azimuth lo, hi; elevation lo, hi) of a turned scanner: the angular hull of the
    tree's bounds and of the ground in front of the scanner (from `front_m` before the trunk on), with
    a margin."""
    lo, hi = scene.points_bounds()
    grid = np.stack(np.meshgrid(*(np.linspace(a, b, 6) for a, b in zip(lo, hi)), indexing="ij"), -1).reshape(-1, 3)
    d = st.distance_m
    toward = -st.position_m[:2] / max(d, 1e-9)
    side = np.array([-toward[1], toward[0]])
    along, across = np.meshgrid(np.linspace(max(d - front_m, 0.5), d + 3.0, 12), np.linspace(-4.0, 4.0, 9))
    xy = st.position_m[:2] + along.reshape(-1, 1) * toward + across.reshape(-1, 1) * side
    z = np.array([scene.ground.height_at(q) for q in xy]) if scene.ground is not None else np.zeros(len(xy))
    pts = apply_transform(T_scan_world, np.vstack([grid, np.c_[xy, z]]))
    alpha = np.degrees(np.arctan2(pts[:, 1], pts[:, 0]))
    beta = np.degrees(np.arctan2(pts[:, 2], np.hypot(pts[:, 0], pts[:, 1])))
    c = np.degrees(np.arctan2(pts[:, 1].mean(), pts[:, 0].mean()))
    rel = (alpha - c + 180.0) % 360.0 - 180.0
    m = 3.0
    return (float(c + rel.min() - m), float(c + rel.max() + m), float(beta.min() - m), float(beta.max() + m))


def _draw_shape(spec: CaseSpec, rng: np.random.Generator) -> TreeShape:
    H = spec.height_m if spec.height_m is not None else float(rng.uniform(*spec.height_range_m))
    # DBH from height (a loose allometry, about 2.5 cm per metre), unless given.
    dbh = spec.dbh_m if spec.dbh_m is not None else float(np.clip(0.025 * H * rng.uniform(0.8, 1.25), 0.15, 0.8))
    return TreeShape(height_m=round(H, 3), dbh_m=round(dbh, 4), orders=spec.orders, bent=spec.bent,
                     lean_deg=spec.lean_deg, leaves=spec.leaves)


def _second_tree(main: TreeShape, stations: list[Station], ground_height, rng: np.random.Generator,
                 sink_m: float) -> TreeInfo:
    """A smaller tree 3.5-6 m from the main one, kept at least 4 m from every station."""
    best, best_gap = None, -1.0
    for _ in range(64):
        a, d = rng.uniform(0, 2 * np.pi), rng.uniform(3.5, 6.0)
        xy = d * np.array([np.cos(a), np.sin(a)])
        gap = min(float(np.hypot(*(xy - s.position_m[:2]))) for s in stations)
        if gap > best_gap:
            best, best_gap = xy, gap
        if gap >= 4.0:
            break
    H2 = main.height_m * rng.uniform(0.5, 0.9)
    shape = replace(main, height_m=round(H2, 3), dbh_m=round(max(0.1, main.dbh_m * H2 / main.height_m), 4),
                    bent=False, lean_deg=0.0, orders=min(main.orders, 2))
    base = np.array([best[0], best[1], float(ground_height(best))])
    return make_tree(shape, rng, base=base, label_override=LABEL_OTHER_TREE, sink_m=sink_m)


def centre_cloud(points: np.ndarray) -> np.ndarray:
    """A tree's cloud moved so its lowest point is at z = 0 and its trunk base at x = y = 0.

    The trunk base is the median x, y of the lowest half metre (at least the lowest 2% of points):
    a bounding-box centre would follow a lopsided crown instead of the stem.
    """
    p = np.asarray(points, dtype=float)[:, :3]
    z = p[:, 2] - p[:, 2].min()
    low = z <= max(0.5, float(np.quantile(z, 0.02)))
    shift = np.array([np.median(p[low, 0]), np.median(p[low, 1]), p[:, 2].min()])
    return p - shift


def _build(spec: CaseSpec, progress: Progress | None) -> SimulatedCase:
    t0 = time.perf_counter()
    say = progress or (lambda f, t: None)
    ss = np.random.SeedSequence(spec.seed)
    # Independent streams, so that e.g. switching leaves on keeps the same stations and noise.
    s_tree, s_stations, s_ground, s_other, s_noise, s_wind = ss.spawn(6)
    rng_tree, rng_stations, rng_ground, rng_other = (np.random.default_rng(s) for s in (s_tree, s_stations, s_ground, s_other))
    n_scans = spec.n_stations + (spec.tilt_mount > 0)
    rng_noise = [np.random.default_rng(s) for s in s_noise.spawn(n_scans)]
    rng_wind = [np.random.default_rng(s) for s in s_wind.spawn(n_scans)]
    trees: tuple[TreeInfo, ...] = ()
    scene: Scene | None = None
    cloud: np.ndarray | None = None
    say(0.0, "growing the tree" if spec.from_points is None else "reading the point cloud")
    if spec.from_points is not None:
        cloud = centre_cloud(read_points(spec.from_points))
        stations = _make_stations(spec, lambda xy: 0.0, rng_stations)
    else:
        shape = _draw_shape(spec, rng_tree)
        sink = _GROUND_SINK_M if spec.ground else 0.0
        main = make_tree(shape, rng_tree, sink_m=sink)
        ground = None
        if spec.ground:
            ground = make_ground(rng_ground.uniform(0, spec.ground_slope_deg), rng_ground.uniform(0, 360),
                                 spec.ground_radius_m)
            height = ground.height_at
        else:
            def height(xy: np.ndarray) -> float:
                return 0.0
        stations = _make_stations(spec, height, rng_stations)
        trees = (main,)
        if spec.second_tree:
            trees = (main, _second_tree(shape, stations, height, rng_other, sink))
        scene = merge_scenes([t.scene for t in trees], ground)

    scans, labels, mixed = [], [], []
    n_rays = 0
    for k, st in enumerate(stations):
        name = f"scan{k + 1}.ply"
        T_scan_world = invert(st.T_world_scan)
        rng = rng_noise[k]
        seen = scene
        if spec.wind_m > 0 and trees:
            # The tree as this station found it: each tree swayed its own way, the ground unmoved.
            sways = [draw_sway(spec.wind_m, spec.flutter, rng_wind[k]) for _ in trees]
            seen = merge_scenes([sway_tree(t, w, rng_wind[k]) for t, w in zip(trees, sways)], scene.ground)
            stations[k] = st = replace(st, sway=sways[0])

        def sub(f: float, text: str, k: int = k) -> None:
            say((k + 0.1 + 0.9 * f) / len(stations), f"{name}: {text}")

        sub(0.0, "casting rays" if cloud is None else "binning points")
        if cloud is not None:
            local = apply_transform(T_scan_world, cloud)
            if spec.splat_radius_m is None:
                pts, _ = visible_points(local, spec.angular_step_deg, rng, spec.range_sigma_m, spec.dropout)
            else:
                pts, _ = visible_points_splat(local, spec.angular_step_deg, spec.splat_radius_m, rng,
                                              spec.range_sigma_m, spec.dropout)
            lab = np.full(len(pts), -1, dtype=np.int8)
        else:
            near = max(st.distance_m - spec.ground_front_m, 0.0)
            mount = spec.tilt_mount > 0 and k == len(stations) - 1
            rs = scan_scene(seen.transformed(T_scan_world), spec.angular_step_deg, rng,
                            spec.range_sigma_m, spec.dropout, ground_near_m=near, progress=sub,
                            mixed_pixels=spec.mixed_pixels,
                            window_deg=_mount_window(seen, st, T_scan_world, spec.ground_front_m) if mount else None)
            pts, lab = rs.points, rs.labels
            n_rays += rs.n_rays
            if spec.mixed_pixels > 0:
                mixed.append(rs.mixed)
        scans.append(Scan.from_points(pts, name=name, angular_step_deg=spec.angular_step_deg))
        labels.append(lab)
    T_world_ref = stations[0].T_world_scan
    # Scan 1 is the reference: exactly the identity, not inv(T) @ T with its rounding.
    T_ref_scan = (np.eye(4),) + tuple(invert(T_world_ref) @ st.T_world_scan for st in stations[1:])
    seconds = time.perf_counter() - t0
    say(1.0, "done")
    metrics = [Metric(f"points in {s.name}", "", s.n_points) for s in scans]
    if trees:
        metrics += [Metric("tree height", "m", trees[0].shape.height_m), Metric("tree DBH", "m", trees[0].shape.dbh_m),
                    Metric("rays cast", "", n_rays)]
    if spec.wind_m > 0:
        metrics += [Metric(f"top sway, {s.name}", "m", round(st.sway.magnitude_m, 4)) for s, st in zip(scans, stations)
                    if st.sway is not None]
    if mixed:
        metrics += [Metric(f"mixed pixels, {s.name}", "", int(m.sum())) for s, m in zip(scans, mixed)]
    metrics.append(Metric("simulation time", "s", round(seconds, 3)))
    return SimulatedCase(spec, tuple(scans), T_ref_scan, tuple(stations), trees, scene, cloud,
                         tuple(labels), seconds, tuple(metrics), mixed=tuple(mixed))


#: Feature sets of the awkward benchmark cases, in turn: every hard feature appears several times.
_AWKWARD = (
    ("leaves", "ground"),
    ("bent", "tilt"),
    ("leaves", "bent", "ground", "tilt"),
    ("ground", "tilt"),
    ("leaves", "tilt"),
    ("bent", "ground"),
    ("leaves", "bent"),
    ("leaves", "ground", "tilt"),
)


def benchmark_cases(n: int = 24, seed: int = 0, small: bool = False) -> list[CaseSpec]:
    """The seeded test set the coarse and fine stages are measured on.

    Every third case (ceil(n/3) of them, starting with the first) is awkward: two or more of
    leaves, a bent trunk, ground and an instrument tilt of up to 0.3 deg, in turn; the others are
    plain leaf-off trees. Trees are 8-15 m tall, 3 stations 8-15 m from the trunk, 90-150 deg
    apart. The angular step grows with the tree's height (and with leaves or ground, which add
    points) so that each scan holds roughly 50k-300k points.

    `small=True` gives the CI variant: trees 6-9 m and coarser steps, roughly 10k-30k points per
    scan, each case simulated in well under 2 s.
    """
    rng = np.random.default_rng(np.random.SeedSequence([seed, 7]))
    specs = []
    for k in range(n):
        features = _AWKWARD[(k // 3) % len(_AWKWARD)] if k % 3 == 0 else ()
        lo, hi = (6.0, 9.0) if small else (8.0, 15.0)
        height = round(float(rng.uniform(lo, hi)), 2)
        # Points per scan scale as (height / (distance * step))^2: a step proportional to the height
        # keeps the count in range whatever the tree; leaves add ~50%, ground ~150%.
        step = (0.085 if small else 0.037) * height / 13.0
        step *= 1.2 if "leaves" in features else 1.0
        step *= 1.6 if "ground" in features else 1.0
        specs.append(CaseSpec(
            seed=seed * 1000 + k,
            angular_step_deg=(round(step, 4), round(step, 4)),
            height_m=height,
            bent="bent" in features,
            leaves="leaves" in features,
            ground="ground" in features,
            tilt_deg=0.3 if "tilt" in features else 0.0,
            lean_deg=round(float(rng.uniform(0, 6)), 2) if k % 3 == 1 else 0.0,
        ))
    return specs


def coarse_like_error(T_true: np.ndarray, points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """`T_true` moved by an error like a coarse registration leaves: 2-8 cm, 0.3-1 deg of yaw and up
    to 0.2 deg of tilt, about the centre of `points` (the scan's points, mapped by `T_true`).

    Fine-stage tests and benchmarks start from it, so they do not depend on the coarse stage.
    """
    from scipy.spatial.transform import Rotation

    d = rng.normal(size=3)
    t = d / np.linalg.norm(d) * rng.uniform(0.02, 0.08)
    axis = np.r_[rng.normal(size=2), 0.0]
    axis /= np.linalg.norm(axis)
    tilt = Rotation.from_rotvec(np.radians(rng.uniform(0.0, 0.2)) * axis).as_matrix()
    R = rotation_z(rng.uniform(0.3, 1.0) * rng.choice([-1, 1])) @ tilt
    c = apply_transform(T_true, points).mean(axis=0)
    return make_transform(R, c - R @ c + t) @ T_true
