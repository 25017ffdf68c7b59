"""Running a campaign: every tree in a process pool (`workers`) or on a Dask cluster (`dask_address`).

Each finished tree is written at once into `<out>/<tree>/` (transforms.json, the CloudCompare and
PDAL matrices, picture.png, and last result.json), so an interrupted run resumes where it stopped:
a tree whose result.json is there with the same fingerprint (files, options, parameters) is not
run again unless `redo`. A tree that ended in an unexpected error is always retried. Workers use
one BLAS thread each: N workers on N cores, not N x N threads.
"""

from __future__ import annotations

import json
import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from multiprocessing import get_context
from pathlib import Path
from typing import Iterator

from ..errors import ConfigError
from ..io.atomic import write_bytes_atomic, write_text_atomic
from ..io.transforms import DEFAULT_NAME, write_exports
from ..params import Params
from ..results import Progress, no_progress
from .jobs import TreeJob
from .tree import FAILED, ScanOutcome, TreeOutcome, fingerprint, run_tree, without_payload

RESULT_NAME = "result.json"
PICTURE_NAME = "picture.png"
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
#: How long to try reaching a Dask scheduler before saying it cannot be reached.
DASK_CONNECT_TIMEOUT = "10s"


def previous(job: TreeJob, params: Params, until: str, out_dir: Path) -> TreeOutcome | None:
    """The tree's earlier outcome if it is still valid (same fingerprint, not an error), else None."""
    path = out_dir / job.name / RESULT_NAME
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if d.get("fingerprint") != fingerprint(job, params, until) or d.get("status") == "error":
        return None
    scans = tuple(ScanOutcome(**s) for s in d.get("scans", []))
    return TreeOutcome(d["tree"], d["status"], int(d["exit_code"]), d.get("message", ""), scans,
                       dict(d.get("seconds", {})), d["fingerprint"])


def write_tree(outcome: TreeOutcome, out_dir: Path) -> None:
    """A tree's files; result.json last (its presence marks the tree as done). Files of an earlier
    run that this outcome does not have (a transform that failed now) are removed, never left stale."""
    d = out_dir / outcome.tree
    d.mkdir(parents=True, exist_ok=True)
    for old in [d / DEFAULT_NAME, d / PICTURE_NAME, *d.glob("*.cloudcompare.txt"), *d.glob("*.pdal.txt")]:
        old.unlink(missing_ok=True)
    if outcome.transforms is not None:
        write_exports(d, outcome.transforms)
    if outcome.picture_png is not None:
        write_bytes_atomic(d / PICTURE_NAME, outcome.picture_png)
    write_text_atomic(d / RESULT_NAME, json.dumps(outcome.summary(), indent=1) + "\n")


def picture_of(tree: str, out_dir: Path) -> bytes | None:
    p = out_dir / tree / PICTURE_NAME
    return p.read_bytes() if p.is_file() else None


@contextmanager
def _one_thread_each() -> Iterator[None]:
    """Worker processes inherit one BLAS thread each (set in the environment they start with)."""
    saved = {k: os.environ.get(k) for k in _THREAD_VARS}
    os.environ.update({k: "1" for k in _THREAD_VARS})
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _crashed(job: TreeJob, params: Params, until: str, why: str) -> TreeOutcome:
    return TreeOutcome(job.name, "error", FAILED, why, (), {}, fingerprint(job, params, until))


def run_batch(jobs: list[TreeJob], params: Params, out_dir: Path, *, until: str = "fine", workers: int | None = None,
              dask_address: str | None = None, redo: bool = False, progress: Progress | None = None
              ) -> tuple[list[TreeOutcome], int]:
    """Register every tree; returns the outcomes in job order and how many were run (not resumed).

    `workers`: processes of the local pool (default: all cores; 1 runs in this process).
    `dask_address`: run on the Dask cluster at this scheduler address instead.
    """
    progress = progress or no_progress
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    done: dict[str, TreeOutcome] = {}
    if not redo:
        for job in jobs:
            prev = previous(job, params, until, out_dir)
            if prev is not None:
                done[job.name] = prev
    todo = [j for j in jobs if j.name not in done]
    total = len(jobs)

    def finished(outcome: TreeOutcome) -> None:
        write_tree(outcome, out_dir)
        done[outcome.tree] = without_payload(outcome)
        progress(len(done) / total, f"{outcome.tree}: {outcome.status}")

    client = _dask_client(dask_address) if dask_address and todo else None  # unreachable: say so first
    progress(len(done) / total, f"{len(done)} of {total} trees already done" if done else "starting")
    if client is not None:
        _run_dask(todo, params, until, client, finished)
    elif (workers or os.cpu_count() or 1) <= 1 or len(todo) <= 1:
        for job in todo:
            finished(run_tree(job, params, until))
    else:
        _run_pool(todo, params, until, workers or os.cpu_count() or 1, finished)
    return [done[j.name] for j in jobs], len(todo)


def _run_pool(todo: list[TreeJob], params: Params, until: str, workers: int, finished) -> None:
    """A process pool; a worker that dies (killed for memory, a crash in a library) fails its tree,
    and the others are run again in a new pool (a tree that breaks the pool twice is given up)."""
    attempts = {j.name: 0 for j in todo}
    left = list(todo)
    while left:
        broken: list[TreeJob] = []
        with _one_thread_each(), ProcessPoolExecutor(max_workers=min(workers, len(left)),
                                                     mp_context=get_context("spawn")) as pool:
            futures = {pool.submit(run_tree, job, params, until): job for job in left}
            for fut in as_completed(futures):
                job = futures[fut]
                try:
                    finished(fut.result())
                except BrokenProcessPool:
                    broken.append(job)
        left = []
        for job in broken:
            attempts[job.name] += 1
            if attempts[job.name] >= 2:
                finished(_crashed(job, params, until, "the worker process died (out of memory?) twice on this tree"))
            else:
                left.append(job)


def _dask_client(address: str):
    try:
        from distributed import Client
    except ImportError:
        raise ConfigError("--dask needs Dask: pip install 'treereg[dask]'") from None
    try:
        return Client(address, timeout=DASK_CONNECT_TIMEOUT)
    except (OSError, TimeoutError, ValueError) as e:
        raise ConfigError(f"--dask {address}: cannot reach the Dask scheduler ({e})") from None


def _run_dask(todo: list[TreeJob], params: Params, until: str, client, finished) -> None:
    from distributed import as_completed as dask_completed

    try:
        futures = {}
        for job in todo:
            fut = client.submit(run_tree, job, params, until, pure=False, key=f"treereg-{job.name}-{os.getpid()}")
            futures[fut] = job
        for fut in dask_completed(list(futures)):
            job = futures[fut]
            try:
                finished(fut.result())
            except Exception as e:  # noqa: BLE001 - a lost worker (KilledWorker, ...) fails this tree only
                finished(_crashed(job, params, until, f"the Dask worker failed: {type(e).__name__}: {e}"))
    finally:
        client.close()
