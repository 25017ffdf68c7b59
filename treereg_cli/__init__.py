"""The `treereg` command line: the one place that knows both treereg_core and treereg_viewer."""

from __future__ import annotations

import os
import sys


def main(argv: list[str] | None = None) -> int:
    """The `treereg` command. The command modules (numpy, scipy, ...) are imported in here, so Ctrl-C
    while Python is still loading them is one line as well, not a traceback."""
    try:
        from .main import main as run
    except KeyboardInterrupt:
        print("treereg: interrupted (Ctrl-C) while starting; nothing was written", file=sys.stderr, flush=True)
        # Nothing to clean up yet; leave at once: an import cut short by Ctrl-C inside an extension
        # module can make Python end by re-raising the signal at exit (status -2 instead of 130).
        os._exit(130)
    return run(argv)


__all__ = ["main"]
