"""Exports of the latest result: the same files `treereg register` writes, plus the merged cloud.

`export_bundle(snapshot)` makes every file in memory (for browser downloads); `write_bundle` puts
them in a folder (`treereg view --out DIR`). The file contents come from treereg_core.io (the
same builder of transforms.json as `treereg register`), so the app and the command line export identical files.
"""

from __future__ import annotations

import io as _io
import json
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from treereg_core import params as P
from treereg_core.io import atomic
from treereg_core.io.atomic import write_bytes_atomic
from treereg_core.io.merged import write_merged
from treereg_core.io.transforms import TransformFile, registration_file, write_exports
from treereg_core.verify.report import quality_report

from .controller import Snapshot


class ExportError(ValueError):
    """Nothing (valid) to export yet; the message says what to do."""


@dataclass(frozen=True)
class ExportBundle:
    """All export files, by file name, and what they were made from."""

    stage: str  # "fine" or "coarse": which stage's transforms
    transforms: dict[str, np.ndarray]
    files: dict[str, bytes]


def transform_file(snap: Snapshot, keep_unverified: bool = False) -> tuple[TransformFile, str]:
    """The TransformFile of the snapshot's transforms, as `treereg register` writes it: the verified
    scans in "transforms", best guesses under "unverified" (or in "transforms" too with
    `keep_unverified`), the evidence under "quality"."""
    if len(snap.scans) < 2:
        raise ExportError("Nothing to export: registration needs at least two scans.")
    stage = "fine" if snap.output("graph") is not None else "coarse" if snap.output("coarse") is not None else None
    if stage is None or len(snap.transforms) < 2:
        raise ExportError("Nothing to export yet: no scan has been registered (run the pipeline up to the "
                          "coarse stage at least; a failed pair has no transform).")
    transforms = {name: np.asarray(T, dtype=np.float64) for name, T in snap.transforms.items()}
    sources = {s.name: str(s.source.resolve()) for s in snap.scans if s.source is not None and s.source.is_absolute()}
    tf = registration_file(snap.scans, transforms, snap.params, stage=stage, metrics=dict(snap.pair_metrics),
                           verdicts=dict(snap.verdicts), quality=quality_report(snap.scans, snap.pairs, snap.outputs),
                           keep_unverified=keep_unverified, sources=sources or None)
    return tf, stage


def export_bundle(snap: Snapshot, cloud_format: str = "ply", keep_unverified: bool = False) -> ExportBundle:
    """transforms.json (with the parameters used and per-pair metrics), CloudCompare and PDAL
    matrices per scan (`transforms.<scan>.cloudcompare.txt`, ...), params.json, and the merged
    registered cloud (`merged.<ply|las>`, every scan's points as loaded, ground included, each
    tagged with its scan's number: PLY `scan_id`, LAS `point_source_id`)."""
    if cloud_format not in ("ply", "las", "laz"):
        raise ExportError(f"merged cloud format must be ply, las or laz, not {cloud_format!r}")
    tf, stage = transform_file(snap, keep_unverified)
    files: dict[str, bytes] = {}
    with tempfile.TemporaryDirectory(prefix="treereg-export-") as tmp:
        for path in write_exports(tmp, tf):
            files[path.name] = path.read_bytes()
        cloud = write_merged(Path(tmp) / f"merged.{cloud_format}", snap.scans, tf.transforms)
        files[cloud.name] = cloud.read_bytes()
    files["params.json"] = (json.dumps(P.to_dict(snap.params), indent=2) + "\n").encode()
    return ExportBundle(stage, dict(tf.transforms), files)


def write_bundle(bundle: ExportBundle, out_dir: Path) -> list[Path]:
    """Write every file of `bundle` into `out_dir`, as one batch: all of them, or (on an error) none
    replace what was there."""
    with atomic.batch():
        return [write_bytes_atomic(Path(out_dir) / name, data) for name, data in bundle.files.items()]


def zip_bundle(bundle: ExportBundle) -> bytes:
    """All files in one zip (one browser download instead of many)."""
    buf = _io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as z:
        for name, data in bundle.files.items():
            z.writestr(name, data)
    return buf.getvalue()

