"""What every command that registers shares: how it gets its parameters and reads its scans."""

from __future__ import annotations

import argparse
from pathlib import Path

from treereg_core import params as P
from treereg_core.errors import ConfigError
from treereg_core.io.scans import read_records, record_to_scan
from treereg_core.params import Params
from treereg_core.scan import Scan


def load_params(args: argparse.Namespace) -> Params:
    """The parameters of a run: a preset (default robust), a config file over it, then --angular-step."""
    base = P.PRESETS[args.preset] if getattr(args, "preset", None) else P.Params()
    if getattr(args, "config", None):
        base = P.load(args.config, base=base)
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


def add_param_args(p: argparse.ArgumentParser) -> None:
    """--config, --preset, --angular-step: how every command that registers gets its parameters."""
    p.add_argument("--config", help="parameter JSON file (as saved by the app or `treereg params`)")
    p.add_argument("--preset", choices=tuple(P.PRESETS), help="start from a preset (paper = the paper's literal settings)")
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


def read_scans(files: list[str], params: Params, scanner_positions: list[list[float]] | None = None) -> list[Scan]:
    """Read scan files (an E57 or PTX file may hold several scans) with the parameters' angular steps
    and returns; `scanner_positions` are given per scan, in order. Names must differ (they key the
    transforms)."""
    records = [(Path(f), r, n) for f in files for r, n in _records(f)]
    positions = [tuple(p) for p in (scanner_positions or [])]
    if positions and len(positions) != len(records):
        names = ", ".join(r.name for _, r, _ in records)
        raise ConfigError(f"--scanner-position was given {len(positions)} time(s) for {len(records)} scans ({names}); "
                          "give it once per scan, in order")
    scans = [record_to_scan(r, f if n == 1 else Path(f"{f}#{r.name}"), params.prepare.angular_step_deg,
                            params.prepare.returns, positions[k] if positions else None)
             for k, (f, r, n) in enumerate(records)]
    names = [s.name for s in scans]
    if len(set(names)) != len(names):
        raise ConfigError(f"scans must have distinct names (file base names, or E57 scan names), got {names}")
    return scans


def _records(path: str) -> list[tuple]:
    records = read_records(path)
    return [(r, len(records)) for r in records]
