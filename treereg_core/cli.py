"""The `treereg` command line. Each subcommand: a `_add_<name>` parser builder and a `_run_<name>`.

Errors a user can fix (bad scan files, bad parameters) print one line and exit with status 2.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Callable

from . import __version__
from .errors import ConfigError, ScanError


class ProgressBar:
    """A one-line text progress bar on stderr; usable as a `Progress` callback."""

    def __init__(self, label: str, stream=None, width: int = 30) -> None:
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.width = width
        self.t0 = time.perf_counter()
        self._last = -1.0

    def __call__(self, fraction: float, text: str = "") -> None:
        fraction = min(max(float(fraction), 0.0), 1.0)
        now = time.perf_counter()
        if fraction < 1.0 and now - self._last < 0.1:
            return
        self._last = now
        n = int(round(fraction * self.width))
        bar = "#" * n + "-" * (self.width - n)
        line = f"\r{self.label} [{bar}] {fraction * 100:5.1f}% {now - self.t0:6.1f}s {text[:40]:<40}"
        self.stream.write(line)
        if fraction >= 1.0:
            self.stream.write("\n")
        self.stream.flush()


Builder = Callable[[argparse._SubParsersAction], None]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="treereg",
        description="Marker-free registration of multi-station TLS scans of a single tree.",
    )
    parser.add_argument("--version", action="version", version=f"treereg {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in _BUILDERS:
        add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ScanError, ConfigError) as e:
        print(f"treereg: error: {e}", file=sys.stderr)
        return 2


_BUILDERS: list[Builder] = []


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
