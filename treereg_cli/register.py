"""`treereg register`: register scans onto the first, verify every scan, write the transform file.

Exit status: 0 when every scan is verified, 1 when any is not (the others are written; stderr gives
one line per scan that is not, with the reason and what to try), 2 for input to fix.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Callable

from treereg_core.errors import ConfigError, ScanError
from treereg_core.io import atomic
from treereg_core.io.atomic import check_distinct, check_output_file
from treereg_core.io.e57 import write_registered_e57
from treereg_core.io.merged import write_merged
from treereg_core.batch.runner import dask_client
from treereg_core.io.scans import WRITE_EXTENSIONS, extension
from treereg_core.io.transforms import (TransformFile, export_paths, registered_e57_name, registration_file, stale_exports,
                                        write_exports, write_transforms)
from treereg_core.params import Params
from treereg_core.scan import Scan
from treereg_core.pipeline import register
from treereg_core.survey.mode import is_survey
from treereg_core.survey.register import register_survey
from treereg_core.survey.report import survey_report_html
from treereg_core.survey.summary import survey_quality, survey_table
from treereg_core.stages import UNTIL
from treereg_core.verify.report import motion_lines, quality_report, verdict_lines, verdict_text
from treereg_core.verify.summary import scan_summaries, summary_table

from treereg_core.text import shown

from .common import (add_initial_arg, add_param_args, add_workers_arg, initial_files, load_params, read_initial,
                     read_scans, scan_readers, workers_of)
from .progress import ProgressBar

#: `--until` choice -> the last stage run ("fine" includes the verification and the joint placement).


def add(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "register",
        help="register scans onto the first one (coarse, fine, verification) and write transforms.json",
        description="Register every scan onto the first (the reference): rotating-projection coarse "
        "registration, fine registration from fitted stem and branch sections, then the evidence that "
        "each scan is placed right. Only verified scans go into \"transforms\"; best guesses are listed "
        "under \"unverified\" with the reasons.",
    )
    p.add_argument("scans", nargs="+", metavar="SCAN", help="scan files (first scan = reference): PLY, LAS/LAZ, "
                   "XYZ/TXT/CSV, NPY/NPZ, or E57/PTX files holding one or more scans; each scan is named by its file's "
                   "name (or its name in the E57), by folder where two share one: a/scan1.ply, b/scan1.ply")
    p.add_argument("--out", default="transforms.json", help="transform file to write (default: transforms.json)")
    p.add_argument("--until", choices=tuple(UNTIL), default="fine",
                   help="last stage to run (default: fine, with verification; coarse leaves every scan unverified)")
    p.add_argument("--keep-unverified", action="store_true",
                   help="also write the best guesses of unverified scans into \"transforms\" (marked in \"quality\")")
    add_param_args(p)
    add_initial_arg(p)
    add_workers_arg(p, "pairs and scans registered side by side")
    p.add_argument("--details", action="store_true",
                   help="also print every pair's numbers, stage by stage (by default one row per scan: its verdict "
                   "and the checks it rests on, each beside its threshold)")
    p.add_argument("--exports", action="store_true",
                   help="also write CloudCompare and PDAL matrix files beside --out, named after it "
                   "(<out>.<scan>.cloudcompare.txt, <out>.<scan>.pdal.txt), and <out>.registered.e57")
    p.add_argument("--e57", metavar="FILE", help="also write the registered scans as one multi-scan E57 (each scan "
                   "with its estimated pose: CloudCompare and other E57 readers open it registered)")
    p.add_argument("--merged", metavar="FILE",
                   help="also write the merged registered cloud (.ply, .las or .laz), each point tagged with "
                   "its scan's number (PLY property scan_id, LAS point_source_id; 1 = the reference)")
    p.add_argument("--report", metavar="FILE",
                   help="a survey's report (HTML): the map of stations and stems with every pair coloured by its verdict, "
                   "each station's row and the loop closures")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--survey", action="store_true",
                      help="a whole-plot survey: every station registered on every stem and the ground it shares with its "
                      "neighbours, all placed together (the default for more than 8 stations; survey.mode)")
    mode.add_argument("--one-tree", action="store_true",
                      help="register the one tree the stations surround, even with more than 8 stations (survey.mode; "
                      "--tree-at keeps it too)")
    p.add_argument("--dask", metavar="SCHEDULER_ADDRESS",
                   help="a survey's stations and pairs on this Dask cluster (tcp://host:8786; its workers must reach "
                   "the scan files; needs treereg[dask]): a large survey as a cluster job")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.merged and extension(args.merged) not in WRITE_EXTENSIONS:
        # Said before minutes of registration, not after.
        raise ConfigError(f"{args.merged}: the merged cloud is written as {', '.join(WRITE_EXTENSIONS)}; "
                          f"not {extension(args.merged) or '(no extension)'!r}")
    if args.e57 and extension(args.e57) != ".e57":  # an E57 under another format's name misleads every reader
        raise ConfigError(f"{args.e57}: --e57 writes an E57 file; give it the extension .e57, "
                          f"not {extension(args.e57) or '(no extension)'!r}")
    out = Path(args.out)
    e57 = Path(args.e57) if args.e57 else (out.parent / registered_e57_name(out.name) if args.exports else None)
    # Where the results go is checked before anything is read or computed: never onto an input, nor
    # two results onto one file.
    outputs = [("--out", out)] + [(what, Path(p)) for what, p in (
        ("--e57" if args.e57 else "the --exports E57 (named after --out)", e57), ("--merged", args.merged),
        ("--report", args.report)) if p]
    inputs = [*args.scans, *([args.config] if args.config else []), *initial_files(args)]
    check_distinct(outputs, inputs)
    check_output_file(out, example="transforms.json")
    if args.report and extension(args.report) not in (".html", ".htm"):
        raise ConfigError(f"{args.report}: --report writes HTML; give it the extension .html, "
                          f"not {extension(args.report) or '(no extension)'!r}")
    for extra in (e57, args.merged, args.report):
        if extra is not None:
            check_output_file(extra)
    params = load_params(args)
    if args.survey or args.one_tree:
        params = params.with_value("survey", "mode", "survey" if args.survey else "one_tree")
    starts = read_initial(args.initial)  # a bad start file is said before the scans are read
    workers = workers_of(args)
    # A survey's stations are read one at a time, each reduced to its summary before the next
    # (60 stations: 1 GB of points not held); files that may hold several scans are read first.
    readers = scan_readers(args.scans, params, args.scanner_position)
    if readers is not None and len(readers) >= 2 and is_survey(len(readers), params):
        _check_matrices(args, [name for name, _ in readers], outputs, inputs, out)
        _check_survey(args, starts)
        return _run_survey(args, [read for _, read in readers], params, out=out, e57=e57, inputs=inputs,
                           workers=workers, read_s=None)
    t_read = time.perf_counter()
    scans = read_scans(args.scans, params, args.scanner_position)
    read_s = time.perf_counter() - t_read
    if len(scans) < 2:
        raise ConfigError("register needs at least two scans (the first is the reference); "
                          f"{', '.join(args.scans)} hold(s) {len(scans)}")
    _check_matrices(args, [s.name for s in scans], outputs, inputs, out)
    if is_survey(len(scans), params):
        _check_survey(args, starts)
        return _run_survey(args, scans, params, out=out, e57=e57, inputs=inputs, workers=workers, read_s=read_s)
    if args.dask:
        raise ConfigError(f"--dask {args.dask}: a cluster runs a survey's stations and pairs (more than 8 stations, or "
                          "--survey); for many trees, `treereg batch --dask` runs each tree on the cluster")
    if args.report:
        raise ConfigError(f"{args.report}: --report is a survey's report (more than 8 stations, or --survey); "
                          "for one tree, transforms.json's quality block and the app show each pair")
    t0 = time.perf_counter()
    bar = ProgressBar("register")
    # The command line runs no threads of its own: its GIL-bound stages may fork processes.
    reg = register(scans, params, until=UNTIL[args.until], events=bar.on_event, workers=workers, fork=True,
                   starts=starts)
    bar.finish()  # a run that stopped early left the bar short of full
    seconds = time.perf_counter() - t0
    pipe = reg.pipeline
    if len(reg.transforms) < 2:
        print(f"treereg: registration failed: {shown(reg.message)}", file=sys.stderr)
        return 1
    verdicts = pipe.verdicts()
    metrics = pipe.pair_metrics()
    tf = registration_file(scans, reg.transforms, params, stage=args.until, metrics=metrics, verdicts=verdicts,
                           quality=quality_report(scans, pipe.pairs, pipe.outputs), keep_unverified=args.keep_unverified,
                           sources={s.name: str(s.source.resolve()) if s.source.exists() else str(s.source) for s in scans},
                           seconds=seconds,
                           stage_seconds={"read": read_s, **{n: o.seconds for n, o in pipe.outputs.items()}})
    written, stale = _write_results(args, scans, tf, out=out, e57=e57, inputs=inputs)
    if args.details:
        _print_details(metrics, scans)
    if pipe.output("graph") is not None:
        print()
        for line in summary_table(scan_summaries(scans, pipe.pairs, pipe.outputs)):
            print(f"  {line}")
    print()
    for name, (verdict, _, _) in verdicts.items():
        start = f" (started from the pose given in {starts[name].source})" if name in starts else ""
        print(f"  {name:<30} {verdict_text(verdict, params, name == scans[0].name)}{start}")
    for line in motion_lines(scans, pipe.pairs, pipe.outputs):
        print(f"  wind: {line}")
    print(f"\nwrote {', '.join(shown(w) for w in written)} in {seconds:.1f} s")
    if stale:
        print(f"removed {', '.join(shown(p) for p in stale)}: an earlier run's matrices of scans this run does not place")
    lines = verdict_lines(verdicts)
    for line in lines:
        name = next((n for n in starts if line.startswith(f"{n}: ")), None)
        if name is not None:  # whose start it judged
            line = f"{name} (started from the pose given in {starts[name].source}): {line[len(name) + 2:]}"
        print(f"treereg: {line}", file=sys.stderr)
    return 1 if lines else 0


def _check_matrices(args: argparse.Namespace, names: list[str], outputs: list, inputs: list, out: Path) -> None:
    """--exports' matrix files (named after the scans; an E57 names its own) checked writable and distinct."""
    if args.exports:
        matrices = export_paths(out.parent, names, out.name)[1:]
        check_distinct(outputs + [("an --exports matrix file (named after --out)", p) for p in matrices], inputs)
        for path in matrices:
            check_output_file(path)


def _check_survey(args: argparse.Namespace, starts: dict) -> None:
    """What a survey refuses, said before a station is read or registered."""
    if starts:
        raise ConfigError("--initial: start poses are for the one-tree registration; a survey places its stations "
                          "from their stem maps (give --one-tree to register one tree from a start)")
    if args.until != "fine":
        raise ConfigError(f"--until {args.until}: a survey has no coarse stage of its own (its stem maps place "
                          "every station); leave --until out, or give --one-tree")


def _run_survey(args: argparse.Namespace, scans: list, params: Params, *, out: Path, e57: Path | None,
                inputs: list, workers: int | None, read_s: float | None) -> int:
    """`register` of a whole-plot survey (treereg_core/survey): the same files, one row per station.
    `scans` are Scans, or functions that read them one at a time (`read_s` None: reading is part of
    the stations' time)."""
    client = dask_client(args.dask) if args.dask else None  # an unreachable cluster is said before any work
    t0 = time.perf_counter()
    bar = ProgressBar("survey")
    try:
        survey = register_survey(scans, params, workers=workers or os.cpu_count() or 1, progress=bar, client=client)
    finally:
        if client is not None:
            client.close()
    bar.finish()
    seconds = time.perf_counter() - t0
    verdicts = survey.verdicts()
    metrics = survey.pair_metrics()
    headers = list(survey.scans)
    tf = registration_file(headers, survey.transforms(), params, stage="survey", metrics=metrics, verdicts=verdicts,
                           quality=survey_quality(survey), keep_unverified=args.keep_unverified,
                           sources={s.name: str(s.source.resolve()) if s.source.exists() else str(s.source) for s in headers},
                           seconds=seconds, stage_seconds={**({"read": read_s} if read_s is not None else {}), **survey.seconds})
    report = survey_report_html(survey, title=f"treereg survey: {len(headers)} stations") if args.report else None
    # The E57 and the merged cloud hold every point: the stations are read again for them.
    points = (lambda: [s if isinstance(s, Scan) else s() for s in scans])
    written, stale = _write_results(args, headers, tf, out=out, e57=e57, inputs=inputs, report=report, points=points)
    if args.details:
        _print_details(metrics, headers)
    print()
    for line in survey_table(survey):
        print(f"  {line}")
    print(f"\nwrote {', '.join(shown(w) for w in written)} in {seconds:.1f} s")
    if stale:
        print(f"removed {', '.join(shown(p) for p in stale)}: an earlier run's matrices of stations this run does not place")
    lines = verdict_lines(verdicts)
    for line in lines:
        print(f"treereg: {line}", file=sys.stderr)
    return 1 if lines else 0


def _write_results(args: argparse.Namespace, scans: list, tf: TransformFile, *, out: Path, e57: Path | None,
                   inputs: list, report: str | None = None,
                   points: Callable[[], list[Scan]] | None = None) -> tuple[list, list]:
    """Write the transform file and what was asked beside it as one batch; (written, stale removed).
    `points` gives the scans with their points where `scans` are headers (a survey's)."""
    # An earlier --exports run's matrices of scans this run refuses go with this one's files.
    stale = stale_exports(out.parent, tf, out.name, inputs) if args.exports else []
    # One batch: the transform file, its matrices, the E57 and the merged cloud all land, or none.
    try:
        with atomic.batch():
            written = (write_exports(out.parent, tf, name=out.name, inputs=inputs) if args.exports
                       else [write_transforms(out, tf)])
            full = (points() if points is not None else scans) if e57 is not None or args.merged else []
            if e57 is not None:
                written.append(write_registered_e57(e57, full, tf))
            if args.merged:
                # The same scans as "transforms": unverified guesses only with --keep-unverified.
                written.append(write_merged(args.merged, full, tf.transforms))
            if report is not None:
                written.append(atomic.write_text_atomic(args.report, report))
    except OSError as e:  # one line naming the file, not a traceback
        raise ScanError(e.filename or str(out), f"cannot write the results ({e.strerror or e}); nothing was written") from None
    return written, stale


def _print_details(metrics: dict, scans: list) -> None:
    """Every pair's numbers, stage by stage (`--details`)."""
    for name, rows in metrics.items():
        print(f"\n{name}" if " -> " in name else f"\n{name} -> {scans[0].name}")
        for r in rows:
            v = r["value"]
            print(f"  {r['stage']:<10} {r['metric']:<40} {_value_text(v, r['unit'])}")


def _value_text(v: object, unit: str) -> str:
    """A metric as `--details` prints it: four significant digits and its unit; "not measured" for
    NaN, "beyond reach" for infinity (never "nan" or "inf")."""
    if isinstance(v, float):
        if v != v:
            return "not measured"
        if v in (float("inf"), float("-inf")):
            return "beyond reach"
        return f"{v:.4g} {unit}".rstrip()
    return f"{v} {unit}".rstrip()
