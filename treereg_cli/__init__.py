"""The `treereg` command line: the one place that knows both treereg_core and treereg_viewer."""

from .main import main

__all__ = ["main"]
