"""Responsive from the first second (issue 18, point 8), in headless Chromium.

A fresh app on the demo in this process, as `treereg view` starts it: the pipeline starts its run
as the page opens. While the run computes, the first view must be drawn within 3 s of the page
opening and Next must answer (the panel's heading names the next stage) within 1 s (on a machine
where the browser alone is slower: at most half again what an idle app takes); once every
stage is done no view may keep redrawing itself. Debian's Chromium through Playwright, offline-
guarded, WebGL on SwiftShader (see tests/conftest.py). `-s` prints the times.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import pytest

pytestmark = [pytest.mark.browser, pytest.mark.timed]

pytest.importorskip("playwright.sync_api")

import viser  # noqa: E402
from browser import offline  # noqa: E402

from treereg_core.demo import demo_case  # noqa: E402
from treereg_core.params import Params  # noqa: E402
from treereg_viewer.app import TreeregApp  # noqa: E402
from treereg_viewer.controller import Controller  # noqa: E402
from treereg_viewer.labels import label  # noqa: E402

#: What issue 18 asks: the first view within 3 s, Next within 1 s (measured then: first view 2.0–2.6 s,
#: Next 0.2–0.5 s). These hold where the browser alone is that quick; on a slower machine the same
#: page of an app at rest (its run finished before the page opened, measured in the same browser
#: just before) takes longer: 2.6–3.6 s for the first view on the 2-core machine of issue 20, 3.1–5.3 s
#: and a Next of 0.24–0.81 s on a later one, varying by up to 1.0 s from page to page. There the run
#: may slow what the browser does at rest by at most RUN_SLOWS (it shares the two cores with the
#: browser for as long as the browser works): against the slower of the idle app's attempts. A run
#: that held the first view or a Next back for its stages would add several seconds.
FIRST_VIEW_S = 3.0
NEXT_S = 1.0
RUN_SLOWS = 1.5
#: Seconds a person looks at the first view before pressing Next.
LOOK_S = 1.0
#: Once done, a view watched this long gets nothing from the app and draws only viser's heartbeat
#: (the client's safety net: one frame a second; a frame on SwiftShader can take most of a second,
#: so a run of frames is not told from heartbeats by counting alone).
QUIET_S = 2.0

FRAME = "() => window.__viserTestpoints?.rendererInfo?.render?.frame ?? -1"
#: The docked panel's heading names stage `l` ('2 Projection', '4 Coarse: scan2.ply → scan1.ply ...').
HEADING = ("(l) => [...document.querySelectorAll('h3')].some(h => h.textContent === l || "
           "h.textContent.startsWith(l + ':') || h.textContent.startsWith(l + ' '))")
#: Every stage done: the status line names them all and none is stale (○) or running (…).
FINISHED = ("() => [...document.querySelectorAll('p')].map(p => p.textContent).some(t => t.includes('1 Scans') && "
            "t.includes('13 Result') && t.includes(' · ') && !/[○…] \\d+ [A-Z]/.test(t))")


@dataclass
class AtRest:
    """The slower of two attempts at each action on an app that is not computing."""

    first_view_s: float
    next_s: float


@dataclass
class FirstRun:
    page: object
    blocked: list[str]
    first_view_s: float
    nexts: list[tuple[str, bool, float]] = field(default_factory=list)  # (stage asked, worker busy, seconds)
    next_at: list[float] = field(default_factory=list)  # the Next button's top (px) at the first view and at each press
    received: list[float] = field(default_factory=list)  # time.perf_counter() of each websocket message
    at_rest: AtRest | None = None  # the same page of an app that is not computing


def _next_top(page) -> float:
    return page.get_by_role("button", name="Next", exact=True).bounding_box()["y"]


def _next(page, asked: str) -> float:
    """Press Next as a person does (a click where the button is) and time until the heading names `asked`."""
    box = page.get_by_role("button", name="Next", exact=True).bounding_box()
    t0 = time.perf_counter()
    page.mouse.click(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    page.wait_for_function(HEADING, arg=asked, timeout=30_000)
    return time.perf_counter() - t0


def _first_view(page, url: str, demo) -> float:
    """Seconds from opening the page to a frame drawn with the scans in it."""
    t0 = time.perf_counter()
    page.goto(url)
    nodes = " && ".join(f"!!m.nodeRefFromName['/scans/s{i}/points']" for i in range(len(demo.scans)))
    page.wait_for_function(f"() => {{ const m = window.__viserMutable; return !!m && {nodes}; }}")
    drawn = page.evaluate(FRAME)
    page.wait_for_function(f"() => ({FRAME})() > {drawn}")  # a frame with the scans in it
    return time.perf_counter() - t0


#: The stages Next is pressed to, in turn, after the first view.
PRESSED = ("projection", "matching")


def _look_and_press(page, before=lambda stage: None) -> list[float]:
    """For each of PRESSED: look at the view LOOK_S, call `before(stage)`, press Next; the seconds
    each Next took."""
    times = []
    for stage in PRESSED:
        page.wait_for_timeout(int(LOOK_S * 1000))
        before(stage)
        times.append(_next(page, label(stage)))
    return times


@pytest.fixture(scope="module")
def at_rest(browser) -> AtRest:
    """The same page of an app whose run has finished before the page opens (two attempts): what
    the browser and the app take to show the first view, and to answer Next, without computing."""
    demo = demo_case()
    controller = Controller(list(demo.scans), truth=demo.truth)
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = TreeregApp(server, controller, tabs="each")
    views, nexts = [], []
    try:
        assert controller.wait_idle(120)
        for _ in range(2):
            context = browser.new_context(viewport={"width": 1600, "height": 1000})
            offline(context)
            page = context.new_page()
            page.set_default_timeout(60_000)
            views.append(_first_view(page, f"http://127.0.0.1:{server.get_port()}/", demo))
            nexts += _look_and_press(page)
            context.close()
    finally:
        app.close()
        server.stop()
    print(f"\n  an app at rest: first view {', '.join(f'{t:.2f}' for t in views)} s, "
          f"Next {', '.join(f'{t:.2f}' for t in nexts)} s")
    return AtRest(max(views), max(nexts))


@pytest.fixture(scope="module")
def first_run(browser, at_rest):
    """The demo's first run in a fresh app, the page opened as it starts: first view, then Next twice
    while the pipeline computes. Yields the measurements and the page (the run goes on)."""
    demo = demo_case()
    context = browser.new_context(viewport={"width": 1600, "height": 1000})
    blocked = offline(context)
    page = context.new_page()
    page.set_default_timeout(60_000)
    received: list[float] = []
    page.on("websocket", lambda ws: ws.on("framereceived", lambda _: received.append(time.perf_counter())))
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    # ICP on every point, not on 2 cm voxels: the run's last stages take a second longer, so that
    # Next is pressed while it computes (the demo's run ends some 5 s after the page opens).
    params = Params().with_value("icp", "voxel_m", 0.0)
    app = TreeregApp(server, Controller(list(demo.scans), params, truth=demo.truth), tabs="each")
    try:
        run = FirstRun(page, blocked, _first_view(page, f"http://127.0.0.1:{server.get_port()}/", demo),
                       received=received, at_rest=at_rest)
        print(f"\n  first view {run.first_view_s:.2f} s")
        run.next_at.append(_next_top(page))
        busy: list[bool] = []

        def before(stage: str) -> None:
            busy.append(app.controller.snapshot.busy)
            run.next_at.append(_next_top(page))
        times = _look_and_press(page, before)
        run.nexts = [(label(stage), b, t) for stage, b, t in zip(PRESSED, busy, times)]
        for stage, b, t in run.nexts:
            print(f"  Next to {stage}: {t:.2f} s (worker computing: {b})")
        yield run
    finally:
        context.close()
        app.close()
        server.stop()


def test_the_first_view_is_drawn_within_3_s_while_the_run_starts(first_run):
    """Within 3 s, or, where the browser alone takes longer, at most RUN_SLOWS times an app at rest."""
    rest = first_run.at_rest.first_view_s
    limit = max(FIRST_VIEW_S, RUN_SLOWS * rest)
    assert first_run.first_view_s < limit, f"the first view took {first_run.first_view_s:.2f} s (an app at rest {rest:.2f} s)"
    assert not first_run.blocked, f"the page tried to load {first_run.blocked}"


def test_next_answers_within_1_s_while_a_stage_computes(first_run):
    # The run is fast enough now (issue 20) that it may end before the second press: the first
    # must fall within it, and every press is held to the second.
    assert first_run.nexts[0][1], f"the run ended before Next was pressed: {first_run.nexts}"
    # The run's news above the buttons once moved Next under the pointer: a click aimed at it missed.
    assert len(set(first_run.next_at)) == 1, f"Next moved while the run went on: top at {first_run.next_at} px"
    rest = first_run.at_rest.next_s
    slow = [(stage, round(s, 2)) for stage, _, s in first_run.nexts if s >= max(NEXT_S, RUN_SLOWS * rest)]
    assert not slow, f"Next answered late: {slow} (an app at rest: {rest:.2f} s)"


def _frames(page, seconds: float) -> list[list[float]]:
    """The renderer's frame counter sampled every 100 ms for `seconds`: [[ms, frame], ...]."""
    page.evaluate("() => { window.__quiet = []; window.__quietTimer = setInterval(() => window.__quiet.push("
                  "[performance.now(), window.__viserTestpoints.rendererInfo.render.frame]), 100); }")
    page.wait_for_timeout(int(seconds * 1000))
    return page.evaluate("() => { clearInterval(window.__quietTimer); return window.__quiet; }")


def _settle(page, quiet_ms: int = 400, timeout_s: float = 10.0) -> None:
    """Wait until no frame was drawn for `quiet_ms` (a view still drawing after `timeout_s` fails)."""
    deadline, last = time.monotonic() + timeout_s, page.evaluate(FRAME)
    while time.monotonic() < deadline:
        page.wait_for_timeout(quiet_ms)
        if (now := page.evaluate(FRAME)) == last:
            return
        last = now
    pytest.fail(f"the view was still drawing {timeout_s} s after it was chosen")


def test_no_view_keeps_redrawing_once_every_stage_is_done(first_run):
    page = first_run.page
    page.wait_for_function(FINISHED, timeout=120_000, polling=100)
    for stage in ("hypotheses", "sections"):  # the views reported to keep redrawing
        page.get_by_label("Stage", exact=True).click()
        page.get_by_role("option", name=label(stage), exact=True).click()
        page.wait_for_function(HEADING, arg=label(stage))
        _settle(page)  # the redraw the choice asked for (the camera glides to the registered tree)
        t0, f0 = time.perf_counter(), page.evaluate(FRAME)
        page.wait_for_timeout(int(QUIET_S * 1000))
        drawn, t1 = page.evaluate(FRAME) - f0, time.perf_counter()
        sent = sum(t0 <= t <= t1 for t in first_run.received)
        print(f"  {label(stage)}: {sent} messages from the app and {drawn} frames in {t1 - t0:.1f} s")
        assert sent == 0, f"{label(stage)}: the app kept sending ({sent} messages in {QUIET_S} s)"
        assert drawn <= QUIET_S + 1, f"{label(stage)} kept redrawing: {drawn} frames in {QUIET_S} s"
