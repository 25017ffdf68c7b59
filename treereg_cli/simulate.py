"""`treereg simulate`: a simulated case folder with ground truth."""

from __future__ import annotations

import argparse

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
    p.add_argument("--angular-step", nargs="+", type=float, default=[0.1], metavar=("H", "V"),
                   help="instrument angular steps in degrees, phi [varphi] (default: 0.1)")
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
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    check_output_dir(args.out)
    spec = CaseSpec(
        seed=args.seed, n_stations=args.stations, angular_step_deg=angular_steps(args.angular_step),
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
