"""Exceptions treereg raises for input a user has to fix."""

from __future__ import annotations


class ScanError(ValueError):
    """A scan file (or array) cannot be used; the message names the file and the problem."""

    def __init__(self, source: str, problem: str) -> None:
        self.source = source
        self.problem = problem
        super().__init__(f"{source}: {problem}")


class ConfigError(ValueError):
    """A parameter file or value is invalid; the message names the key and the problem."""


class OutputError(ValueError):
    """A file or folder treereg was asked to write cannot be written there; the message names it and says why."""

    def __init__(self, path: str, problem: str) -> None:
        self.path = path
        self.problem = problem
        super().__init__(f"{path}: {problem}")


class ScanWarning(UserWarning):
    """Something in a scan file was repaired (e.g. rows with NaN dropped); the message says what."""
