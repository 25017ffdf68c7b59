"""The `treereg` command line. Each subcommand: a `_add_<name>` parser builder and a `_run_<name>`.

Errors a user can fix (bad scan files, bad parameters) print one line and exit with status 2.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Callable

import numpy as np

from . import __version__
from .errors import ConfigError, ScanError


class ProgressBar:
    """A one-line text progress bar on stderr; usable as a `Progress` callback."""

    def __init__(self, label: str, stream=None, width: int = 30) -> None:
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.width = width
        self.t0 = time.perf_counter()
        self._last = -1.0

    def __call__(self, fraction: float, text: str = "") -> None:
        fraction = min(max(float(fraction), 0.0), 1.0)
        now = time.perf_counter()
        if fraction < 1.0 and now - self._last < 0.1:
            return
        self._last = now
        n = int(round(fraction * self.width))
        bar = "#" * n + "-" * (self.width - n)
        line = f"\r{self.label} [{bar}] {fraction * 100:5.1f}% {now - self.t0:6.1f}s {text[:40]:<40}"
        self.stream.write(line)
        if fraction >= 1.0:
            self.stream.write("\n")
        self.stream.flush()


Builder = Callable[[argparse._SubParsersAction], None]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="treereg",
        description="Marker-free registration of multi-station TLS scans of a single tree.",
    )
    parser.add_argument("--version", action="version", version=f"treereg {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in _BUILDERS:
        add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ScanError, ConfigError) as e:
        print(f"treereg: error: {e}", file=sys.stderr)
        return 2


_BUILDERS: list[Builder] = []


# ---- simulate -----------------------------------------------------------------------------
def _add_simulate(sub: argparse._SubParsersAction) -> None:
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
    p.set_defaults(func=_run_simulate)


def _run_simulate(args: argparse.Namespace) -> int:
    from .simulate import CaseSpec, write_case

    steps = args.angular_step
    if len(steps) > 2:
        raise ConfigError(f"--angular-step takes one or two values (H [V]), got {len(steps)}")
    spec = CaseSpec(
        seed=args.seed, n_stations=args.stations, angular_step_deg=(steps[0], steps[-1]),
        height_m=args.height, dbh_m=args.dbh, orders=args.orders, bent=args.bent, lean_deg=args.lean,
        leaves=args.leaves, ground=args.ground, ground_radius_m=args.ground_radius,
        ground_front_m=args.ground_front, second_tree=args.second_tree, tilt_deg=args.tilt,
        range_sigma_m=args.noise, dropout=args.dropout, station_distance_m=tuple(args.distance),
        from_points=args.from_points, splat_radius_m=args.splat,
    )
    case = spec.build(progress=ProgressBar("simulate"))
    truth = write_case(case, args.out, dtype="float32" if args.float32 else "float64")
    for m in case.metrics:
        print(f"  {m.description:<24} {m.formatted()}")
    print(f"wrote {', '.join(case.names)} and {truth.name} to {args.out}")
    return 0


_BUILDERS.append(_add_simulate)


# ---- register / evaluate ------------------------------------------------------------------
def _load_params(args: argparse.Namespace):
    """The parameters of a run: a preset (default robust), a config file over it, then --angular-step."""
    from . import params as P

    base = P.PRESETS[args.preset] if getattr(args, "preset", None) else P.Params()
    if getattr(args, "config", None):
        base = P.load(args.config, base=base)
    if getattr(args, "angular_step", None):
        steps = args.angular_step
        if len(steps) > 2:
            raise ConfigError(f"--angular-step takes one or two values (H [V]), got {len(steps)}")
        base = base.with_value("prepare", "angular_step_deg", (steps[0], steps[-1]))
    return base


def _add_param_args(p: argparse.ArgumentParser) -> None:
    """--config, --preset, --angular-step: how every command that registers gets its parameters."""
    p.add_argument("--config", help="parameter JSON file (as saved by the app or `treereg params`)")
    p.add_argument("--preset", choices=("robust", "paper"), help="start from a preset (paper = the paper's literal settings)")
    p.add_argument("--angular-step", nargs="+", type=float, metavar=("H", "V"),
                   help="instrument angular steps in degrees (phi [varphi]); estimated from the data when absent")


def _read_scans(files: list[str], params) -> list:
    """Read scan files with the parameters' angular steps; base names must differ (they key the transforms)."""
    from .io import read_scan

    scans = [read_scan(f, angular_step_deg=params.prepare.angular_step_deg) for f in files]
    names = [s.name for s in scans]
    if len(set(names)) != len(names):
        raise ConfigError(f"scan files must have distinct base names, got {names}")
    return scans


def _add_register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "register",
        help="register scans onto the first one (coarse, then fine) and write transforms.json",
        description="Register every scan onto the first (the reference): rotating-projection coarse "
        "registration, then fine registration from fitted stem and branch sections.",
    )
    p.add_argument("scans", nargs="+", metavar="SCAN", help="scan files (first = reference): PLY, LAS/LAZ, XYZ/TXT/CSV, NPY/NPZ")
    p.add_argument("--out", default="transforms.json", help="transform file to write (default: transforms.json)")
    p.add_argument("--until", choices=("coarse", "fine"), default="fine", help="last stage to run (default: fine)")
    _add_param_args(p)
    p.add_argument("--exports", action="store_true", help="also write CloudCompare and PDAL matrix files beside --out")
    p.set_defaults(func=_run_register)


def _run_register(args: argparse.Namespace) -> int:
    from pathlib import Path

    from .params import to_dict
    from .pipeline import register
    from .transform_io import TransformFile, write_exports, write_transforms

    if len(args.scans) < 2:
        raise ConfigError("register needs at least two scans (the first is the reference)")
    params = _load_params(args)
    scans = _read_scans(args.scans, params)
    bar = ProgressBar("register")
    t0 = time.perf_counter()
    reg = register(scans, params, until=args.until, progress=bar)
    seconds = time.perf_counter() - t0
    missing = [s.name for s in scans[1:] if s.name not in reg.transforms]
    if len(missing) == len(scans) - 1:
        print(f"treereg: registration failed: {reg.message}", file=sys.stderr)
        return 1
    extra_missing = {"unregistered": missing} if missing else {}
    tf = TransformFile(
        reference=scans[0].name,
        transforms=reg.transforms,
        params=to_dict(params),
        extra={
            "stage": args.until,
            "seconds": round(seconds, 3),
            "angular_step_deg": {s.name: list(s.angular_step_deg) for s in scans},
            "sources": {s.name: str(Path(f).resolve()) for s, f in zip(scans, args.scans)},
            "metrics": reg.pipeline.pair_metrics(),
            **extra_missing,
        },
    )
    out = Path(args.out)
    if args.exports:
        written = write_exports(out.parent, tf, name=out.name)
    else:
        write_transforms(out, tf)
        written = [out]
    for name, rows in reg.pipeline.pair_metrics().items():
        print(f"\n{name} -> {scans[0].name}")
        for r in rows:
            v = r["value"]
            print(f"  {r['stage']:<10} {r['metric']:<40} {v:.4g} {r['unit']}" if isinstance(v, float)
                  else f"  {r['stage']:<10} {r['metric']:<40} {v} {r['unit']}")
    print(f"\nwrote {', '.join(str(w) for w in written)} in {seconds:.1f} s")
    if missing:
        # The other pairs are written; say plainly which scans have no transform and why.
        print(f"treereg: not registered: {', '.join(missing)} ({reg.message})", file=sys.stderr)
        return 1
    return 0


_BUILDERS.append(_add_register)


# ---- params -------------------------------------------------------------------------------
def _add_params(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "params",
        help="print or write the parameters (a preset, optionally over a config file) as JSON",
        description="Print the full parameter tree as JSON, with units and docs via --explain.",
    )
    p.add_argument("--preset", choices=("robust", "paper"), help="start from a preset (default: robust)")
    p.add_argument("--config", help="parameter JSON file to apply over the preset")
    p.add_argument("--out", help="write to this file instead of printing")
    p.add_argument("--explain", action="store_true", help="print every parameter with its unit and meaning")
    p.set_defaults(func=_run_params)


def _run_params(args: argparse.Namespace) -> int:
    import json

    from . import params as P

    params = _load_params(args)
    if args.explain:
        for sec in P.SECTIONS:
            print(f"[{sec}]")
            for f in P.field_info(sec):
                unit = f" ({f.metadata['unit']})" if f.metadata["unit"] else ""
                print(f"  {f.name} = {getattr(getattr(params, sec), f.name)!r}{unit}: {f.metadata['doc']}")
        return 0
    if args.out:
        P.save(params, args.out)
        print(f"wrote {args.out}")
    else:
        print(json.dumps(P.to_dict(params), indent=2))
    return 0


_BUILDERS.append(_add_params)


# ---- view (the browser app; treereg_viewer is imported only when the command runs) ----------
def _add_view(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "view",
        help="open the browser app to step through the registration (the bundled demo without scans)",
        description="Serve treereg's browser app: every stage of the registration drawn, every parameter "
        "editable, exports as downloads. Without SCAN files it opens the demo case in assets/.",
    )
    p.add_argument("scans", nargs="*", metavar="SCAN", help="scan files (first = reference); none = the demo")
    _add_param_args(p)
    p.add_argument("--truth", help="truth.json with the true transforms (default: the one beside the scans, if any)")
    p.add_argument("--out", help="folder to also write exports to (besides the browser downloads)")
    p.add_argument("--port", type=int, default=8080, help="port (default 8080; 0 = any free port)")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1: this machine only)")
    p.set_defaults(func=_run_view)


def _run_view(args: argparse.Namespace) -> int:
    from pathlib import Path

    from treereg_viewer.app import serve
    from treereg_viewer.controller import Controller
    from treereg_viewer.demo import find_demo, load_case, read_truth, truth_beside

    params = _load_params(args)
    if args.scans:
        scans = _read_scans(args.scans, params)
        truth_path = Path(args.truth) if args.truth else truth_beside([Path(f) for f in args.scans])
        truth = read_truth(truth_path) if truth_path else None
    else:
        folder = find_demo()
        print(f"treereg view: no scans given, opening the demo in {folder}", flush=True)
        scans, truth = load_case(folder, angular_step_deg=params.prepare.angular_step_deg)
        if args.truth:
            truth = read_truth(Path(args.truth))
    serve(Controller(scans, params, truth), host=args.host, port=args.port,
          out_dir=Path(args.out) if args.out else None)
    return 0


_BUILDERS.append(_add_view)

# ---- evaluate -----------------------------------------------------------------------------
def _add_evaluate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "evaluate",
        help="print the evaluation table of a transform file (paper's branch model; errors against truth)",
        description="Evaluate every transform of a transform file: the paper's branch-centre error "
        "(eq. 8) per branch and overall and, with --truth, the rotation error and mean displacement "
        "of each scan's points against the true transform.",
    )
    p.add_argument("transforms", help="transforms.json written by `treereg register` or the app")
    p.add_argument("--truth", help="truth.json of a simulated case (same scan names)")
    p.add_argument("--scan-dir", help="folder holding the scans (default: the paths recorded in the "
                   "transform file, else the transform file's folder)")
    p.add_argument("--branches", action="store_true", help="also print the per-branch table (paper Figs. 13-14)")
    p.set_defaults(func=_run_evaluate)


def _scan_path(name: str, tf, args: argparse.Namespace):
    from pathlib import Path

    if args.scan_dir:
        return Path(args.scan_dir) / name
    recorded = (tf.extra.get("sources") or {}).get(name)
    if recorded and Path(recorded).exists():
        return Path(recorded)
    return Path(args.transforms).resolve().parent / name


def _run_evaluate(args: argparse.Namespace) -> int:
    from . import params as P
    from .evaluation import evaluate_pair, find_branches
    from .ground import prepare_scan
    from .io import read_scan
    from .rigid import invert
    from .transform_io import read_transforms

    tf = read_transforms(args.transforms)
    truth = read_transforms(args.truth) if args.truth else None
    params = P.from_dict(tf.params, source=f"{args.transforms}: params") if tf.params else P.Params()
    steps = tf.extra.get("angular_step_deg") or {}
    names = tf.names
    if truth is not None:
        missing = [n for n in names if n not in truth.names]
        if missing:
            raise ConfigError(f"{args.truth}: no true transform for {', '.join(missing)}")

    def load(name: str):
        step = steps.get(name) if isinstance(steps, dict) else None
        scan = read_scan(_scan_path(name, tf, args), angular_step_deg=tuple(step) if step else params.prepare.angular_step_deg, name=name)
        return prepare_scan(scan, params.prepare).scan

    ref = load(names[0])
    branches = find_branches(ref, params.evaluation)
    header = "| pair | branches | layer pairs | d (m), eq. 8 |"
    rule = "|---|---|---|---|"
    if truth is not None:
        header += " rotation error (deg) | mean displacement (m) |"
        rule += "---|---|"
    rows, branch_rows = [header, rule], []
    bar = ProgressBar("evaluate")
    for k, name in enumerate(names[1:]):
        bar(k / max(len(names) - 1, 1), name)
        tgt = load(name)
        T_true = None
        if truth is not None:
            # Truth files map onto their own reference; express the truth relative to ours.
            T_true = invert(truth.matrix(names[0])) @ truth.matrix(name)
        ev = evaluate_pair(ref, tgt, tf.matrix(name), params.evaluation, T_true, branches)
        d = f"{ev.mean_distance_m:.4f}" if ev.ok else f"n/a ({ev.message})"
        row = f"| {name} -> {names[0]} | {len(ev.branches)} | {ev.n_pairs} | {d} |"
        if truth is not None:
            row += f" {ev.rotation_error_deg:.3f} | {ev.mean_displacement_m:.4f} |"
        rows.append(row)
        for b in ev.branches:
            ds = ", ".join(f"{x:.4f}" for x in b.distances_m)
            branch_rows.append(f"| {name} -> {names[0]} | {b.index} | {b.height_m:.2f} | {b.radius_m:.3f} | {ds} | {np.mean(b.distances_m):.4f} |")
    bar(1.0, "done")
    print("\n".join(rows))
    if args.branches and branch_rows:
        print("\n| pair | branch | height (m) | radius (m) | d1..dn (m) | mean d (m) |\n|---|---|---|---|---|---|")
        print("\n".join(branch_rows))
    return 0


_BUILDERS.append(_add_evaluate)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
