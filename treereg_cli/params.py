"""`treereg params`: print or write the parameters."""

from __future__ import annotations

import argparse
import json

from treereg_core import params as P
from treereg_core.io.atomic import check_output_file

from .common import load_params


def add(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "params",
        help="print or write the parameters (a preset, optionally over a config file) as JSON",
        description="Print the full parameter tree as JSON, with units and docs via --explain.",
    )
    p.add_argument("--preset", choices=tuple(P.PRESETS), help="start from a preset (default: robust)")
    p.add_argument("--config", help="parameter JSON file to apply over the preset")
    p.add_argument("--out", help="write to this file instead of printing")
    p.add_argument("--explain", action="store_true", help="print every parameter with its unit and meaning")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.out:
        check_output_file(args.out, example="params.json")
    params = load_params(args)
    if args.explain:
        for sec in P.SECTIONS:
            print(f"[{sec}]")
            for f in P.field_info(sec):
                unit = f" ({f.metadata['unit']})" if f.metadata["unit"] else ""
                lo, hi = f.metadata["min"], f.metadata["max"]
                span = "" if lo is None and hi is None else f" [{'' if lo is None else f'{lo:g}'} to {'' if hi is None else f'{hi:g}'}]"
                print(f"  {f.name} = {getattr(getattr(params, sec), f.name)!r}{unit}{span}: {f.metadata['doc']}")
        return 0
    if args.out:
        P.save(params, args.out)
        print(f"wrote {args.out}")
    else:
        print(json.dumps(P.to_dict(params), indent=2))
    return 0
