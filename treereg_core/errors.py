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
