"""Exceptions treereg raises for input a user has to fix.

Their messages quote file names and scan names, which come from outside: each message is shown
through `text.shown`, so a newline or an escape sequence in a name can neither forge another line
of output nor drive the terminal (the attributes keep the raw values, for code).
"""

from __future__ import annotations

from .text import shown


class ScanError(ValueError):
    """A scan file (or array) cannot be used; the message names the file and the problem."""

    def __init__(self, source: str, problem: str) -> None:
        self.source = source
        self.problem = problem
        super().__init__(shown(f"{source}: {problem}"))


class ConfigError(ValueError):
    """A parameter file or value is invalid; the message names the key and the problem."""

    def __str__(self) -> str:  # raised with a message built in many places, naming files: shown once here
        return shown(super().__str__())


class OutputError(ValueError):
    """A file or folder treereg was asked to write cannot be written there; the message names it and says why."""

    def __init__(self, path: str, problem: str) -> None:
        self.path = path
        self.problem = problem
        super().__init__(shown(f"{path}: {problem}"))


class ScanWarning(UserWarning):
    """Something in a scan file was repaired (e.g. rows with NaN dropped); the message says what."""
