"""The `treereg` command line: one module per subcommand, each with `add(subparsers)` and `run(args)`.

Errors a user can fix (bad scan files, bad parameters) print one line and exit with status 2.
"""

from __future__ import annotations

import argparse
import sys
import warnings

from treereg_core._version import __version__
from treereg_core.errors import ConfigError, ScanError

from . import batch, evaluate, params, register, simulate, view

#: The subcommands, in the order `treereg --help` lists them.
COMMANDS = (simulate, register, batch, evaluate, params, view)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="treereg",
        description="Marker-free registration of multi-station TLS scans of a single tree.",
    )
    parser.add_argument("--version", action="version", version=f"treereg {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS:
        command.add(sub)
    return parser


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings about the user's input (a step estimate to doubt, rows dropped) as one line each."""
    print(f"treereg: warning: {message}", file=file or sys.stderr)


def main(argv: list[str] | None = None) -> int:
    warnings.showwarning = _one_line_warning
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ScanError, ConfigError) as e:
        print(f"treereg: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
