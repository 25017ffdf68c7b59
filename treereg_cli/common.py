"""What every command that registers shares: how it gets its parameters and reads its scans."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

from treereg_core import params as P
from treereg_core.coarse.start import StartPose
from treereg_core.errors import ConfigError
from treereg_core.io.naming import scan_names
from treereg_core.io.start import read_start
from treereg_core.io.scans import MULTI_SCAN_EXTENSIONS, READ_EXTENSIONS, ScanRecord, extension, read_records, record_to_scan
from treereg_core.parallel import default_workers
from treereg_core.params import Params
from treereg_core.scan import Scan


#: How --set, and `treereg params --explain`, say the order in which a run's parameters are applied.
ORDER = ("--preset, then --config, then each --set in order, then the flags naming one parameter "
         "(--angular-step, --returns, --tree-at)")


def load_params(args: argparse.Namespace) -> Params:
    """The parameters of a run, applied in `ORDER`: a preset (default robust), a config file over it,
    each `--set section.field=value`, then the specific flags."""
    base = P.PRESETS[args.preset] if getattr(args, "preset", None) else P.Params()
    if getattr(args, "config", None):
        base = P.load(args.config, base=base)
    base = apply_sets(base, getattr(args, "set", None) or [])
    if getattr(args, "angular_step", None):
        base = base.with_value("prepare", "angular_step_deg", angular_steps(args.angular_step))
    if getattr(args, "returns", None):
        base = base.with_value("prepare", "returns", args.returns)
    if getattr(args, "tree_at", None):
        base = base.with_value("target", "tree_at", tuple(args.tree_at))
    return base


def angular_steps(values: list[float]) -> tuple[float, float]:
    """--angular-step H [V] as (phi, varphi), checked against the parameter's range."""
    if len(values) > 2:
        raise ConfigError(f"--angular-step takes one or two values (H [V]), got {len(values)}")
    try:
        return P.Params().with_value("prepare", "angular_step_deg", (values[0], values[-1])).prepare.angular_step_deg
    except ConfigError as e:
        raise ConfigError(f"--angular-step: {str(e).split(': ', 1)[1]}") from None


def set_value(text: str) -> Any:
    """The value of `--set key=VALUE`: JSON first (5, 0.02, true, null, [1, 1.6], "ramp"), else
    None for None, else the text itself (ramp; 1,1.6 for a tuple), which `with_value` then coerces."""
    try:
        return json.loads(text)
    except ValueError:
        return None if text.strip() == "None" else text


def apply_sets(params: Params, settings: list[str]) -> Params:
    """`params` with each `section.field=value` of `settings` applied in order, checked by
    `Params.with_value` (a bad key or value: one ConfigError naming it). A key that moved
    (`params.MOVED`) is taken at its new place."""
    for setting in settings:
        key, eq, text = setting.partition("=")
        section, dot, name = key.strip().partition(".")
        if not (eq and dot and section and name):
            raise ConfigError(f"--set {setting}: expected section.field=value (e.g. --set projection.theta_deg=5; "
                              "`treereg params --explain` lists every key)")
        section, name = P.moved(section, name)
        try:
            params = params.with_value(section, name, set_value(text))
        except ConfigError as e:
            raise ConfigError(f"--set {e}") from None
    return params


def add_set_arg(p: argparse.ArgumentParser) -> None:
    """--set section.field=value (repeatable): any parameter from the command line."""
    p.add_argument("--set", action="append", metavar="SECTION.FIELD=VALUE",
                   help="set one parameter (repeatable; `treereg params --explain` lists every key): numbers, "
                   "true/false, null, lists as 1,1.6 or JSON, words as they are; e.g. --set projection.theta_deg=5. "
                   f"Applied in this order: {ORDER}")


#: The most workers a run may be given (more than any machine's cores this runs on; a typo beyond).
MAX_WORKERS = 1024


def add_workers_arg(p: argparse.ArgumentParser, what: str, spare: int = 0) -> None:
    """--workers N: how many cores one registration uses (by default all but `spare`)."""
    default = "all cores" if not spare else f"all cores but {spare}, left to the browser"
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help=f"{what} (default: {default}, here {default_workers(spare)}; the results are the same for any number)")


def workers_of(args: argparse.Namespace) -> int | None:
    """--workers, checked (None: all cores)."""
    n = getattr(args, "workers", None)
    if n is not None and not 1 <= n <= MAX_WORKERS:
        raise ConfigError(f"--workers must be between 1 and {MAX_WORKERS}, got {n}")
    return n


def add_param_args(p: argparse.ArgumentParser) -> None:
    """--config, --preset, --set, --angular-step, ...: how every command that registers gets its parameters."""
    p.add_argument("--config", help="parameter JSON file (as saved by the app or `treereg params`)")
    p.add_argument("--preset", choices=tuple(P.PRESETS), help="start from a preset (paper = the paper's literal settings)")
    add_set_arg(p)
    p.add_argument("--angular-step", nargs="+", type=float, metavar=("H", "V"),
                   help="instrument angular steps in degrees (phi [varphi]); read off the file's grid (PTX, "
                   "structured E57) or estimated from the data when absent")
    p.add_argument("--returns", choices=("first", "all"),
                   help="several returns per pulse: keep the first (default) or all (files that number returns)")
    p.add_argument("--scanner-position", nargs=3, type=float, action="append", metavar=("X", "Y", "Z"),
                   help="the scanner's position in the file's coordinates, for scans not in their scanner's frame "
                   "(georeferenced or project coordinates); give it once per scan, in order")
    p.add_argument("--tree-at", nargs=2, type=float, metavar=("X", "Y"),
                   help="the target tree's stem in the first scan's frame (default: the stem the stations surround)")


def add_initial_arg(p: argparse.ArgumentParser) -> None:
    """--initial SCAN=FILE (repeatable): a start pose for a scan the coarse stage gets wrong."""
    p.add_argument("--initial", action="append", metavar="SCAN=FILE",
                   help="start scan SCAN (its name, as transforms.json names it) from the pose in FILE instead of "
                   "the coarse stage's: 4 rows of 4 numbers mapping it onto the reference (CloudCompare's matrix "
                   "layout, as --exports writes it) or a transforms.json with an entry for SCAN. The fine stage "
                   "and the verification run from there: a wrong start is refused like any pose (repeatable)")


def initial_files(args: argparse.Namespace) -> list[Path]:
    """The files --initial names (inputs: no output may be one of them)."""
    return [Path(text.partition("=")[2]) for text in getattr(args, "initial", None) or [] if "=" in text]


def read_initial(settings: list[str] | None) -> dict[str, StartPose]:
    """Each --initial SCAN=FILE read and checked (`io.start.read_start`): scan name -> StartPose. That
    the scans exist and none is the reference is checked when they are read (`Pipeline.start`)."""
    out: dict[str, StartPose] = {}
    for setting in settings or []:
        scan, eq, file = setting.partition("=")
        if not (eq and scan.strip() and file.strip()):
            raise ConfigError(f"--initial {setting}: expected SCAN=FILE (e.g. --initial scan2.ply=start.txt), the "
                              "scan's name as transforms.json names it")
        if scan in out:
            raise ConfigError(f"--initial {setting}: {scan!r} was given a start pose twice "
                              f"(also from {out[scan].source})")
        out[scan] = read_start(file, scan)
    return out


def read_scans(files: list[str], params: Params, scanner_positions: list[list[float]] | None = None) -> list[Scan]:
    """Read scan files (an E57 or PTX file may hold several scans) with the parameters' angular steps
    and returns; `scanner_positions` are given per scan, in order. Each scan is named by
    `io.naming.scan_names` (by folder where two files share a name: a/scan1.ply, b/scan1.ply), the
    name that keys the transforms."""
    records: list[tuple[str, ScanRecord, int]] = []  # (file, record, records in that file)
    for f in files:
        in_file = read_records(f)
        records += [(f, r, len(in_file)) for r in in_file]
    positions = [tuple(p) for p in (scanner_positions or [])]
    if positions and len(positions) != len(records):
        names = ", ".join(r.name for _, r, _ in records)
        raise ConfigError(f"--scanner-position was given {len(positions)} time(s) for {len(records)} scans ({names}); "
                          "give it once per scan, in order")
    names = scan_names([(f, r.name) for f, r, _ in records])
    # One file at a time: read side by side (tried for issue 20) they took 0.2 s less for three
    # stations of 300 k points and raised the run's peak memory by a tenth.
    return [record_to_scan(replace(r, name=name), Path(f) if n == 1 else Path(f"{f}#{r.name}"),
                           params.prepare.angular_step_deg, params.prepare.returns, positions[k] if positions else None)
            for k, ((f, r, n), name) in enumerate(zip(records, names))]


def scan_readers(files: list[str], params: Params,
                 scanner_positions: list[list[float]] | None = None) -> list[tuple[str, Callable[[], Scan]]] | None:
    """Each file's scan as (its name, a function that reads it), named as `read_scans` names them,
    nothing read yet: a survey reads its stations one at a time. None when a file may hold several
    scans (E57, PTX): their names and count are known only once read (`read_scans` then)."""
    if any(extension(f) in MULTI_SCAN_EXTENSIONS for f in files):
        return None
    for f in files:  # a missing file or unknown format is said now, not after the stations before it
        if not Path(f).is_file() or extension(f) not in READ_EXTENSIONS:
            read_records(f)  # raises the one-line ScanError naming it
    positions = [tuple(p) for p in (scanner_positions or [])]
    if positions and len(positions) != len(files):
        raise ConfigError(f"--scanner-position was given {len(positions)} time(s) for {len(files)} scans; "
                          "give it once per scan, in order")
    names = scan_names([(f, Path(f).name) for f in files])  # a single-scan file's record is named by its file

    def reader(k: int, f: str, name: str) -> Callable[[], Scan]:
        def read() -> Scan:
            (r,) = read_records(f)
            return record_to_scan(replace(r, name=name), Path(f), params.prepare.angular_step_deg,
                                  params.prepare.returns, positions[k] if positions else None)
        return read

    return [(name, reader(k, f, name)) for k, (f, name) in enumerate(zip(files, names))]
