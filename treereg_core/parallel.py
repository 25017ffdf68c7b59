"""The machine's cores for one registration: pairs, scans and candidate poses computed side by side.

A registration has a budget of `n` workers (`Workers`). Threads where the work releases the GIL
(scipy's k-d tree queries, OpenCV's ORB and morphology, numpy on whole arrays): the scans and
surfaces are shared without a copy and the caches of features, surfaces and range images serve
every pair. Forked processes where it does not: the fitting of sections and the joint adjustment
are thousands of small numpy calls, whose Python between them holds the GIL, so two threads there
ran slower than one (the fine stage of a bent tree, 6.3 s on one thread, 6.7 s on two).

* `Workers.each(fn, n_items, started, fork=...)` — a stage's items (scans or pairs), from the
  pipeline's thread, which says which item starts (`started(k)`, on its own thread: progress
  events never come from a helper). Threads: the pipeline's thread coordinates. Processes
  (`fork=True`, and only where `Workers.may_fork`: a process with no other threads, the command
  line): this thread computes items itself and forks a child per other item, which inherits
  everything computed so far (copy on write: no scan is pickled), computes it and sends its result
  back through a file; a child that dies has its item computed here instead.
* `map(fn, items)` — work inside an item (the hypotheses of a pair, the candidate poses of the
  fine stage): the calling thread computes items itself and lends the rest to threads that are
  free at that moment, so a pair left alone at the end of a stage spreads onto the idle core and
  there are never more than `n` computing.

Results never depend on the number of workers: every item is computed by the same code on the
same inputs whichever thread or process runs it, and results are returned in item order
(`tests/test_parallel.py` compares the transforms of 1 and 2 workers bit for bit). Shared caches
computed twice (by a race, or in a child) hold the same values. With `n` = 1 nothing starts a
thread or a process: a plain loop.

`map` reads the budget of the run it is called in (`using`; a context variable the helper threads
inherit); outside a run it is a plain loop.
"""

from __future__ import annotations

import contextvars
import os
import pickle
import signal
import tempfile
import threading
import time
from contextlib import contextmanager
from typing import Callable, Iterator, Sequence, TypeVar

T = TypeVar("T")
R = TypeVar("R")

#: Work on whole stations (reducing them to the working resolution) runs side by side only for
#: stations up to this many points: its temporaries are the size of a station, and two at once cost
#: more memory than they save time (three 3 M-point stations: peak 0.58 -> 0.68 GB).
SIDE_BY_SIDE_POINTS = 1_500_000

#: How often a thread waiting for others wakes (Ctrl-C reaches the main thread only between waits).
_POLL_S = 0.1
#: How often the parent looks for a finished child while it has nothing else to do.
_REAP_S = 0.002


def fewer_malloc_arenas() -> None:
    """glibc gives every thread its own malloc arena, and memory a thread freed stays in its arena:
    with the pairs on two threads a run's peak memory grew by a fifth (3 x 300 k points: 0.23 ->
    0.28 GB; two arenas: 0.26 GB). The command line asks for two arenas, once, before any thread;
    elsewhere (another C library, another system) nothing happens."""
    try:
        import ctypes
        import ctypes.util

        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.mallopt(_M_ARENA_MAX, 2)
    except (OSError, AttributeError, TypeError):
        pass


#: glibc's mallopt parameter for the number of arenas (malloc.h).
_M_ARENA_MAX = -8


#: Cores the app's run leaves to the browser that shows it (on the same machine, usually) and to
#: the tabs' drawing (`treereg view`). On a 2-core machine (benchmarks/RESULTS.md, issue 20): with
#: one worker the demo's verdicts came at 8.6 and 9.1 s, with two at 9.2 and 9.6 s, and Next
#: answered as quickly or more so.
APP_SPARE_CORES = 1


def default_workers(spare: int = 0) -> int:
    """The machine's cores available to this process (what `--workers` defaults to), less `spare`
    left for other work (the app leaves one to the browser), at least one."""
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, cores - spare)


class Workers:
    """A budget of `n` workers for one registration (n = 1: everything on the caller's thread).
    `may_fork`: GIL-bound stages may fork processes (only in a process with no threads of its own
    besides the caller's: forking copies no other thread, and a lock one of them held stays held
    in the child)."""

    def __init__(self, n: int = 1, may_fork: bool = False, between: Callable[[], None] | None = None) -> None:
        if n < 1:
            raise ValueError(f"workers must be at least 1, got {n}")
        self.n = int(n)
        self.may_fork = bool(may_fork) and hasattr(os, "fork")
        #: Called by every thread before it starts an item (where a run may pause: the app's tabs).
        self.between = between or _nothing
        # Slots for helper threads: the caller of `map` computes with its own, `each` starts all n.
        self._slots = threading.BoundedSemaphore(self.n)
        self._cancelled = threading.Event()

    def __repr__(self) -> str:
        return f"Workers({self.n})"

    def cancel(self) -> None:
        """No new item is started (Ctrl-C): items running finish, their results are dropped."""
        self._cancelled.set()

    # ---- a stage's items, from the pipeline's thread ------------------------------------------
    def each(self, fn: Callable[[int], R], n_items: int, started: Callable[[int], None], *,
             fork: bool = False) -> list[R]:
        """`fn(k)` for k in range(n_items), up to `n` at once; `started(k)` is called on this thread
        as item k starts. Threads: this thread only coordinates (with n = 1 it computes, in
        order). `fork` (honoured where `may_fork`): forked processes instead (`_each_forked`)."""
        if self.n == 1 or n_items <= 1:
            out = []
            for k in range(n_items):
                started(k)
                self.between()
                out.append(fn(k))
            return out
        if fork and self.may_fork and threading.active_count() == 1:
            return self._each_forked(fn, n_items, started)
        results: list[R | None] = [None] * n_items
        errors: list[tuple[int, BaseException]] = []
        finished = threading.Semaphore(0)
        lock = threading.Lock()

        def run(k: int) -> None:
            try:
                self.between()
                results[k] = fn(k)
            except BaseException as e:  # noqa: BLE001 - raised on the coordinating thread
                with lock:
                    errors.append((k, e))
            finally:
                self._slots.release()
                finished.release()

        launched = 0
        try:
            for k in range(n_items):
                while not self._slots.acquire(timeout=_POLL_S):
                    pass
                if errors or self._cancelled.is_set():
                    self._slots.release()
                    break
                started(k)
                _start(run, k)
                launched += 1
            for _ in range(launched):
                while not finished.acquire(timeout=_POLL_S):
                    pass
        except BaseException:
            self.cancel()  # Ctrl-C while waiting: the running items are abandoned, none started
            raise
        if errors:
            raise min(errors, key=lambda e: e[0])[1]
        return results  # type: ignore[return-value]

    def _each_forked(self, fn: Callable[[int], R], n_items: int, started: Callable[[int], None]) -> list[R]:
        """Items in forked children (up to n - 1 at once) while this process computes items too."""
        results: list[R | None] = [None] * n_items
        running: dict[int, tuple[int, str]] = {}  # pid -> (item, result file)
        todo = list(range(n_items))

        def one(k: int) -> R:
            # Each process computes its item on its own thread: n processes, not n x n threads.
            token = _current.set(SERIAL)
            try:
                return fn(k)
            finally:
                _current.reset(token)

        def launch() -> None:
            k = todo.pop(0)
            started(k)
            fd, path = tempfile.mkstemp(prefix="treereg-item-")
            os.close(fd)
            pid = os.fork()
            if pid == 0:  # the child: compute, write, leave without running any clean-up of the parent's
                code = 1
                try:
                    signal.signal(signal.SIGINT, signal.SIG_DFL)  # Ctrl-C ends it; the parent says so
                    try:
                        out: tuple[str, object] = ("ok", one(k))
                    except Exception as e:  # noqa: BLE001 - raised again in the parent
                        out = ("error", e)
                    with open(path, "wb") as fh:
                        try:
                            pickle.dump(out, fh, protocol=pickle.HIGHEST_PROTOCOL)
                        except Exception as e:  # noqa: BLE001 - an exception that does not pickle
                            fh.seek(0)
                            fh.truncate()
                            pickle.dump(("error", RuntimeError(f"{type(out[1]).__name__}: {out[1]}")), fh)
                    code = 0
                finally:
                    os._exit(code)
            running[pid] = (k, path)

        def reap(block: bool) -> None:
            """Collect the children that finished (with `block`, wait for one)."""
            while True:
                done = [(pid, st) for pid in list(running) for got, st in [os.waitpid(pid, os.WNOHANG)] if got]
                if done or not block:
                    break
                time.sleep(_REAP_S)
            for pid, status in done:
                k, path = running.pop(pid)
                try:
                    with open(path, "rb") as fh:
                        kind, value = pickle.load(fh) if os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0 \
                            else ("died", None)
                except (OSError, EOFError, pickle.UnpicklingError):
                    kind, value = "died", None
                finally:
                    _unlink(path)
                if kind == "error":
                    raise value  # type: ignore[misc]
                # A child that died (killed for memory, a crash in a library): its item is computed here.
                results[k] = value if kind == "ok" else one(k)

        try:
            while todo or running:
                while todo and len(running) < self.n - 1:
                    launch()
                if todo:
                    k = todo.pop(0)
                    started(k)
                    results[k] = one(k)
                    reap(block=False)
                else:
                    reap(block=True)
        except BaseException:
            for pid, (_, path) in running.items():
                _kill(pid)
                _unlink(path)
            raise
        return results  # type: ignore[return-value]

    # ---- work inside an item ----------------------------------------------------------------
    def map(self, fn: Callable[[T], R], items: Sequence[T]) -> list[R]:
        """`[fn(x) for x in items]`, the calling thread computing and lending items to free threads."""
        n = len(items)
        if self.n == 1 or n <= 1:
            return [fn(x) for x in items]  # the item's own thread: its pauses are the item's
        results: list[R | None] = [None] * n
        errors: list[tuple[int, BaseException]] = []
        lock = threading.Lock()
        state = {"next": 0, "helpers": 0}
        done = threading.Condition(lock)

        def take() -> int | None:
            with lock:
                if errors or self._cancelled.is_set() or state["next"] >= n:
                    return None
                i = state["next"]
                state["next"] += 1
                return i

        def work() -> None:
            while (i := take()) is not None:
                lend()
                self.between()
                try:
                    results[i] = fn(items[i])
                except BaseException as e:  # noqa: BLE001 - raised on the calling thread
                    with lock:
                        errors.append((i, e))

        def helper() -> None:
            try:
                work()
            finally:
                self._slots.release()
                with done:
                    state["helpers"] -= 1
                    done.notify_all()

        def lend() -> None:
            # One more thread when items are left and a slot is free now (never waits for one).
            with lock:
                left = state["next"] < n
            if left and self._slots.acquire(blocking=False):
                with lock:
                    state["helpers"] += 1
                _start(helper)

        try:
            work()
            with done:
                while state["helpers"]:
                    done.wait(_POLL_S)
        except BaseException:
            self.cancel()
            raise
        if errors:
            raise min(errors, key=lambda e: e[0])[1]
        return results  # type: ignore[return-value]


def _nothing() -> None:
    """The default `between`: no pause."""


def _kill(pid: int) -> None:
    try:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
    except (ProcessLookupError, ChildProcessError):
        pass


def _unlink(path: str) -> None:
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass


def _start(target: Callable[..., None], *args: object) -> None:
    """A daemon thread running `target(*args)` in a copy of this thread's context (its budget):
    daemon, so Ctrl-C ends the process without waiting for a pair half computed."""
    ctx = contextvars.copy_context()
    threading.Thread(target=ctx.run, args=(target, *args), daemon=True, name="treereg-worker").start()


SERIAL = Workers(1)
_current: contextvars.ContextVar[Workers] = contextvars.ContextVar("treereg_workers", default=SERIAL)


def current() -> Workers:
    """The budget of the run this thread works for (serial outside a run)."""
    return _current.get()


@contextmanager
def using(workers: Workers) -> Iterator[Workers]:
    """Run the block with `workers` as the current budget (what `map` uses), the BLAS library on
    one thread each (`one_blas_thread`)."""
    token = _current.set(workers)
    try:
        with one_blas_thread():
            yield workers
    finally:
        _current.reset(token)


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """The BLAS library (OpenBLAS under numpy and scipy) on one thread while inside.

    A registration's matrix products are small (a section's 300 x 13 rows, 20 000 points by a
    3 x 3 rotation): waking BLAS's own threads for them cost more than they saved (a run's CPU time
    7.7 s against 6.3 s on 3 x 300 k points, the wall time the same), and with the pairs already
    spread over the cores they only compete. Results do not depend on it (the same transforms to
    the last bit on the benchmark trees)."""
    from threadpoolctl import threadpool_limits  # type: ignore[import-untyped]  # global: only while a run lasts

    with threadpool_limits(limits=1, user_api="blas"):
        yield


def map(fn: Callable[[T], R], items: Sequence[T]) -> list[R]:  # noqa: A001 - the module's verb
    """`[fn(x) for x in items]` on the current run's threads (`Workers.map`)."""
    return _current.get().map(fn, items)
