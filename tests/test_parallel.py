"""Both cores: pairs and scans side by side (threads, or forked processes on the command line), with
results identical to one worker's, bit for bit."""

import json
import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from treereg_core import parallel
from treereg_core.params import Params
from treereg_core.pipeline import Pipeline
from treereg_core.simulate.cases import benchmark_cases, write_case
from treereg_core.stages import STAGE_NAMES

from conftest import ROOT


@pytest.fixture(scope="module")
def case():
    # Three scans: three pairs, so a stage's items outnumber two workers.
    return benchmark_cases(3, seed=0, small=True)[0].build()


def _run(case, workers, fork=False):
    pipe = Pipeline(list(case.scans), Params(), workers=workers, fork=fork)
    pipe.run("graph")
    return pipe


@pytest.mark.slow
def test_two_threads_give_the_transforms_and_verdicts_of_one_bit_for_bit(case):
    one, two = _run(case, 1), _run(case, 2)
    t1, t2 = one.transforms(), two.transforms()
    assert t1.keys() == t2.keys() and len(t1) == len(case.scans)
    for name in t1:
        assert np.array_equal(t1[name], t2[name]), name
    assert one.verdicts() == two.verdicts()
    # Every stage's metrics too (what transforms.json and the app list).
    assert one.pair_metrics() == two.pair_metrics()


@pytest.mark.slow
def test_register_with_two_workers_writes_what_one_worker_writes(case, tmp_path):
    """The command line forks processes for its GIL-bound stages: still the same numbers."""
    folder = tmp_path / "case"
    write_case(case, folder)
    files = [str(folder / s.name) for s in case.scans]
    out = {}
    for n in (1, 2):
        dest = tmp_path / f"w{n}.json"
        proc = subprocess.run([sys.executable, "-m", "treereg_cli", "register", *files, "--out", str(dest),
                               "--workers", str(n)], cwd=ROOT, capture_output=True, text=True, timeout=600)
        assert proc.returncode in (0, 1), proc.stderr
        out[n] = json.loads(dest.read_text())
    assert out[1]["transforms"] == out[2]["transforms"]
    assert out[1]["quality"] == out[2]["quality"]
    assert not list(tmp_path.glob("treereg-item-*"))


def test_workers_out_of_range_is_one_line_naming_the_option(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "treereg_cli", "register", "a.ply", "b.ply", "--workers", "0",
                           "--out", str(tmp_path / "t.json")], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.strip() == "treereg: error: --workers must be between 1 and 1024, got 0"
    assert not (tmp_path / "t.json").exists()


# ---- the workers themselves ------------------------------------------------------------------
def test_each_keeps_item_order_and_tells_each_start_on_the_callers_thread():
    caller = threading.current_thread()
    seen = []
    w = parallel.Workers(2)

    def started(k):
        assert threading.current_thread() is caller
        seen.append(k)

    out = w.each(lambda k: (time.sleep(0.02 * (3 - k)), k * k)[1], 4, started)
    assert out == [0, 1, 4, 9]
    assert sorted(seen) == [0, 1, 2, 3]


def test_never_more_than_n_compute_at_once_even_nested():
    w = parallel.Workers(2)
    busy, peak, lock = [0], [0], threading.Lock()

    def leaf(x):
        with lock:
            busy[0] += 1
            peak[0] = max(peak[0], busy[0])
        time.sleep(0.01)
        with lock:
            busy[0] -= 1
        return x

    def item(k):
        with parallel.using(w):
            return sum(parallel.map(leaf, list(range(6))))

    assert w.each(item, 3, lambda k: None) == [15, 15, 15]
    assert peak[0] <= 2


def test_the_first_items_error_is_raised():
    w = parallel.Workers(2)

    def fn(k):
        if k in (1, 2):
            raise ValueError(f"item {k}")
        return k

    with pytest.raises(ValueError, match="item 1"):
        w.each(fn, 4, lambda k: None)
    with pytest.raises(ValueError, match="item 1"):
        with parallel.using(parallel.Workers(2)):
            parallel.map(fn, [0, 1, 2, 3])


#: Run in a fresh interpreter: the workers fork only in a process without other threads, and by the
#: time the suite reaches this module earlier tests have left some (a skip here never ran in CI).
FORKED_ITEMS = """
import os
from treereg_core import parallel

parent = os.getpid()
w = parallel.Workers(2, may_fork=True)

def fn(k):
    if k == 1 and os.getpid() != parent:
        os._exit(9)  # a child killed mid-item (out of memory, a crash in a library)
    return (k, os.getpid() != parent)

out = w.each(fn, 3, lambda k: None, fork=True)
assert [k for k, _ in out] == [0, 1, 2], out
assert out[0][1] is True, out  # item 0 came back from a child
assert out[1][1] is False, out  # the child computing item 1 died: computed here

def bad(k):
    raise KeyError(f"no such thing {k}")

try:
    w.each(bad, 2, lambda k: None, fork=True)
except KeyError:
    print("ok")
"""


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_forked_items_come_back_and_a_dead_child_is_computed_again_here():
    res = subprocess.run([sys.executable, "-c", FORKED_ITEMS], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and res.stdout.strip() == "ok", res.stdout + res.stderr


def test_every_stage_declares_how_its_items_run_side_by_side():
    from treereg_core.stages import stage
    forked = [s for s in STAGE_NAMES if stage(s).processes]
    assert forked == ["sections", "fine"]
