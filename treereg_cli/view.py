"""`treereg view`: the browser app. The only command that imports treereg_viewer (and so viser),
when it runs."""

from __future__ import annotations

import argparse
import errno
import math
import socket
import warnings
from pathlib import Path

import numpy as np

from treereg_core.demo import DEMO_DIR
from treereg_core.errors import ConfigError, ScanError
from treereg_core.io.atomic import check_output_dir
from treereg_core.io.cases import TRUTH_NAME, read_truth, truth_beside
from treereg_core.limits import MAX_UPLOAD_POINTS
from treereg_core.parallel import APP_SPARE_CORES
from treereg_core.params import Params
from treereg_core.scan import Scan
from treereg_core.survey.mode import is_survey

from .common import add_param_args, add_workers_arg, load_params, read_scans, workers_of

#: Largest scan file a browser may upload, unless --max-upload-mb says otherwise.
DEFAULT_MAX_UPLOAD_MB = 1024.0


def add(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "view",
        help="open the browser app to step through the registration (the bundled demo without scans)",
        description="Serve treereg's browser app: every stage of the registration drawn, every parameter "
        "editable, exports as downloads. Without SCAN files it opens the bundled demo case.",
    )
    p.add_argument("scans", nargs="*", metavar="SCAN", help="scan files (first = reference); none = the demo")
    add_param_args(p)
    add_workers_arg(p, "threads a registration uses", spare=APP_SPARE_CORES)
    p.add_argument("--truth", help="truth.json with the true transforms (default: the one beside the scans, if any; "
                   "one that cannot be read is a warning, and the app shows no errors against truth)")
    p.add_argument("--no-truth", action="store_true", help="do not look for a truth.json beside the scans")
    p.add_argument("--out", help="folder to also write exports to (besides the browser downloads)")
    p.add_argument("--port", type=int, default=8080, help="port (default 8080; 0 = any free port); a port in use is an error")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to bind (default 127.0.0.1: this machine only; anything else lets other "
                   "machines upload files and write exports, without a login)")
    p.add_argument("--projector", action="store_true",
                   help="open every tab in projector mode: text, 3-D labels, lines and points 1.6 times larger "
                   "for a room, and the arrow keys and Space step too (each tab can switch it in its Teach tab)")
    p.add_argument("--max-upload-mb", type=float, default=DEFAULT_MAX_UPLOAD_MB, metavar="MB",
                   help=f"largest scan file the browser may upload (default {DEFAULT_MAX_UPLOAD_MB:g} MB)")
    p.add_argument("--max-upload-points", type=int, default=MAX_UPLOAD_POINTS, metavar="N",
                   help=f"most points an uploaded scan may hold, as its header announces (lines for text), "
                   f"checked before any point is read: a compressed file can unpack to far more than its "
                   f"size suggests, and each point takes about 64 bytes of the server's memory while it is "
                   f"read and prepared (default {MAX_UPLOAD_POINTS:,})")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--survey", action="store_true",
                      help="open the survey view: the stations registered as a whole-plot survey (every station on "
                      "every stem it shares with its neighbours), their map, pairs and stems (the default for more "
                      "than 8 stations; survey.mode)")
    mode.add_argument("--one-tree", action="store_true",
                      help="step through the one-tree registration's stages, even with more than 8 stations (survey.mode)")
    p.set_defaults(func=run)


def check_address(host: str, port: int) -> None:
    """Refuse a port that is in use (viser would silently take the next one) or an address this
    machine cannot bind, before anything is read."""
    if not 0 <= port <= 65535:
        raise ConfigError(f"--port: {port} is not a port number (0 to 65535; 0 = any free port)")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as e:
        raise ConfigError(f"--host {host}: not an address of this machine ({e.strerror})") from None
    family, kind, proto, _, addr = infos[0]
    with socket.socket(family, kind, proto) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server binds
        try:
            s.bind(addr)
        except OSError as e:
            if port and e.errno == errno.EADDRINUSE:
                raise ConfigError(f"--port {port}: the port is in use (another treereg view?); choose another "
                                  "port, or --port 0 for any free one") from None
            raise ConfigError(f"--host {host}: cannot listen there ({(e.strerror or str(e)).lower()})") from None


def run(args: argparse.Namespace) -> int:
    # Everything that can be wrong with the command line is checked before any scan is read.
    check_address(args.host, args.port)
    out_dir = check_output_dir(args.out) if args.out else None
    if not (math.isfinite(args.max_upload_mb) and args.max_upload_mb > 0):
        raise ConfigError(f"--max-upload-mb: {args.max_upload_mb:g} must be a positive, finite size in MB")
    if args.max_upload_points < 1:
        raise ConfigError(f"--max-upload-points: {args.max_upload_points} must be a positive number of points")
    params = load_params(args)
    if args.survey or args.one_tree:
        params = params.with_value("survey", "mode", "survey" if args.survey else "one_tree")
    workers = workers_of(args)
    scans, truth = scans_and_truth(args, params)
    # The app (viser, its web client) is imported only here: every other command stays light.
    from treereg_viewer.app import serve
    from treereg_viewer.controller import Controller
    from treereg_viewer.export import check_not_inputs, file_names

    if out_dir is not None:  # no export may replace a file the app reads (a scan named merged.ply there)
        check_not_inputs(out_dir, file_names(s.name for s in scans),
                         [*args.scans, *(f for f in (args.config, args.truth) if f)])

    survey = is_survey(len(scans), params)
    if survey:
        print(f"treereg view: {len(scans)} stations: the survey view (--one-tree steps through one tree's stages)",
              flush=True)
    serve(Controller(scans, params, truth, workers=workers, survey=survey), host=args.host, port=args.port, out_dir=out_dir,
          max_upload_bytes=int(args.max_upload_mb * 1e6), max_upload_points=args.max_upload_points,
          projector=args.projector)
    return 0


def scans_and_truth(args: argparse.Namespace, params: Params) -> tuple[list[Scan], dict[str, np.ndarray] | None]:
    """The scans the app opens (the demo's without SCAN files) and their truth, if any."""
    if args.truth and args.no_truth:
        raise ConfigError("--truth and --no-truth: give one of them")
    files = list(args.scans)
    if not files:
        # The demo's files read as `treereg register` reads any files (the angular steps estimated
        # from each scan, or --angular-step): the app and the command line give the same transforms.
        files = [str(DEMO_DIR / name) for name in read_truth(DEMO_DIR / TRUTH_NAME)]
        print(f"treereg view: no scans given, opening the demo in {DEMO_DIR}", flush=True)
    scans = read_scans(files, params, args.scanner_position)
    if args.truth:  # asked for: it must be read
        return scans, read_truth(Path(args.truth))
    if args.no_truth:
        return scans, None
    return scans, _truth_beside([Path(f) for f in files], [s.name for s in scans])


def _truth_beside(files: list[Path], names: list[str]) -> dict[str, np.ndarray] | None:
    """The truth.json beside the scans, if there is one the app can use: one it cannot read, or one
    that names none of these scans, is a warning (the app then shows no errors against truth), never
    a reason not to start."""
    path = truth_beside(files)
    if path is None:
        return None
    try:
        truth = read_truth(path)
    except (ConfigError, ScanError) as e:
        warnings.warn(f"{e}: not read as the truth of these scans (the app shows no errors against truth; "
                      "--truth FILE gives one, --no-truth stops looking)", UserWarning, stacklevel=2)
        return None
    if not any(n in truth for n in names):
        warnings.warn(f"{path}: names none of these scans, so it is not their truth (the app shows no errors "
                      "against truth)", UserWarning, stacklevel=2)
        return None
    return truth
