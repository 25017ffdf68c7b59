"""Case folders: scans plus a truth.json with their true transforms (simulated cases, the demo).

`truth.json` is a transform file (`io.transforms`): reference scan1.ply, the true `T_ref_scan` of
every scan, and usually "angular_step_deg": [phi, varphi] (the simulated instrument's steps).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..scan import Scan
from .scans import read_scan
from .transforms import TransformFile, read_transforms

TRUTH_NAME = "truth.json"


@dataclass(frozen=True, eq=False)
class Case:
    """The scans of a case folder in truth order (reference first) and their true transforms."""

    folder: Path
    scans: tuple[Scan, ...]
    truth: dict[str, np.ndarray]
    truth_file: TransformFile


def read_truth(path: str | Path) -> dict[str, np.ndarray]:
    """{scan name: true T_ref_scan} from a truth.json (the reference included, as the identity)."""
    tf = read_transforms(path)
    return {name: np.asarray(tf.matrix(name)) for name in tf.names}


def truth_beside(scan_files: list[Path]) -> Path | None:
    """A truth.json in the folder of the first scan, if there is one."""
    cand = Path(scan_files[0]).resolve().parent / TRUTH_NAME if scan_files else None
    return cand if cand is not None and cand.is_file() else None


def read_case(folder: str | Path, angular_step_deg: tuple[float, float] | None = None) -> Case:
    """Read a case folder: its scans in truth.json's order, and the truth.

    The angular steps are `angular_step_deg` when given, else the ones truth.json records, else
    estimated from each scan.
    """
    d = Path(folder)
    truth_path = d / TRUTH_NAME
    tf = read_transforms(truth_path)
    missing = [n for n in tf.names if not (d / n).is_file()]
    if missing:
        raise ConfigError(f"{truth_path}: scans {missing} named there are not in {d}")
    step = angular_step_deg
    recorded = tf.extra.get("angular_step_deg")
    if step is None and recorded is not None:
        if not (isinstance(recorded, list) and len(recorded) == 2):
            raise ConfigError(f"{truth_path}: 'angular_step_deg' must be [phi, varphi], got {recorded!r}")
        step = (float(recorded[0]), float(recorded[1]))
    scans = tuple(read_scan(d / name, angular_step_deg=step) for name in tf.names)
    return Case(d, scans, {name: np.asarray(tf.matrix(name)) for name in tf.names}, tf)
