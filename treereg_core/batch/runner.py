"""Running a campaign: every tree in a process pool (`workers`) or on a Dask cluster (`dask_address`).

Each finished tree is written at once into `<out>/<tree>/` (transforms.json, the CloudCompare and
PDAL matrices, picture.png and result.json, all or none), so an interrupted run resumes where it
stopped: a tree whose result.json is there with the same fingerprint (scan paths and content,
options, parameters) and whose files still read back is not run again unless `redo`. A tree that
ended in an unexpected error is always retried. A run never replaces a tree's result with a worse
one (a failed re-run keeps the verified result, and says so). Workers use one BLAS thread each: N
workers on N cores, not N x N threads; Ctrl-C or SIGTERM ends them at once.
"""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from multiprocessing import get_context
from pathlib import Path
from dataclasses import replace
from typing import Callable, Iterator

import numpy as np

from ..errors import ConfigError
from ..io import atomic
from ..io.atomic import write_bytes_atomic, write_text_atomic
from ..io.transforms import (DEFAULT_NAME, export_names, parse_cloudcompare_matrix, parse_pdal_matrix, read_transforms,
                             write_exports)
from ..params import Params
from ..results import Progress, no_progress
from .jobs import TreeJob
from .tree import FAILED, ScanOutcome, TreeOutcome, fingerprint, run_tree, without_payload

RESULT_NAME = "result.json"
PICTURE_NAME = "picture.png"
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
#: How long to try reaching a Dask scheduler before saying it cannot be reached.
DASK_CONNECT_TIMEOUT = "10s"


#: How good a status is: a run never replaces an earlier result with a worse one (nothing verified
#: instead of verified scans, no transform file instead of one).
_RANK = {"ok": 2, "partial": 2, "unverified": 1, "failed": 0, "error": 0}


def _record(d: Path) -> dict | None:
    """The tree folder's result.json, or None when there is none or it does not read."""
    try:
        rec = json.loads((d / RESULT_NAME).read_text())
    except (OSError, ValueError):
        return None
    return rec if isinstance(rec, dict) else None


def result_problem(d: Path, rec: dict) -> str | None:
    """What is wrong with the files a result.json vouches for (one missing, or not reading back as the
    transforms it was written from), or None when every one is there and sound."""
    files = rec.get("files")
    if not isinstance(files, list) or not all(isinstance(f, str) for f in files):
        return f"its {RESULT_NAME} does not list its files"
    for name in files:
        if not (d / name).is_file():
            return f"its {name} is missing"
    if DEFAULT_NAME not in files:
        return None
    path = d / DEFAULT_NAME
    try:
        tf = read_transforms(path)
    except ConfigError as e:
        return f"its {DEFAULT_NAME} does not read ({str(e).removeprefix(f'{path}: ')})"
    for scan, names in export_names(tf.names).items():
        for name, parse in zip(names, (parse_cloudcompare_matrix, parse_pdal_matrix)):
            try:
                same = np.allclose(parse((d / name).read_text()), tf.matrix(scan), rtol=0, atol=1e-12)
            except (ConfigError, OSError, UnicodeDecodeError) as e:
                return f"its {name} does not read ({e})"
            if not same:
                return f"its {name} does not hold the transform of {scan} in {DEFAULT_NAME}"
    return None


def _outcome(rec: dict) -> TreeOutcome:
    scans = tuple(ScanOutcome(**s) for s in rec.get("scans", []))
    return TreeOutcome(rec["tree"], rec["status"], int(rec["exit_code"]), rec.get("message", ""), scans,
                       dict(rec.get("seconds", {})), rec["fingerprint"], kept=rec.get("kept"))


def previous(job: TreeJob, params: Params, until: str, out_dir: Path) -> tuple[TreeOutcome | None, str | None]:
    """The tree's earlier outcome if it still stands (same fingerprint, not an error, every file it
    vouches for there and sound), else None and, when that is not plain (changed input, an error,
    never run), why the tree is run again."""
    d = out_dir / job.name
    if not (d / RESULT_NAME).exists():
        return None, None
    rec = _record(d)
    if rec is None:
        return None, f"its {RESULT_NAME} does not read"
    if rec.get("fingerprint") != fingerprint(job, params, until) or rec.get("status") == "error":
        return None, None
    problem = result_problem(d, rec)
    if problem is not None:
        return None, problem
    try:
        return _outcome(rec), None
    except (KeyError, TypeError, ValueError):
        return None, f"its {RESULT_NAME} does not read"


def _standing(d: Path) -> dict | None:
    """The earlier result in a tree folder whose files are there and sound: its status, when it was
    written and its files (a result kept by a later failed run counts as itself)."""
    rec = _record(d)
    if rec is None or result_problem(d, rec) is not None or not rec["files"]:
        return None
    own = rec.get("kept") if isinstance(rec.get("kept"), dict) else rec
    if own.get("status") not in _RANK:
        return None
    return {"status": own["status"], "written": str(own.get("written", "an earlier run")), "files": rec["files"]}


def _keeping(outcome: TreeOutcome, earlier: dict) -> TreeOutcome:
    """This run's outcome, saying that the earlier, better result stays in place."""
    what = "verified" if _RANK[earlier["status"]] == 2 else "unverified"
    why = f"{outcome.message}; " if outcome.message else ""
    return replace(outcome, message=f"{why}the previous {what} result of {earlier['written']} is kept "
                                    f"(this run replaced none of its files)",
                   kept={"status": earlier["status"], "written": earlier["written"]}, transforms=None, picture_png=None)


def _result_json(outcome: TreeOutcome, files: list[str]) -> str:
    rec = {**outcome.summary(), "files": files, "written": time.strftime("%Y-%m-%d %H:%M")}
    return json.dumps(rec, indent=1) + "\n"


def _ours(d: Path) -> list[Path]:
    """The files a tree's result can have (result.json aside)."""
    return [d / DEFAULT_NAME, d / PICTURE_NAME, *d.glob("*.cloudcompare.txt"), *d.glob("*.pdal.txt")]


def write_tree(outcome: TreeOutcome, out_dir: Path) -> TreeOutcome:
    """A tree's files, written together with its result.json (whose presence marks the tree as done):
    all of them or, interrupted, none replace the earlier ones. Returns the outcome as recorded.

    An outcome worse than the earlier result standing in the folder (`_RANK`: a failed re-run, nothing
    verified where scans were) leaves that result's files in place and says so in its message. An
    outcome with files of its own replaces the earlier ones, and files of the earlier run it does not
    have (a transform that failed now) are removed, never left stale. Nothing is removed otherwise.
    """
    d = out_dir / outcome.tree
    d.mkdir(parents=True, exist_ok=True)
    earlier = _standing(d)
    if earlier is not None and _RANK.get(outcome.status, 0) < _RANK[earlier["status"]]:
        outcome = _keeping(outcome, earlier)
        write_text_atomic(d / RESULT_NAME, _result_json(outcome, earlier["files"]))
        return outcome
    files: list[str] = []
    with atomic.batch():
        if outcome.transforms is not None:
            files += [p.name for p in write_exports(d, outcome.transforms)]
        if outcome.picture_png is not None:
            files.append(write_bytes_atomic(d / PICTURE_NAME, outcome.picture_png).name)
        write_text_atomic(d / RESULT_NAME, _result_json(outcome, files))
        if files:  # removed with the batch's renames: an interrupted write removes nothing either
            for old in _ours(d):
                if old.name not in files:
                    atomic.remove_atomic(old)
    return without_payload(outcome)


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


# Nine parameters: the campaign (jobs, parameters, folder) and, by keyword, how it is run (stage,
# workers or a Dask cluster, redo) and where it reports (progress, notices); each defaults sensibly.
def run_batch(jobs: list[TreeJob], params: Params, out_dir: Path, *, until: str = "fine", workers: int | None = None,
              dask_address: str | None = None, redo: bool = False, progress: Progress | None = None,
              notice: Callable[[str], None] | None = None) -> tuple[list[TreeOutcome], int]:
    """Register every tree; returns the outcomes in job order and how many were run (not resumed).

    `workers`: processes of the local pool (default: all cores; 1 runs in this process).
    `dask_address`: run on the Dask cluster at this scheduler address instead.
    `notice`: told, as "<tree>: <why>; registering it again", of a result that cannot be trusted.
    Ctrl-C (KeyboardInterrupt) stops the workers at once; the trees finished are written, the others not.
    """
    progress = progress or no_progress
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    done: dict[str, TreeOutcome] = {}
    if not redo:
        for job in jobs:
            prev, why = previous(job, params, until, out_dir)
            if prev is not None:
                done[job.name] = prev
            elif why and notice is not None:
                notice(f"{job.name}: {why}; registering it again")
    todo = [j for j in jobs if j.name not in done]
    total = len(jobs)

    def finished(outcome: TreeOutcome) -> None:
        done[outcome.tree] = write_tree(outcome, out_dir)
        progress(len(done) / total, f"{outcome.tree}: {outcome.status}")

    client = dask_client(dask_address) if dask_address and todo else None  # unreachable: say so first
    progress(len(done) / total, f"{len(done)} of {total} trees already done" if done else "starting")
    if client is not None:
        _run_dask(todo, params, until, client, finished)
    elif (workers or os.cpu_count() or 1) <= 1 or len(todo) <= 1:
        # One tree at a time, in this process: each registration uses every core itself (forking
        # for its GIL-bound stages only from the main thread of a process that runs no other).
        fork = threading.current_thread() is threading.main_thread()
        for job in todo:
            finished(run_tree(job, params, until, workers=None, fork=fork))
    else:
        _run_pool(todo, params, until, workers or os.cpu_count() or 1, finished)
    return [done[j.name] for j in jobs], len(todo)


@contextmanager
def _workers_ignore_ctrl_c() -> Iterator[None]:
    """Workers started inside are born ignoring SIGINT (an ignored signal stays ignored across exec,
    and Python keeps it so): Ctrl-C reaches the terminal's whole process group, and it is the main
    process's to handle, by stopping them, without a traceback from each."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _stop_workers(pool: ProcessPoolExecutor) -> None:
    """End the pool's processes now rather than after their trees (an interrupt, SIGTERM): none is
    left running, orphaned, with its memory."""
    processes = getattr(pool, "_processes", None) or {}  # the executor's own table (no public one before 3.14)
    for proc in list(processes.values()):
        proc.terminate()
    pool.shutdown(wait=True, cancel_futures=True)


def _run_pool(todo: list[TreeJob], params: Params, until: str, workers: int, finished) -> None:
    """A process pool; a worker that dies (killed for memory, a crash in a library) fails its tree,
    and the others are run again in a new pool (a tree that breaks the pool twice is given up)."""
    attempts = {j.name: 0 for j in todo}
    left = list(todo)
    while left:
        broken: list[TreeJob] = []
        with _one_thread_each(), ProcessPoolExecutor(max_workers=min(workers, len(left)),
                                                     mp_context=get_context("spawn")) as pool:
            try:
                with _workers_ignore_ctrl_c():  # the workers start at submit
                    futures = {pool.submit(run_tree, job, params, until): job for job in left}
                for fut in as_completed(futures):
                    job = futures[fut]
                    try:
                        finished(fut.result())
                    except BrokenProcessPool:
                        broken.append(job)
            except BaseException:
                _stop_workers(pool)
                raise
        left = []
        for job in broken:
            attempts[job.name] += 1
            if attempts[job.name] >= 2:
                finished(_crashed(job, params, until, "the worker process died (out of memory?) twice on this tree"))
            else:
                left.append(job)


def dask_client(address: str):
    """A Dask client of the scheduler at `address`, or one ConfigError line saying why not (no Dask,
    nothing there, another service's port)."""
    try:
        from dask.utils import parse_timedelta
        from distributed import Client
        from distributed.comm.addressing import parse_address, parse_host_port
    except ImportError:
        raise ConfigError("--dask needs Dask: pip install 'treereg[dask]'") from None
    timeout_s = parse_timedelta(DASK_CONNECT_TIMEOUT)
    try:
        scheme, location = parse_address(address)
        if scheme == "tcp":  # tls, ucx, inproc: their own handshakes, bounded by the client's timeout alone
            _probe_scheduler(address, parse_host_port(location), timeout_s)
        return Client(address, timeout=DASK_CONNECT_TIMEOUT)
    except ConfigError:  # the probe's own words (a ConfigError is a ValueError)
        raise
    except (OSError, TimeoutError, ValueError) as e:
        raise ConfigError(f"--dask {address}: cannot reach the Dask scheduler ({e})") from None


#: The most bytes a scheduler's first message (its handshake, some 60 bytes) may announce.
_MAX_HANDSHAKE_BYTES = 64 * 1024


def _probe_scheduler(address: str, host_port: tuple[str, int], timeout_s: float) -> None:
    """Refuse, within `timeout_s`, a peer at `host_port` that does not speak Dask's comm protocol.

    distributed's own handshake waits without end on a peer that says nothing (an HTTP port), and
    allocates whatever length the first 8 bytes of a garbage answer announce ("HTTP/1.1" is 3 EiB).
    A scheduler writes its handshake first, unasked: a message of 8-byte lengths (the message's, the
    frame count's and each frame's) that must agree, checked here before distributed reads it.
    """
    import socket
    import struct

    deadline = time.monotonic() + timeout_s
    with socket.create_connection(host_port, timeout=timeout_s) as sock:
        def read(n: int) -> bytes:
            data = b""
            while len(data) < n:
                sock.settimeout(max(deadline - time.monotonic(), 0.001))
                try:
                    chunk = sock.recv(n - len(data))
                except TimeoutError:
                    raise ConfigError(
                        f"--dask {address}: nothing answered as a Dask scheduler within {timeout_s:g} s (another "
                        "service's port, e.g. the dashboard's or an HTTP server?); give the scheduler's own address, "
                        "which it prints when it starts (tcp://HOST:8786 by default)") from None
                if not chunk:
                    raise ConfigError(f"--dask {address}: the peer closed the connection without answering as a "
                                      "Dask scheduler; give the scheduler's own address (tcp://HOST:8786 by default)")
                data += chunk
            return data

        total, = struct.unpack("=Q", read(8))
        nframes = struct.unpack("=Q", read(8))[0] if 16 <= total <= _MAX_HANDSHAKE_BYTES else 0
        sizes = struct.unpack(f"={nframes}Q", read(8 * nframes)) if 1 <= nframes <= (total - 8) // 8 else ()
        if not sizes or 8 + 8 * nframes + sum(sizes) != total:
            raise ConfigError(f"--dask {address}: the peer answered, but not in Dask's protocol (another service's "
                              "port?); give the scheduler's own address, which it prints when it starts "
                              "(tcp://HOST:8786 by default)")


def _run_dask(todo: list[TreeJob], params: Params, until: str, client, finished) -> None:
    from distributed import as_completed as dask_completed

    futures = {}
    try:
        for job in todo:
            fut = client.submit(run_tree, job, params, until, pure=False, key=f"treereg-{job.name}-{os.getpid()}")
            futures[fut] = job
        for fut in dask_completed(list(futures)):
            job = futures[fut]
            try:
                finished(fut.result())
            except Exception as e:  # noqa: BLE001 - a lost worker (KilledWorker, ...) fails this tree only
                finished(_crashed(job, params, until, f"the Dask worker failed: {type(e).__name__}: {e}"))
    except KeyboardInterrupt:
        client.cancel(list(futures))  # the cluster stops this campaign's trees too
        raise
    finally:
        client.close()
