"""`treereg batch`: register every tree of a campaign (a folder of tree folders, or a CSV manifest)."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from treereg_core.batch.jobs import SUMMARY_NAMES, TreeJob, find_jobs
from treereg_core.batch.report import write_summary
from treereg_core.batch.runner import PICTURE_NAME, RESULT_NAME, picture_of, run_batch
from treereg_core.errors import ConfigError, OutputError
from treereg_core.io.atomic import check_distinct
from treereg_core.io.naming import scan_names
from treereg_core.io.transforms import export_paths
from treereg_core.text import shown

from . import progress
from .common import add_param_args, load_params
from .progress import ProgressBar


def add(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "batch",
        help="register many trees: a folder of tree folders or a CSV manifest -> per-tree transforms and a report",
        description="Register every tree of a campaign. INPUT is a folder with one sub-folder per tree (its "
        "scan files; the first by name, or by truth.json's order, is the reference) or a CSV manifest with "
        "the columns tree, scans (files separated by ';', reference first)[, angular_step][, target][, initial "
        "(start poses as register --initial gives them: SCAN=FILE separated by ';')]. Writes "
        "OUT/<tree>/transforms.json with the CloudCompare and PDAL matrices, and OUT/summary.csv, "
        "OUT/scans.csv and a self-contained OUT/report.html. Trees already done are skipped (unless --redo); "
        "a failing tree never stops the others.",
    )
    p.add_argument("input", metavar="INPUT", help="folder of tree folders, or a .csv manifest")
    p.add_argument("--out", help="output folder (default: INPUT_results beside the input)")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help=f"processes working in parallel (default: all cores, here {os.cpu_count()})")
    p.add_argument("--dask", metavar="SCHEDULER_ADDRESS",
                   help="run the trees on this Dask cluster instead (tcp://host:8786; needs treereg[dask])")
    p.add_argument("--redo", action="store_true", help="register every tree again, even those already done")
    p.add_argument("--until", choices=("coarse", "fine"), default="fine",
                   help="last stage to run (default: fine, with verification; coarse leaves every scan unverified)")
    add_param_args(p)
    p.set_defaults(func=run)


def _default_out(src: Path) -> Path:
    return src.parent / f"{src.stem if src.is_file() else src.name}_results"


def check_out(src: Path, out: Path) -> None:
    """The results folder is not the input folder nor inside it: the next run would take the
    results (matrix text files, CSVs) for scans."""
    if not src.is_dir():
        return
    s, o = src.resolve(), out.resolve()
    if o == s or s in o.parents:
        where = "the input folder" if o == s else f"inside the input folder {src}"
        raise OutputError(str(out), f"is {where}; the results would be read as scans by the next run: "
                          f"choose a folder outside it (e.g. {_default_out(src)})")


def check_outputs(src: Path, out: Path, jobs: list[TreeJob]) -> None:
    """No file batch writes is one of its inputs (a scan, the manifest, a truth.json)."""
    outputs = [(f"the campaign's {name}", out / name) for name in SUMMARY_NAMES]
    inputs: list[Path] = [src] if src.is_file() else []
    for job in jobs:
        d = out / job.name
        files = [d / RESULT_NAME, d / PICTURE_NAME, *export_paths(d, _scan_names(job))]
        outputs += [(f"the result {f.name} of tree {job.name}", f) for f in files]
        inputs += [*job.scans, *([job.truth] if job.truth else [])]
    check_distinct(outputs, inputs, advice="choose another --out folder")


def _scan_names(job: TreeJob) -> list[str]:
    """The names the tree's scans will have (as `batch.tree.run_tree` names them), before any is read."""
    try:
        return scan_names([(f, Path(f).name) for f in job.scans])
    except ConfigError:  # a file listed twice: that tree fails on its own, saying so
        return [Path(f).name for f in job.scans]


def _notice(text: str) -> None:
    progress.end_line()
    print(f"  {shown(text)}", file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    src = Path(args.input)
    out = Path(args.out) if args.out else _default_out(src)
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers must be at least 1, got {args.workers}")
    params = load_params(args)
    check_out(src, out)
    jobs = find_jobs(src)
    check_outputs(src, out, jobs)
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".treereg-write-test"
        probe.write_text("")
        probe.unlink()
    except OSError as e:
        raise ConfigError(f"{out}: cannot write the results there ({e.strerror or e})") from None
    t0 = time.perf_counter()
    where = f"Dask cluster {args.dask}" if args.dask else f"{args.workers or os.cpu_count()} worker(s)"
    print(f"{len(jobs)} trees from {shown(src)}, {shown(where)}, results in {shown(out)}", file=sys.stderr)
    outcomes, ran = run_batch(jobs, params, out, until=args.until, workers=args.workers, dask_address=args.dask,
                              redo=args.redo, progress=ProgressBar("batch"), notice=_notice)
    seconds = time.perf_counter() - t0
    paths = write_summary(outcomes, out, {o.tree: picture_of(o.tree, out) for o in outcomes},
                          title=f"treereg batch: {src.name}")
    counts = {s: sum(o.status == s for o in outcomes) for s in ("ok", "partial", "unverified", "failed", "error")}
    print(f"{len(outcomes)} trees ({ran} run, {len(outcomes) - ran} already done) in {seconds:.1f} s: "
          + ", ".join(f"{v} {k}" for k, v in counts.items() if v))
    for o in outcomes:
        if o.status != "ok":
            print(f"  {shown(o.tree)}: {o.status}: {shown(o.message)}", file=sys.stderr)
    print(f"wrote {', '.join(shown(p) for p in paths)}")
    return 0 if counts["ok"] == len(outcomes) else 1
