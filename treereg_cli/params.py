"""`treereg params`: print or write the parameters."""

from __future__ import annotations

import argparse
import dataclasses
import json

from treereg_core import params as P
from treereg_core.io.atomic import check_output_file
from treereg_core.text import shown

from .common import ORDER, add_set_arg, load_params


def add(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "params",
        help="print or write the parameters (a preset, optionally over a config file) as JSON",
        description="Print the full parameter tree as JSON, with units and docs via --explain.",
    )
    p.add_argument("--preset", choices=tuple(P.PRESETS), help="start from a preset (default: robust)")
    p.add_argument("--config", help="parameter JSON file to apply over the preset")
    add_set_arg(p)
    p.add_argument("--out", help="write to this file instead of printing")
    p.add_argument("--explain", action="store_true", help="print every parameter with its unit and meaning")
    p.set_defaults(func=run)


def explain_header() -> str:
    """How --explain says every key is set from the command line."""
    return ("Set any parameter below with --set SECTION.FIELD=VALUE on register, view, batch and evaluate "
            "(repeatable; numbers, true/false, null, lists as 1,1.6), e.g. --set projection.theta_deg=5.\n"
            f"Order: {ORDER}.")


def explain_line(section: str, f: dataclasses.Field, value: object) -> str:
    """One parameter: its --set key, current value, unit, range, choices and meaning."""
    unit = f" ({f.metadata['unit']})" if f.metadata["unit"] else ""
    lo, hi = f.metadata["min"], f.metadata["max"]
    span = "" if lo is None and hi is None else \
        f" [{'' if lo is None else P.number_text(lo)} to {'' if hi is None else P.number_text(hi)}]"
    choices = f" {{{'|'.join(P.set_text(c) for c in f.metadata['choices'])}}}" if f.metadata["choices"] else ""
    most = f" (at most {f.metadata['max_len']} values)" if f.metadata["max_len"] else ""
    return f"  --set {section}.{f.name}={P.set_text(value)}{unit}{span}{most}{choices} — {f.metadata['doc']}"


def run(args: argparse.Namespace) -> int:
    if args.out:
        check_output_file(args.out, example="params.json")
    params = load_params(args)
    if args.explain:
        print(explain_header())
        for sec in P.SECTIONS:
            print(f"\n[{sec}]")
            for f in P.field_info(sec):
                print(explain_line(sec, f, getattr(getattr(params, sec), f.name)))
        return 0
    if args.out:
        P.save(params, args.out)
        print(f"wrote {shown(args.out)}")
    else:
        print(json.dumps(P.to_dict(params), indent=2))
    return 0
