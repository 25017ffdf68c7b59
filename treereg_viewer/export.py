"""Exports of the latest result: the same files `treereg register` writes, plus the merged cloud.

`export_bundle(snapshot)` makes every file in memory (for browser downloads); `write_bundle` puts
them in a folder (`treereg view --out DIR`), never over one of the files the app reads (a scan
named merged.ply in that folder): `check_not_inputs` refuses, at start and at each export. The file contents come from treereg_core.io (the
same builder of transforms.json as `treereg register`), so the app and the command line export identical files.
"""

from __future__ import annotations

import io as _io
import json
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from treereg_core import params as P
from treereg_core.errors import OutputError
from treereg_core.io import atomic
from treereg_core.io.atomic import check_distinct, write_bytes_atomic
from treereg_core.io.merged import write_merged
from treereg_core.io.naming import file_safe, file_stem
from treereg_core.io.start import STARTS_KEY, starts_doc
from treereg_core.io.transforms import TransformFile, export_paths, registration_file, write_exports
from treereg_core.verify.report import quality_report

from .controller import Snapshot


#: The merged cloud's formats and the parameter file's name, as the exports name them.
CLOUD_FORMATS = ("ply", "las", "laz")
PARAMS_NAME = "params.json"
#: The start poses given by hand (Align), as a transforms.json that `treereg register --initial
#: SCAN=starts.json` reads back: {"reference", "transforms": {scan: 4x4}, "sources": {scan: where from}}.
STARTS_NAME = "starts.json"
#: What to do when an export would replace an input (said at start and in the app).
CLASH_ADVICE = "start treereg view with another --out folder"


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
    if cloud_format not in CLOUD_FORMATS:
        raise ExportError(f"merged cloud format must be ply, las or laz, not {cloud_format!r}")
    tf, stage = transform_file(snap, keep_unverified)
    files: dict[str, bytes] = {}
    with tempfile.TemporaryDirectory(prefix="treereg-export-") as tmp:
        for path in write_exports(tmp, tf):
            files[path.name] = path.read_bytes()
        cloud = write_merged(Path(tmp) / f"merged.{cloud_format}", snap.scans, tf.transforms)
        files[cloud.name] = cloud.read_bytes()
    files[PARAMS_NAME] = params_file(snap.params, snap)
    if snap.starts:
        files[STARTS_NAME] = starts_file(snap)
    return ExportBundle(stage, dict(tf.transforms), files)


def starts_file(snap: Snapshot) -> bytes:
    """The start poses in force (`Snapshot.starts`) as a transforms.json a start file may be
    (`treereg_core.io.start`): each maps its scan as its file gives it onto the reference."""
    return (json.dumps(starts_doc(snap.scans[0].name, snap.starts), indent=2) + "\n").encode()


def params_file(params: P.Params, snap: Snapshot) -> bytes:
    """params.json: the parameters, and beside them (top-level "starts", `io.start.STARTS_KEY`) the start
    poses in force, so loading the file restores both (`P.from_dict` skips them; `register --initial
    SCAN=params.json` reads them)."""
    doc: dict[str, object] = dict(P.to_dict(params))
    if snap.starts and snap.scans:
        doc[STARTS_KEY] = starts_doc(snap.scans[0].name, snap.starts)
    return (json.dumps(doc, indent=2) + "\n").encode()


def file_names(scan_names: Iterable[str]) -> list[str]:
    """Every file an export of these scans may write (any cloud format)."""
    return ([p.name for p in export_paths(".", list(scan_names))] + [f"merged.{f}" for f in CLOUD_FORMATS]
            + [PARAMS_NAME, STARTS_NAME])


def check_not_inputs(out_dir: Path, names: Iterable[str], inputs: Iterable[str | Path]) -> None:
    """`OutputError` when an export `names` in `out_dir` would be one of the `inputs` (also through a link)."""
    check_distinct([(f"the export {n}", Path(out_dir) / n) for n in names], inputs, advice=CLASH_ADVICE)


def input_clash(bundle: ExportBundle, out_dir: Path, inputs: Iterable[str | Path]) -> str | None:
    """Why `bundle` may not be written into `out_dir` (a file of it would replace an input), or None."""
    try:
        check_not_inputs(out_dir, bundle.files, inputs)
    except OutputError as e:
        return str(e)
    return None


def write_bundle(bundle: ExportBundle, out_dir: Path, inputs: Iterable[str | Path] = ()) -> list[Path]:
    """Write every file of `bundle` into `out_dir`, as one batch: all of them, or (on an error) none
    replace what was there; none when one of them would replace one of the `inputs` (`OutputError`)."""
    check_not_inputs(out_dir, bundle.files, inputs)
    with atomic.batch():
        return [write_bytes_atomic(Path(out_dir) / name, data) for name, data in bundle.files.items()]


def zip_bundle(bundle: ExportBundle) -> bytes:
    """All files in one zip (one browser download instead of many)."""
    buf = _io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as z:
        for name, data in bundle.files.items():
            z.writestr(name, data)
    return buf.getvalue()



#: The longest case name a zip's name takes (a folder's name can be long).
MAX_CASE_CHARS = 60


def case_name(snap: Snapshot) -> str:
    """What the scans are of, for a file name: the folder all the loaded scan files sit in (the case's
    folder: `demo`, `plot_17`), else the reference scan's name (`scan1.ply` -> `scan1`); made safe
    as one file name (`io.naming.file_safe`)."""
    folders = {s.source.resolve().parent for s in snap.scans if s.source is not None and s.source.is_absolute()}
    every = all(s.source is not None and s.source.is_absolute() for s in snap.scans)
    name = next(iter(folders)).name if every and len(folders) == 1 else ""
    if not name and snap.scans:
        name = file_stem(snap.scans[0].name)
    return file_safe(name or "scans")[:MAX_CASE_CHARS]


def zip_name(snap: Snapshot, bundle: ExportBundle, cloud_format: str) -> str:
    """The zip of every export, named after what it holds: the case, the registration (the scans
    placed, or the coarse poses only when that is all that ran) and the merged cloud's format
    (`demo_registered_ply.zip`, `demo_coarse_only_las.zip`)."""
    what = "registered" if bundle.stage == "fine" else "coarse_only"
    return f"{case_name(snap)}_{what}_{cloud_format}.zip"
