"""The `treereg` command line: one module per subcommand, each with `add(subparsers)` and `run(args)`.

Errors a user can fix (bad scan files, bad parameters, an output that cannot be written) print one
line and exit with status 2; Ctrl-C prints one line and exits with status 130, leaving every file
as it was (all writes are atomic). Warnings about input (rows dropped) are printed as sentences.
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings

from treereg_core._version import __version__
from treereg_core.errors import ConfigError, OutputError, ScanError
from treereg_core.io.scans import ScanWarning

from . import batch, evaluate, params, progress, register, simulate, view

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


def say(text: str) -> None:
    """One line on stderr, starting on a fresh line (a progress bar may be half drawn)."""
    progress.end_line()
    print(f"treereg: {text}", file=sys.stderr, flush=True)


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """What treereg says about its input is a sentence; anything else keeps Python's format."""
    if issubclass(category, ScanWarning):
        say(f"warning: {message}")
    else:
        progress.end_line()
        sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    with warnings.catch_warnings():
        warnings.simplefilter("always", ScanWarning)  # one per file, not one per line of code
        warnings.showwarning = _show_warning
        try:
            return int(args.func(args) or 0)
        except (ScanError, ConfigError, OutputError) as e:
            say(f"error: {e}")
            return 2
        except KeyboardInterrupt:
            say("interrupted (Ctrl-C); no file was left half-written or replaced by a partial result")
            return 130
        except BrokenPipeError:  # `treereg params | head`: the reader has all it wanted
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # nothing left to flush at exit
            return 141  # as a shell reports a command ended by SIGPIPE


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
