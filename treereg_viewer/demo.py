"""Finding and loading the bundled demo case (assets/) and a case's truth.json."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from treereg_core.errors import ConfigError
from treereg_core.io import read_scan
from treereg_core.scan import Scan
from treereg_core.transform_io import read_transforms

#: The repository's assets folder (the demo case lives there or in a folder below it).
ASSETS = Path(__file__).resolve().parent.parent / "assets"


def find_demo(assets: Path = ASSETS) -> Path:
    """The folder of the demo case: the first folder (assets/ itself, then its subfolders) with a truth.json."""
    for folder in [assets, *sorted(p for p in assets.glob("*") if p.is_dir())]:
        if (folder / "truth.json").is_file():
            return folder
    raise ConfigError(f"{assets}: no demo case (a folder with truth.json and its scans) found")


def read_truth(path: Path) -> dict[str, np.ndarray]:
    """{scan name: true T_ref_scan} from a truth.json (the reference included, as the identity)."""
    tf = read_transforms(path)
    return {name: np.asarray(tf.matrix(name)) for name in tf.names}


def truth_beside(scan_files: list[Path]) -> Path | None:
    """A truth.json in the folder of the first scan, if there is one."""
    cand = Path(scan_files[0]).resolve().parent / "truth.json" if scan_files else None
    return cand if cand is not None and cand.is_file() else None


def load_case(folder: Path, angular_step_deg: tuple[float, float] | None = None) -> tuple[list[Scan], dict[str, np.ndarray]]:
    """The scans of a case folder in truth.json's order (reference first), and the truth."""
    truth_path = folder / "truth.json"
    tf = read_transforms(truth_path)
    missing = [n for n in tf.names if not (folder / n).is_file()]
    if missing:
        raise ConfigError(f"{truth_path}: scans {missing} named there are not in {folder}")
    scans = [read_scan(folder / n, angular_step_deg=angular_step_deg) for n in tf.names]
    return scans, {name: np.asarray(tf.matrix(name)) for name in tf.names}
