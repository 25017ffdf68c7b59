"""The worker gives way to a tab opening while it computes (issue 18: the first view within 3 s),
within bounds: at most GIVE_WAY_MAX_S at a time, and not again before it has run GIVE_WAY_GAP_S."""

from __future__ import annotations

import pytest

from treereg_core.demo import demo_case
from treereg_viewer.controller import GIVE_WAY_GAP_S, GIVE_WAY_MAX_S, Controller


@pytest.mark.slow
@pytest.mark.timed
def test_the_worker_pauses_for_a_tab_at_most_so_long_then_runs_on():
    demo = demo_case()
    ctl = Controller(list(demo.scans), truth=demo.truth)
    try:
        ctl.give_way(10 * GIVE_WAY_MAX_S)  # a tab asking far too much
        ctl.request_run("projection")
        assert ctl.wait_idle(60)
        assert GIVE_WAY_MAX_S - 0.1 <= ctl.paused_s <= GIVE_WAY_MAX_S + 0.5
        assert ctl.snapshot.status("projection") == "done"
        # Asked again at once (within GIVE_WAY_GAP_S of the last pause): the worker runs on.
        assert GIVE_WAY_GAP_S > 1.0
        before = ctl.paused_s
        ctl.give_way(1.0)
        ctl.request_run("matching")
        assert ctl.wait_idle(60)
        assert ctl.paused_s == before and ctl.snapshot.status("matching") == "done"
    finally:
        ctl.close()
