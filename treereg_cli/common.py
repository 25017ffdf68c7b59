"""What every command that registers shares: how it gets its parameters and reads its scans."""

from __future__ import annotations

import argparse

from treereg_core import params as P
from treereg_core.errors import ConfigError
from treereg_core.io.scans import read_scan
from treereg_core.params import Params
from treereg_core.scan import Scan


def load_params(args: argparse.Namespace) -> Params:
    """The parameters of a run: a preset (default robust), a config file over it, then --angular-step."""
    base = P.PRESETS[args.preset] if getattr(args, "preset", None) else P.Params()
    if getattr(args, "config", None):
        base = P.load(args.config, base=base)
    if getattr(args, "angular_step", None):
        base = base.with_value("prepare", "angular_step_deg", angular_steps(args.angular_step))
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
                   help="instrument angular steps in degrees (phi [varphi]); estimated from the data when absent")


def read_scans(files: list[str], params: Params) -> list[Scan]:
    """Read scan files with the parameters' angular steps; base names must differ (they key the transforms)."""
    scans = [read_scan(f, angular_step_deg=params.prepare.angular_step_deg) for f in files]
    names = [s.name for s in scans]
    if len(set(names)) != len(names):
        raise ConfigError(f"scan files must have distinct base names, got {names}")
    return scans
