"""`treereg evaluate`: the evaluation table of a transform file."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from treereg_core import params as P
from treereg_core.errors import ConfigError
from treereg_core.evaluate.branches import evaluate_pair, find_branches
from treereg_core.geometry.rigid import invert
from treereg_core.io.scans import read_scan
from treereg_core.io.transforms import TransformFile, check_transform, read_transforms
from treereg_core.prepare.ground import prepare_scan
from treereg_core.scan import Scan
from treereg_core.text import shown

from .common import add_set_arg, apply_sets
from .progress import ProgressBar


def add(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "evaluate",
        help="print the evaluation table of a transform file (paper's branch model; errors against truth)",
        description="Evaluate every transform of a transform file: the paper's branch-centre error "
        "(eq. 8) per branch and overall and, with --truth, the rotation error and mean displacement "
        "of each scan's points against the true transform.",
    )
    p.add_argument("transforms", help="transforms.json written by `treereg register` or the app")
    p.add_argument("--truth", help="truth.json of a simulated case (same scan names)")
    p.add_argument("--scan-dir", help="folder holding the scans, each at its name (a scan named by its folder, "
                   "a/scan1.ply, in that sub-folder; default: the paths recorded in the transform file, else the "
                   "transform file's folder)")
    p.add_argument("--branches", action="store_true", help="also print the per-branch table (paper Figs. 13-14)")
    add_set_arg(p)  # over the parameters the transform file records (e.g. --set evaluation.max_rms_m=0.02)
    p.set_defaults(func=run)


def _scan_path(name: str, tf: TransformFile, args: argparse.Namespace) -> Path:
    if args.scan_dir:
        return Path(args.scan_dir) / name
    recorded = (tf.extra.get("sources") or {}).get(name)
    if recorded and Path(recorded).exists():
        return Path(recorded)
    return Path(args.transforms).resolve().parent / name


def run(args: argparse.Namespace) -> int:
    tf = read_transforms(args.transforms)
    truth = read_transforms(args.truth) if args.truth else None
    params = P.from_dict(tf.params, source=f"{args.transforms}: params") if tf.params else P.Params()
    params = apply_sets(params, args.set or [])
    steps = tf.extra.get("angular_step_deg") or {}
    # Best guesses listed under "unverified" are evaluated too (their verdict says what they are).
    unverified = tf.extra.get("unverified") or {}
    guesses = {n: check_transform(v.get("matrix"), f"{args.transforms}: unverified[{n!r}]")
               for n, v in unverified.items() if isinstance(v, dict) and n not in tf.transforms}
    names = tf.names + sorted(guesses)
    verdicts = {n: (v or {}).get("verdict", "") for n, v in ((tf.extra.get("quality") or {}).get("scans") or {}).items()}
    if truth is not None:
        missing = [n for n in names if n not in truth.names]
        if missing:
            raise ConfigError(f"{args.truth}: no true transform for {', '.join(missing)}")

    def load(name: str) -> Scan:
        step = steps.get(name) if isinstance(steps, dict) else None
        scan = read_scan(_scan_path(name, tf, args), angular_step_deg=tuple(step) if step else params.prepare.angular_step_deg, name=name)
        return prepare_scan(scan, prepare=params.prepare).scan

    ref = load(names[0])
    branches = find_branches(ref, evaluation=params.evaluation)
    header = "| pair | verdict | branches | layer pairs | d (m), eq. 8 |"
    rule = "|---|---|---|---|---|"
    if truth is not None:
        header += " rotation error (deg) | mean displacement (m) |"
        rule += "---|---|"
    rows, branch_rows = [header, rule], []
    bar = ProgressBar("evaluate")
    for k, name in enumerate(names[1:]):
        bar(k / max(len(names) - 1, 1), name)
        tgt = load(name)
        T_true = None
        if truth is not None:
            # Truth files map onto their own reference; express the truth relative to ours.
            T_true = invert(truth.matrix(names[0])) @ truth.matrix(name)
        T = guesses[name] if name in guesses else tf.matrix(name)
        ev = evaluate_pair(ref, tgt, T, evaluation=params.evaluation, T_true=T_true, branches=branches)
        d = f"{ev.mean_distance_m:.4f}" if ev.ok else f"n/a ({ev.message})"
        verdict = verdicts.get(name) or ("unverified" if name in guesses else "(not recorded)")
        row = f"| {name} -> {names[0]} | {verdict} | {len(ev.branches)} | {ev.n_pairs} | {d} |"
        if truth is not None:
            row += f" {ev.rotation_error_deg:.3f} | {ev.mean_displacement_m:.4f} |"
        rows.append(row)
        for b in ev.branches:
            ds = ", ".join(f"{x:.4f}" for x in b.distances_m)
            branch_rows.append(f"| {name} -> {names[0]} | {b.index} | {b.height_m:.2f} | {b.radius_m:.3f} | {ds} | {np.mean(b.distances_m):.4f} |")
    bar(1.0, "done")
    print("\n".join(shown(r) for r in rows))  # names are transforms.json's keys: text from outside
    if args.branches and branch_rows:
        print("\n| pair | branch | height (m) | radius (m) | d1..dn (m) | mean d (m) |\n|---|---|---|---|---|---|")
        print("\n".join(shown(r) for r in branch_rows))
    return 0
