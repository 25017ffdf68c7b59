"""`treereg simulate`: a simulated case folder with ground truth."""

from __future__ import annotations

import argparse
import re
from typing import Any

from treereg_core.errors import ConfigError
from treereg_core.io.atomic import check_distinct, check_output_dir, check_output_file
from treereg_core.simulate.cases import CaseSpec, case_paths, write_case
from treereg_core.text import shown

from .common import angular_steps
from .progress import ProgressBar


def add(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate",
        help="simulate TLS scans of a tree with known ground truth (scan1.ply, ..., truth.json)",
        description="Grow a procedural tree (or take a point cloud), scan it from several stations "
        "with a simulated terrestrial laser scanner, and write a case folder: one PLY per scan in "
        "its scanner frame, and truth.json with the true transform of every scan onto scan1.ply.",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="case folder to write")
    p.add_argument("--seed", type=int, default=0, help="random seed; the same seed gives the same points (default: 0)")
    p.add_argument("--stations", type=int, default=3, help="number of scans (default: 3)")
    p.add_argument("--angular-step", nargs="+", type=float, metavar=("H", "V"),
                   help="instrument angular steps in degrees, phi [varphi] (default: 0.1; 0.17 for a survey)")
    p.add_argument("--height", type=float, metavar="M", help="tree height in metres (default: drawn, 5-25 m)")
    p.add_argument("--dbh", type=float, metavar="M", help="diameter at breast height in metres (default: from the height)")
    p.add_argument("--orders", type=int, choices=(1, 2, 3), default=3, help="branching orders (default: 3)")
    p.add_argument("--leaves", action="store_true", help="add leaves (small disks) to the outer branches")
    p.add_argument("--bent", action="store_true", help="bend the trunk")
    p.add_argument("--lean", type=float, default=0.0, metavar="DEG", help="lean the whole tree by this angle")
    p.add_argument("--ground", action="store_true", help="add a (slightly sloped) ground plane")
    p.add_argument("--ground-radius", type=float, default=20.0, metavar="M",
                   help="the ground reaches this far around the tree (default: 20)")
    p.add_argument("--ground-front", type=float, default=2.0, metavar="M",
                   help="scans reach down to the ground this far in front of the trunk (default: 2)")
    p.add_argument("--second-tree", action="store_true", help="add a smaller tree nearby")
    p.add_argument("--tilt", type=float, nargs="?", const=0.3, default=0.0, metavar="DEG",
                   help="instruments not perfectly levelled, by up to DEG (0.3 when given without a value)")
    p.add_argument("--wind", type=float, default=0.0, metavar="TOP_SWAY_M",
                   help="wind between the stations: before each station scans, the stem bends with this sway at "
                   "its top (m) in a direction of the station's own; small branches and leaves flutter by up to "
                   "half of it (truth.json records each station's sway; default: 0, still air)")
    p.add_argument("--flutter", type=float, default=0.5, metavar="SHARE",
                   help="with --wind: how far small branches flutter, as a share of the top sway (default: 0.5)")
    p.add_argument("--mixed-pixels", type=float, default=0.0, metavar="SHARE",
                   help="this share of the returns at a silhouette's edge are mixed pixels, strung out 2-80 cm "
                   "behind the edge along their ray (default: 0)")
    p.add_argument("--noise", type=float, default=0.003, metavar="M", help="range noise sigma in metres (default: 0.003)")
    p.add_argument("--dropout", type=float, default=0.02, help="fraction of returns lost (default: 0.02)")
    p.add_argument("--distance", type=float, nargs=2, default=[8.0, 15.0], metavar=("MIN", "MAX"),
                   help="station distance from the trunk in metres (default: 8 15)")
    p.add_argument("--from-points", metavar="FILE",
                   help="make the stations from this point cloud (a whole tree: PLY, LAS/LAZ, XYZ, ...) instead")
    p.add_argument("--splat", type=float, metavar="M",
                   help="with --from-points: each point also hides what lies behind it as a sphere of "
                   "this radius (about the point spacing), so a sparse trunk is not seen through")
    p.add_argument("--float32", action="store_true", help="write float32 PLY (half the size)")
    g = p.add_argument_group("surveys", "a whole plot scanned from a grid of stations (st01.ply, st02.ply, ... "
                             "row by row, truth onto st01.ply); --seed, --leaves, --angular-step (default 0.17 "
                             "here), --tilt, --noise, --dropout and --float32 apply too")
    g.add_argument("--survey", metavar="COLSxROWS", help="simulate a survey: stations on this grid, e.g. 3x3")
    g.add_argument("--spacing", type=float, metavar="M", help="stations this far apart (default: 10)")
    g.add_argument("--trees", type=int, metavar="N", help="this many trees over the plot (default: about 220-290 per hectare)")
    g.add_argument("--slope", type=float, metavar="DEG", help="the ground rises by this angle (default: 2)")
    g.add_argument("--orchard", action="store_true",
                   help="one tree cloned on a 4 x 3 m grid, each copy turned about its vertical, instead of a forest")
    p.set_defaults(func=run)
    # What only a single-tree case takes, with its default: given with --survey, it is refused.
    _CASE_ONLY.update({dest: p.get_default(dest) for dest in (
        "stations", "height", "dbh", "orders", "bent", "lean", "ground", "ground_radius", "ground_front",
        "second_tree", "wind", "flutter", "mixed_pixels", "distance", "from_points", "splat")})


#: The single-tree flags (argparse dest: default), filled by `add`.
_CASE_ONLY: dict[str, Any] = {}
#: What only a survey takes.
_SURVEY_ONLY = ("spacing", "trees", "slope", "orchard")
#: SurveySpec's field names as the flags that set them, for its messages.
_SURVEY_FLAGS = {"grid": "--survey", "spacing_m": "--spacing", "n_trees": "--trees", "ground_slope_deg": "--slope",
                 "angular_step_deg": "--angular-step", "range_sigma_m": "--noise", "dropout": "--dropout",
                 "seed": "--seed", "tilt_deg": "--tilt"}


def _flag(dest: str) -> str:
    return "--" + dest.replace("_", "-")


def _grid(text: str) -> tuple[int, int]:
    """--survey COLSxROWS as (cols, rows)."""
    m = re.fullmatch(r"\s*(\d{1,4})\s*[xX]\s*(\d{1,4})\s*", text)
    if m is None:
        raise ConfigError(f"--survey: needs COLSxROWS, e.g. 3x3, got {shown(text)!r}")
    return int(m.group(1)), int(m.group(2))


def _survey_spec(args: argparse.Namespace) -> Any:
    """The SurveySpec the flags ask for; a flag that does not apply, or a bad value, is one ConfigError."""
    from treereg_core.simulate.survey import SurveySpec

    given = [_flag(d) for d, default in _CASE_ONLY.items() if getattr(args, d) != default]
    if given:
        raise ConfigError(f"{', '.join(given)}: only for a single-tree case, not with --survey")
    options: dict[str, Any] = {"seed": args.seed, "grid": _grid(args.survey), "leaves": args.leaves,
                               "orchard": args.orchard, "tilt_deg": args.tilt, "range_sigma_m": args.noise,
                               "dropout": args.dropout}
    if args.angular_step is not None:  # else the survey's own, coarser (~0.6 M points a station)
        options["angular_step_deg"] = angular_steps(args.angular_step)
    if args.spacing is not None:
        options["spacing_m"] = args.spacing
    if args.trees is not None:
        options["n_trees"] = (args.trees, args.trees)
    if args.slope is not None:
        options["ground_slope_deg"] = args.slope
    try:
        return SurveySpec(**options)
    except ConfigError as e:
        field, sep, rest = str(e).partition(": ")
        raise ConfigError(f"{_SURVEY_FLAGS.get(field, field)}{sep}{rest}") from None


def run_survey(args: argparse.Namespace) -> int:
    from treereg_core.simulate.survey import survey_paths, write_survey

    check_output_dir(args.out)
    spec = _survey_spec(args)
    paths = survey_paths(args.out, spec)  # checked before the (long) simulation
    check_distinct([(f"the survey's {p.name}", p) for p in paths], advice="choose another --out")
    for path in paths:
        check_output_file(path)
    truth, metrics = write_survey(spec, args.out, dtype="float32" if args.float32 else "float64",
                                  progress=ProgressBar("simulate"))
    for m in metrics:
        print(f"  {m.description:<24} {m.formatted()}")
    print(f"wrote {spec.n_stations} stations ({spec.names[0]} ... {spec.names[-1]}) and {truth.name} to {shown(args.out)}")
    return 0


def run(args: argparse.Namespace) -> int:
    if args.survey is not None:
        return run_survey(args)
    given = [_flag(d) for d in _SURVEY_ONLY if getattr(args, d) not in (None, False)]
    if given:
        raise ConfigError(f"{', '.join(given)}: only with --survey COLSxROWS")
    check_output_dir(args.out)
    spec = CaseSpec(
        seed=args.seed, n_stations=args.stations, angular_step_deg=angular_steps(args.angular_step or [0.1]),
        height_m=args.height, dbh_m=args.dbh, orders=args.orders, bent=args.bent, lean_deg=args.lean,
        leaves=args.leaves, ground=args.ground, ground_radius_m=args.ground_radius,
        ground_front_m=args.ground_front, second_tree=args.second_tree, tilt_deg=args.tilt,
        range_sigma_m=args.noise, dropout=args.dropout, station_distance_m=tuple(args.distance),
        from_points=args.from_points, splat_radius_m=args.splat, wind_m=args.wind, flutter=args.flutter,
        mixed_pixels=args.mixed_pixels,
    )
    paths = case_paths(args.out, spec.n_stations)  # checked before the (long) simulation
    check_distinct([(f"the case's {p.name}", p) for p in paths], [args.from_points] if args.from_points else [],
                   advice="choose another --out")
    for path in paths:
        check_output_file(path)
    case = spec.build(progress=ProgressBar("simulate"))
    truth = write_case(case, args.out, dtype="float32" if args.float32 else "float64")
    for m in case.metrics:
        print(f"  {m.description:<24} {m.formatted()}")
    print(f"wrote {', '.join(case.names)} and {truth.name} to {shown(args.out)}")
    return 0
