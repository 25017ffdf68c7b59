"""`treereg register`: register scans onto the first and write the transform file."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from treereg_core.errors import ConfigError
from treereg_core.io.atomic import check_output_file
from treereg_core.io.transforms import export_paths, registration_file, write_exports, write_transforms
from treereg_core.pipeline import register

from .common import add_param_args, load_params, read_scans
from .progress import ProgressBar


def add(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "register",
        help="register scans onto the first one (coarse, then fine) and write transforms.json",
        description="Register every scan onto the first (the reference): rotating-projection coarse "
        "registration, then fine registration from fitted stem and branch sections.",
    )
    p.add_argument("scans", nargs="+", metavar="SCAN", help="scan files (first = reference): PLY, LAS/LAZ, XYZ/TXT/CSV, NPY/NPZ")
    p.add_argument("--out", default="transforms.json", help="transform file to write (default: transforms.json)")
    p.add_argument("--until", choices=("coarse", "fine"), default="fine", help="last stage to run (default: fine)")
    add_param_args(p)
    p.add_argument("--exports", action="store_true", help="also write CloudCompare and PDAL matrix files beside --out")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if len(args.scans) < 2:
        raise ConfigError("register needs at least two scans (the first is the reference)")
    out = Path(args.out)
    # Where the results go is checked before anything is read or computed.
    names = [Path(f).name for f in args.scans]
    for path in (export_paths(out.parent, names, out.name) if args.exports else [out]):
        check_output_file(path, example="transforms.json")
    params = load_params(args)
    scans = read_scans(args.scans, params)
    t0 = time.perf_counter()
    reg = register(scans, params, until=args.until, progress=ProgressBar("register"))
    seconds = time.perf_counter() - t0
    missing = [s.name for s in scans[1:] if s.name not in reg.transforms]
    if len(missing) == len(scans) - 1:
        print(f"treereg: registration failed: {reg.message}", file=sys.stderr)
        return 1
    metrics = reg.pipeline.pair_metrics()
    tf = registration_file(scans, reg.transforms, params, stage=args.until, metrics=metrics,
                           sources={s.name: str(Path(f).resolve()) for s, f in zip(scans, args.scans)}, seconds=seconds)
    written = write_exports(out.parent, tf, name=out.name) if args.exports else [write_transforms(out, tf)]
    for name, rows in metrics.items():
        print(f"\n{name} -> {scans[0].name}")
        for r in rows:
            v = r["value"]
            text = f"{v:.4g}" if isinstance(v, float) else str(v)
            print(f"  {r['stage']:<10} {r['metric']:<40} {text} {r['unit']}")
    print(f"\nwrote {', '.join(str(w) for w in written)} in {seconds:.1f} s")
    if missing:
        # The other pairs are written; say plainly which scans have no transform and why.
        print(f"treereg: not registered: {', '.join(missing)} ({reg.message})", file=sys.stderr)
        return 1
    return 0
