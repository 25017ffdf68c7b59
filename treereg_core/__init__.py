"""treereg: marker-free registration of multi-station TLS scans of a single tree.

Pure computation, no UI. One import for scripts::

    from treereg_core import read_scan, register, Params
    reg = register([read_scan("scan1.ply"), read_scan("scan2.ply")], Params())
    reg.transforms["scan2.ply"]          # 4x4 T_ref_scan

A whole-plot survey (a grid of stations, not one tree they surround) is `register_survey`: each
station given as a Scan or a function that reads it, `Survey.transforms()` its result.

The stages (`STAGES`, in `treereg_core.stages`) run in a `Pipeline` that caches each one. The
names below are loaded on first use, so importing a submodule (or `treereg --help`) stays quick.
"""

from __future__ import annotations

import importlib
from typing import Any

from ._version import __version__

#: Public name -> the module that defines it.
_API: dict[str, str] = {
    "register": "pipeline", "Pipeline": "pipeline", "Registration": "pipeline",
    "Params": "params", "PRESETS": "params",
    "Scan": "scan", "read_scan": "io.scans", "write_scan": "io.scans",
    "Case": "io.cases", "read_case": "io.cases",
    "TransformFile": "io.transforms", "read_transforms": "io.transforms", "write_transforms": "io.transforms",
    "ScanError": "errors", "ConfigError": "errors",
    "Stage": "stage", "StageOutput": "stage", "Pair": "stage", "Skipped": "stage",
    "STAGES": "stages", "STAGE_NAMES": "stages",
    "PreparedScan": "prepare.ground", "MatchResult": "coarse.matching", "CoarseResult": "coarse.estimate",
    "SliceResult": "fine.slicing", "SliceArcs": "fine.arcs", "SectionsResult": "fine.sections",
    "FineResult": "fine.pose", "IcpResult": "evaluate.icp", "PairReport": "evaluate.report",
    "register_survey": "survey.register", "Survey": "survey.register",
}

__all__ = ["__version__", *_API]


def __getattr__(name: str) -> Any:
    if name not in _API:
        raise AttributeError(f"module 'treereg_core' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{_API[name]}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)
