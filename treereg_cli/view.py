"""`treereg view`: the browser app. The only command that imports treereg_viewer (and so viser),
when it runs."""

from __future__ import annotations

import argparse
from pathlib import Path

from treereg_core.demo import DEMO_DIR, demo_case
from treereg_core.io.cases import read_truth, truth_beside

from .common import add_param_args, load_params, read_scans


def add(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "view",
        help="open the browser app to step through the registration (the bundled demo without scans)",
        description="Serve treereg's browser app: every stage of the registration drawn, every parameter "
        "editable, exports as downloads. Without SCAN files it opens the bundled demo case.",
    )
    p.add_argument("scans", nargs="*", metavar="SCAN", help="scan files (first = reference); none = the demo")
    add_param_args(p)
    p.add_argument("--truth", help="truth.json with the true transforms (default: the one beside the scans, if any)")
    p.add_argument("--out", help="folder to also write exports to (besides the browser downloads)")
    p.add_argument("--port", type=int, default=8080, help="port (default 8080; 0 = any free port)")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1: this machine only)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    params = load_params(args)
    if args.scans:
        scans = read_scans(args.scans, params, args.scanner_position)
        truth_path = Path(args.truth) if args.truth else truth_beside([Path(f) for f in args.scans])
        truth = read_truth(truth_path) if truth_path else None
    else:
        print(f"treereg view: no scans given, opening the demo in {DEMO_DIR}", flush=True)
        case = demo_case(params.prepare.angular_step_deg)
        scans, truth = list(case.scans), case.truth
        if args.truth:
            truth = read_truth(Path(args.truth))
    # The app (viser, its web client) is imported only here: every other command stays light.
    from treereg_viewer.app import serve
    from treereg_viewer.controller import Controller

    serve(Controller(scans, params, truth), host=args.host, port=args.port,
          out_dir=Path(args.out) if args.out else None)
    return 0
