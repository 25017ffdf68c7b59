"""One tree of a campaign: read its scans, register them, and return everything there is to write.

`run_tree` never raises: bad input, a failed registration and an unexpected error all become a
`TreeOutcome` with a status and a one-line message, so one tree never stops the others. It writes
nothing itself (the runner does, in the process that owns the output folder), so it runs the same
in a local process pool and on a Dask worker that only sees the input files.
"""

from __future__ import annotations

import hashlib
import json
import os
import stat
import time
import traceback
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..errors import ConfigError, ScanError
from ..geometry.rigid import apply_transform, rotation_error_deg
from ..io.cases import read_truth
from ..io.naming import scan_names
from ..io.scans import read_scan
from ..io.start import read_start
from ..io.transforms import TransformFile, registration_file
from ..params import Params, to_dict
from ..pipeline import register
from ..stages import UNTIL
from ..verify.report import quality_report
from .jobs import TreeJob
from .picture import tree_picture

#: Exit codes as `treereg register` gives them: 0 all registered, 1 some or all failed, 2 bad input.
OK, FAILED, BAD_INPUT = 0, 1, 2
#: Bytes hashed at each end of a scan file for the resume fingerprint (with its size): a multi-GB
#: scan is fingerprinted in milliseconds, and a scan replaced by another file is seen even when
#: its size and time were kept (`cp -p`); a file of up to twice this is hashed whole.
FINGERPRINT_BYTES = 1 << 20


@dataclass(frozen=True)
class ScanOutcome:
    """One scan of a tree: how it ended, and its error against the truth when there is one.

    verdict : "reference", "verified" (placed, with the evidence), "unverified" (a best guess, listed
        under "unverified" in transforms.json; `message` says why and what to try) or "failed" (no
        transform; `message` says where and why). The error against truth is given for verified
        scans and for unverified guesses alike, so a campaign shows what verification held back.
    """

    name: str
    points: int
    verdict: str
    message: str = ""
    rot_err_deg: float | None = None
    disp_err_m: float | None = None
    started_from: str = ""  # the start pose file the user gave it (the manifest's initial column)


@dataclass(frozen=True)
class TreeOutcome:
    """A tree's result: status "ok" (every scan verified), "partial" (some verified), "unverified"
    (best guesses only, e.g. `--until coarse`), "failed" (no scan registered, or bad input) or
    "error" (an unexpected exception; its last line is the message). Only "ok" exits 0."""

    tree: str
    status: str
    exit_code: int
    message: str
    scans: tuple[ScanOutcome, ...]
    seconds: dict[str, float]
    fingerprint: str
    transforms: TransformFile | None = None
    picture_png: bytes | None = None
    kept: dict | None = None  # the earlier result left in place of this run's worse one: status, written

    def summary(self) -> dict:
        """JSON-ready record (what result.json holds; the transforms are in transforms.json)."""
        return {"tree": self.tree, "status": self.status, "exit_code": self.exit_code, "message": self.message,
                "scans": [s.__dict__ for s in self.scans], "seconds": self.seconds, "fingerprint": self.fingerprint,
                "kept": self.kept}


def content_digest(path: Path) -> str:
    """A scan file's content: a hash of its size and its first and last `FINGERPRINT_BYTES`."""
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):  # a FIFO would block the read
            return "not a regular file"
        h = hashlib.sha256()
        with open(path, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            h.update(f"{size}|".encode())
            h.update(fh.read(FINGERPRINT_BYTES))
            if size > FINGERPRINT_BYTES:
                fh.seek(max(FINGERPRINT_BYTES, size - FINGERPRINT_BYTES))
                h.update(fh.read(FINGERPRINT_BYTES))
        return h.hexdigest()
    except OSError as e:
        return f"unreadable ({e.errno})"


def fingerprint(job: TreeJob, params: Params, until: str) -> str:
    """What a tree's result depends on: its files (path and content), its options and the parameters.
    A resumed run redoes a tree whose fingerprint changed."""
    h = hashlib.sha256()
    for f in job.scans:
        h.update(f"{Path(f).resolve()}|{content_digest(Path(f))}".encode())
    for name, f in job.starts:  # a start pose changed or given: the tree is redone
        h.update(f"start|{name}|{Path(f).resolve()}|{content_digest(Path(f))}".encode())
    h.update(json.dumps([job.angular_step_deg, job.target_xy_m, until, to_dict(params)], sort_keys=True).encode())
    return h.hexdigest()[:16]


def tree_params(job: TreeJob, params: Params) -> Params:
    """The parameters of one tree: the campaign's, with the tree's own angular step and target."""
    p = params
    if job.angular_step_deg is not None:
        p = p.with_value("prepare", "angular_step_deg", job.angular_step_deg)
    if job.target_xy_m is not None:
        p = apply_target(p, job.target_xy_m)
    return p


def apply_target(params: Params, xy: tuple[float, float]) -> Params:
    """The target stem's position (x y in the reference scan's frame) as the target section's parameter."""
    return params.with_value("target", "tree_at", xy)


def run_tree(job: TreeJob, params: Params, until: str = "fine", picture: bool = True,
             workers: int | None = 1, fork: bool = False) -> TreeOutcome:
    """Register one tree (never raises; see the module docstring). `workers`, `fork`: the
    registration's own (`pipeline.register`): one in a pool of trees, all cores when alone."""
    t0 = time.perf_counter()
    fp = fingerprint(job, params, until)
    seconds: dict[str, float] = {}
    try:
        p = tree_params(job, params)
        starts = {name: read_start(f, name) for name, f in job.starts}
        if len(job.scans) < 2:
            raise ConfigError(f"{job.name}: only {len(job.scans)} scan file; at least two are needed")
        scans = [read_scan(f, angular_step_deg=p.prepare.angular_step_deg) for f in job.scans]
        # Named as `treereg register` names them: by folder where two files share a name.
        names = scan_names([(f, s.name) for f, s in zip(job.scans, scans)])
        scans = [s if s.name == n else s.with_points(s.points, name=n) for s, n in zip(scans, names)]
        seconds["read"] = time.perf_counter() - t0
        t1 = time.perf_counter()
        reg = register(scans, p, until=UNTIL[until], workers=workers, fork=fork, starts=starts)
        seconds["register"] = time.perf_counter() - t1
    except (ScanError, ConfigError) as e:
        seconds["total"] = time.perf_counter() - t0
        return TreeOutcome(job.name, "failed", BAD_INPUT, str(e), (), seconds, fp)
    except Exception as e:  # noqa: BLE001 - one tree's bug or exhaustion must not stop the campaign
        seconds["total"] = time.perf_counter() - t0
        last = traceback.format_exception_only(type(e), e)[-1].strip()
        return TreeOutcome(job.name, "error", FAILED, f"unexpected error: {last}", (), seconds, fp)
    truth = _read_truth(job)
    pipe = reg.pipeline
    verdicts = pipe.verdicts()
    outcomes = [ScanOutcome(scans[0].name, scans[0].n_points, "reference")]
    for s in scans[1:]:
        verdict, reasons, hint = verdicts.get(s.name, ("failed", ("not registered",), ""))
        msg = "; ".join(reasons) + (f" (try: {hint})" if hint and verdict != "verified" else "")
        rot = disp = None
        if truth is not None and s.name in reg.transforms and s.name in truth and names[0] in truth:
            T_true = np.linalg.inv(truth[names[0]]) @ truth[s.name]
            T = reg.transforms[s.name]
            rot = rotation_error_deg(T, T_true)
            disp = float(np.linalg.norm(apply_transform(T, s.points) - apply_transform(T_true, s.points), axis=1).mean())
        outcomes.append(ScanOutcome(s.name, s.n_points, verdict, msg, rot, disp,
                                    starts[s.name].source if s.name in starts else ""))
    n_verified = sum(o.verdict == "verified" for o in outcomes)
    n_failed = sum(o.verdict == "failed" for o in outcomes)
    status = ("ok" if n_verified == len(scans) - 1 else "partial" if n_verified else
              "failed" if n_failed == len(scans) - 1 else "unverified")
    message = "; ".join(f"{o.name}: {o.verdict}: {o.message}" for o in outcomes if o.verdict in ("unverified", "failed"))
    tf = None
    if len(reg.transforms) >= 2:  # unverified guesses are written too, under "unverified", never as verified
        tf = registration_file(scans, reg.transforms, p, stage=until, metrics=pipe.pair_metrics(), verdicts=verdicts,
                               quality=quality_report(scans, pipe.pairs, pipe.outputs),
                               sources={s.name: str(Path(f).resolve()) for s, f in zip(scans, job.scans)},
                               seconds=seconds["register"])
    # The picture shows what the transform file vouches for: the reference and the verified scans.
    shown = {n: reg.transforms[n] for n in tf.transforms} if tf is not None else {}
    png = tree_picture([s.points for s in scans], [shown.get(s.name) for s in scans]) if picture else None
    seconds["total"] = time.perf_counter() - t0
    return TreeOutcome(job.name, status, OK if status == "ok" else FAILED, message, tuple(outcomes),
                       {k: round(v, 3) for k, v in seconds.items()}, fp, tf, png)


def _read_truth(job: TreeJob) -> dict[str, np.ndarray] | None:
    if job.truth is None:
        return None
    try:
        return read_truth(job.truth)
    except (ConfigError, OSError):
        return None


def without_payload(outcome: TreeOutcome) -> TreeOutcome:
    """The outcome without its transforms and picture (what the summary needs)."""
    return replace(outcome, transforms=None, picture_png=None)
