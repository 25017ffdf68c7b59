"""How quickly the app answers in the browser: re-runs after a parameter change (issue 13) and
responsiveness from the first second (issue 18, point 8).

The app serves the case (a viewer per tab) in this process; headless Chromium (Debian's
/usr/bin/chromium, SwiftShader) opens it. Prints markdown tables.

Re-run (the demo): waits until every stage is done, then for each change steps to the stage, types
the new value, presses Run and times until the status line marks the stage done again (the app
publishes each stage as it finishes, so the stage is shown before the later ones have run). The
baseline, in the same process: the same stages run by the `Pipeline` alone, without app or browser;
the ratio is browser / pipeline.

Responsiveness (the demo, and an awkward 3-scan case with leaves and ground): the app starts (it
runs the whole pipeline at once) and the page opens at the same moment, as with `treereg view`.
Timed from `page.goto`: the first view drawn (every scan's points node exists and a frame was
rendered after it), all verdicts (the status line marks 11 Placement done), every stage done (both
noted by a watcher in the page while the bench drives it). While the pipeline computes, Next is
pressed a few times, a second after each view was shown (a click where the button is), and timed
until the panel's heading names the next stage; as ICP starts (the verdicts are published then),
Verify and Placement are chosen in the Stage list and timed the same way. Once every stage is
done, the renderer's frame counter is sampled every 100 ms on the view the tab is on, then on
Hypotheses and Fits: the longest stretch of samples in which frames kept being drawn without input
(viser's client draws a heartbeat frame once a second, so a lone frame reads 0.1 s). From the
app's side: when the first snapshot with the graph output (the verdicts) was published, ICP's start
and end, and how long the worker gave way to the tab.

    python benchmarks/bench_app_rerun.py [--repeats 3] [--part both|rerun|responsive]
                                         [--case both|demo|awkward] [--nexts 4] [--idle 8]

To measure another checkout (a worktree of an older commit), run this file with that checkout
first on PYTHONPATH: `cd /tmp/base && PYTHONPATH=/tmp/base python3 /work/main/benchmarks/bench_app_rerun.py`.
"""

from __future__ import annotations

import argparse
import re
import statistics
import sys
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Iterator

# Appended, not inserted: a checkout given on PYTHONPATH is the one measured.
sys.path.append(str(Path(__file__).resolve().parents[1]))

import viser  # noqa: E402
from playwright.sync_api import expect, sync_playwright  # noqa: E402

import treereg_core  # noqa: E402
from treereg_core.demo import demo_case  # noqa: E402
from treereg_core.pipeline import Pipeline  # noqa: E402
from treereg_viewer.app import TreeregApp  # noqa: E402
from treereg_viewer.controller import Controller, Snapshot  # noqa: E402
from treereg_viewer.labels import STAGE_NAMES, label  # noqa: E402

ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync",
        "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
#: (what changes, stage label, parameter label in the app, section, field, values to alternate, stages it re-runs
#: until the stage is shown)
CHANGES = (
    ("arcs.min_points", "7 Arcs", "min points", "arcs", "min_points", (25, 15), ("arcs",)),
    ("sections.min_arc_deg", "8 Fits", "min arc (deg)", "sections", "min_arc_deg", (40.0, 45.0), ("sections",)),
    ("evaluation.layer_spacing_m", "13 Result", "layer spacing (m)", "evaluation", "layer_spacing_m", (0.16, 0.15),
     ("evaluation",)),
)
DONE = ("() => [...document.querySelectorAll('p, div')].some(e => /✓ 13 Result/.test(e.textContent) && "
        "!/[○…✗]/.test(e.textContent) && /1 Scans/.test(e.textContent))")
SHOWN = ("(l) => [...document.querySelectorAll('p, div')].some(e => e.textContent.includes('✓ ' + l) && "
         "/1 Scans/.test(e.textContent) && !e.textContent.includes('○ ' + l) && !e.textContent.includes('… ' + l))")

# ---- responsiveness: what the page is asked -------------------------------------------------------
#: The status line: the shortest element text naming the first and the last stage with the marks' separator
#: (the Stage list's options name them too, without it).
_STATUS = ("(() => { let best = null; for (const e of document.querySelectorAll('p, div')) { const t = e.textContent; "
           "if (t.includes('1 Scans') && t.includes('13 Result') && t.includes(' · ') && "
           "(best === null || t.length < best.length)) best = t; } return best; })()")
#: The verdicts are in: 11 Placement finished (✓, or ⚠/✗ when it warned or failed).
PLACED = f"() => {{ const t = {_STATUS}; return !!t && /[✓⚠✗] 11 Placement/.test(t); }}"
#: Every stage finished: none stale (○) or running (…).
FINISHED = f"() => {{ const t = {_STATUS}; return !!t && !/[○…] \\d+ [A-Z]/.test(t); }}"
#: The docked panel's heading names stage `l` ('4 Coarse', '4 Coarse: scan2 → scan1 ✓ verified').
HEADING = ("(l) => [...document.querySelectorAll('h3')].some(h => h.textContent === l || "
           "h.textContent.startsWith(l + ':') || h.textContent.startsWith(l + ' '))")
FRAME = "() => window.__viserTestpoints?.rendererInfo?.render?.frame ?? -1"
SAMPLE_START = ("() => { window.__treeregFrames = []; window.__treeregTimer = setInterval(() => window.__treeregFrames"
                ".push([performance.now(), window.__viserTestpoints.rendererInfo.render.frame]), 100); }")
SAMPLE_STOP = "() => { clearInterval(window.__treeregTimer); return window.__treeregFrames; }"
#: Views sampled for redraws once everything is done (besides the one the tab is on).
IDLE_VIEWS = ("hypotheses", "sections")


def pipeline_seconds(scans, truth, section: str, field: str, value, stages: tuple[str, ...]) -> float:
    """The baseline: the stages a change re-runs, by the pipeline alone (no app, no browser)."""
    pipe = Pipeline(list(scans), truth=truth)
    pipe.run("evaluation")
    p = pipe.params
    pipe.set_params(replace(p, **{section: replace(getattr(p, section), **{field: value})}))
    t0 = time.perf_counter()
    pipe.run(stages[-1])
    return time.perf_counter() - t0


@contextmanager
def served(scans, truth) -> Iterator[tuple[TreeregApp, str]]:
    """The app on a fresh server (it starts the whole run at once); yields it and its URL."""
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = TreeregApp(server, Controller(list(scans), truth=truth), tabs="each")
    try:
        yield app, f"http://127.0.0.1:{server.get_port()}/"
    finally:
        app.close()
        server.stop()


def rerun_rows(browser, repeats: int) -> list[tuple]:
    demo = demo_case()
    rows = []
    with served(demo.scans, demo.truth) as (app, url):
        page = browser.new_page(viewport={"width": 1600, "height": 1000})
        page.set_default_timeout(120_000)
        page.goto(url)
        page.wait_for_function(DONE, timeout=300_000)
        for name, stage, label_text, section, fld, values, stages in CHANGES:
            choose_stage(page, stage)
            seen = []
            for k in range(repeats):
                page.wait_for_function(DONE)
                # Parameters are text inputs, not tied to their label element: the input beside it.
                box = page.locator("label", has_text=re.compile(f"^{re.escape(label_text)}$")).filter(visible=True).locator(
                    "xpath=ancestor::div[.//input][1]//input").first
                box.fill(str(values[k % 2]))
                box.press("Enter")
                # The stage is stale (○) now: Run brings it back (✓).
                expect(page.get_by_text("Parameters changed", exact=False)).to_be_visible(timeout=60_000)
                t0 = time.perf_counter()
                page.get_by_role("button", name="Run", exact=True).click()
                page.wait_for_function(SHOWN, arg=stage)
                seen.append(time.perf_counter() - t0)
            base = statistics.median(pipeline_seconds(demo.scans, demo.truth, section, fld, values[k % 2], stages)
                                     for k in range(repeats))
            rows.append((name, stage, statistics.median(seen), min(seen), base))
        page.close()
    return rows


def print_rerun(rows: list[tuple], repeats: int) -> None:
    print(f"\nRe-run after a parameter change, the demo (3 scans), median of {repeats} "
          "(from pressing Run until the stage shows done in the browser):\n")
    print("| parameter changed | stage shown | seen in the browser (s), median | best (s) | pipeline alone (s) | ratio |")
    print("|---|---|---|---|---|---|")
    for name, stage, med, best, base in rows:
        print(f"| {name} | {stage} | {med:.2f} | {best:.2f} | {base:.2f} | {med / max(base, 1e-9):.1f} |")


# ---- responsiveness -----------------------------------------------------------------------------------
def load_case(name: str) -> tuple[str, list[Any], Any]:
    if name == "demo":
        d = demo_case()
        return "the demo", list(d.scans), d.truth
    from treereg_core.simulate.cases import benchmark_cases

    c = benchmark_cases(24, 0)[0].build()
    return "awkward (leaves, ground)", list(c.scans), c.truth()


@dataclass
class AppLog:
    """What the app published, seen from this process: (time, running stage, graph output in it, busy)."""

    events: list[tuple[float, str | None, bool, bool]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)
    t0: float = 0.0  # time.perf_counter() at page.goto

    def __call__(self, snap: Snapshot) -> None:
        with self.lock:
            self.events.append((time.perf_counter(), snap.running, "graph" in snap.outputs, snap.busy))

    def first(self, pred) -> float | None:
        with self.lock:
            return next((t for t, running, graph, busy in self.events if pred(running, graph, busy)), None)

    def since(self, pred) -> float | None:
        """Seconds from page.goto to the first snapshot `pred` holds for."""
        t = self.first(pred)
        return None if t is None else t - self.t0


@dataclass
class Responsive:
    case: str
    points: int
    first_view: float = float("nan")
    nexts: list[tuple[str, str | None, float]] = field(default_factory=list)  # (stage asked, stage computing, seconds)
    placed: float = float("nan")
    during_icp: list[tuple[str, float, bool]] = field(default_factory=list)  # (stage chosen, seconds, ICP throughout)
    finished: float = float("nan")
    idle: list[tuple[str, float, float]] = field(default_factory=list)  # (view, longest stretch s, frames per second)
    graph_published: float | None = None  # seconds after page.goto
    icp_started: float | None = None
    icp_ended: float | None = None
    graph_before_icp: bool = False
    paused: float | None = None  # seconds the worker gave way to the tab (None: a checkout without it)


def say(text: str) -> None:
    """Progress, on stderr (the tables go to stdout)."""
    print(text, file=sys.stderr, flush=True)


def choose_stage(page, stage_label: str) -> None:
    page.get_by_label("Stage", exact=True).click()
    page.get_by_role("option", name=stage_label, exact=True).click()


def press_next(page) -> Callable[[], None]:
    """A press of Next as a person makes it: a click where the button is (found before the timing starts)."""
    box = page.get_by_role("button", name="Next", exact=True).bounding_box()
    return lambda: page.mouse.click(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)


def timed_heading(page, act, stage_label: str) -> float:
    """Seconds from starting `act()` until the panel's heading names `stage_label`."""
    t0 = time.perf_counter()
    act()
    page.wait_for_function(HEADING, arg=stage_label, timeout=120_000)
    return time.perf_counter() - t0


def longest_stretch(samples: list[list[float]]) -> float:
    """The longest run of consecutive samples (ms, frame) in which the frame counter grew, in s."""
    best, start = 0.0, None
    for (t0, f0), (t1, f1) in zip(samples, samples[1:]):
        if f1 > f0:
            start = t0 if start is None else start
            best = max(best, t1 - start)
        else:
            start = None
    return best / 1000.0


def idle_redraws(page, view: str, seconds: float) -> tuple[str, float, float]:
    page.evaluate(SAMPLE_START)
    page.wait_for_timeout(int(seconds * 1000))
    samples = page.evaluate(SAMPLE_STOP)
    span = max((samples[-1][0] - samples[0][0]) / 1000.0, 1e-9) if len(samples) > 1 else float("nan")
    frames = samples[-1][1] - samples[0][1] if len(samples) > 1 else 0
    return view, longest_stretch(samples), frames / span


def watch_status() -> str:
    """A script for every page of the context: notes (Date.now(), ms) when the status line first shows the verdicts
    in and every stage done, while the bench drives the page meanwhile."""
    return (f"window.__treeregSeen = {{}}; setInterval(() => {{ const s = window.__treeregSeen; "
            f"if (!s.placed && ({PLACED})()) s.placed = Date.now(); "
            f"if (!s.finished && ({FINISHED})()) s.finished = Date.now(); }}, 50);")


def seen(page, what: str, t0_epoch: float) -> float:
    """Seconds from `t0_epoch` (time.time() at page.goto) until the page's watcher saw `what`."""
    page.wait_for_function(f"() => !!window.__treeregSeen?.{what}", timeout=900_000, polling=100)
    return page.evaluate(f"() => window.__treeregSeen.{what}") / 1000.0 - t0_epoch


def wait_running(ctl: Controller, stage: str, timeout_s: float = 600.0) -> bool:
    """Wait until the worker computes `stage` (True), or has gone past it (False)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        snap = ctl.snapshot
        if snap.running == stage:
            return True
        if not snap.busy or (snap.running and STAGE_NAMES.index(snap.running) > STAGE_NAMES.index(stage)):
            return False
        time.sleep(0.01)
    return False


@contextmanager
def opened(browser, scans, truth) -> Iterator[tuple[Any, Controller, AppLog, float, float]]:
    """A fresh app on `scans` (its run starts) and a page opened on it at once; waits for the first view.
    Yields (page, controller, what the app published, seconds to the first view, time.time() at page.goto)."""
    context = browser.new_context(viewport={"width": 1600, "height": 1000})
    context.add_init_script(watch_status())
    page = context.new_page()
    page.set_default_timeout(120_000)
    log = AppLog()
    try:
        with served(scans, truth) as (app, url):
            app.controller.subscribe(log)
            t0, t0_epoch = time.perf_counter(), time.time()
            log.t0 = t0
            page.goto(url)
            nodes = " && ".join(f"!!m.nodeRefFromName['/scans/s{i}/points']" for i in range(len(scans)))
            page.wait_for_function(f"() => {{ const m = window.__viserMutable; return !!m && {nodes}; }}",
                                   timeout=300_000)
            f = page.evaluate(FRAME)
            page.wait_for_function(f"() => ({FRAME})() > {f}", timeout=300_000)  # a frame with the scans in it
            yield page, app.controller, log, time.perf_counter() - t0, t0_epoch
    finally:
        context.close()


def responsive(browser, case: str, nexts: int, idle_s: float) -> Responsive:
    """Two fresh runs: Next pressed while the pipeline computes, then idle redraws once done; and
    Verify and Placement chosen as ICP starts."""
    name, scans, truth = load_case(case)
    res = Responsive(name, sum(s.n_points for s in scans))
    with opened(browser, scans, truth) as (page, ctl, log, first, t0_epoch):
        res.first_view = first
        say(f"{case}: first view {res.first_view:.1f} s")
        # Next while the pipeline computes: a second to look at each view, then a press.
        for at in range(min(nexts, len(STAGE_NAMES) - 1)):
            page.wait_for_timeout(1000)
            running = ctl.snapshot.running
            if running is None:
                break
            asked = label(STAGE_NAMES[at + 1])
            res.nexts.append((asked, running, timed_heading(page, press_next(page), asked)))
        say(f"{case}: Next {[round(x[2], 2) for x in res.nexts]}")
        res.placed = seen(page, "placed", t0_epoch)
        res.finished = seen(page, "finished", t0_epoch)
        say(f"{case}: verdicts {res.placed:.1f} s, every stage done {res.finished:.1f} s")
        res.idle.append(idle_redraws(page, label(STAGE_NAMES[len(res.nexts)]), idle_s))  # where Next left the tab
        for stage in IDLE_VIEWS:
            timed_heading(page, lambda: choose_stage(page, label(stage)), label(stage))
            res.idle.append(idle_redraws(page, label(stage), idle_s))
        res.graph_published = log.since(lambda running, graph, busy: graph)
        res.icp_started = log.since(lambda running, graph, busy: running == "icp")
        res.icp_ended = log.since(lambda running, graph, busy: running == "evaluation")
        res.paused = getattr(ctl, "paused_s", None)
        res.graph_before_icp = (res.graph_published is not None and res.icp_started is not None
                                and res.graph_published <= res.icp_started)
    # The verdicts are published as ICP starts: are Verify and Placement usable while it runs?
    with opened(browser, scans, truth) as (page, ctl, log, _, _):
        wait_running(ctl, "icp")
        for stage in ("verify", "graph"):
            started = time.perf_counter()
            s = timed_heading(page, lambda: choose_stage(page, label(stage)), label(stage))
            icp_from = log.first(lambda running, graph, busy: running == "icp")
            end = log.first(lambda running, graph, busy: running == "evaluation" or not busy and graph)
            throughout = icp_from is not None and icp_from <= started and (end is None or end >= started + s)
            res.during_icp.append((label(stage), s, throughout))
        ctl.wait_idle(600)
    return res


def _s(v: float | None) -> str:
    return "–" if v is None or v != v else f"{v:.2f}"


def print_responsive(results: list[Responsive], idle_s: float) -> None:
    print("\nResponsiveness from the first second (the app starts its run as the page opens; seconds after "
          f"page.goto unless said; idle redraws sampled for {idle_s:.0f} s per view):\n")
    print("| measure | " + " | ".join(f"{r.case} ({r.points:,} points)" for r in results) + " |")
    print("|---|" + "---|" * len(results))

    def row(what: str, cells) -> None:
        print(f"| {what} | " + " | ".join(cells) + " |")

    row("first view drawn", [_s(r.first_view) for r in results])
    row("Next during the run: median (s)", [_s(statistics.median(x[2] for x in r.nexts)) if r.nexts else "–"
                                            for r in results])
    row("Next during the run: max (s)", [_s(max(x[2] for x in r.nexts)) if r.nexts else "–" for r in results])
    row("Next during the run: presses", [str(len(r.nexts)) for r in results])
    row("all verdicts (11 Placement done)", [_s(r.placed) for r in results])
    row("snapshot with the verdicts published (app)", [_s(r.graph_published) for r in results])
    row("ICP ran (app): start – end", [f"{_s(r.icp_started)} – {_s(r.icp_ended)}" for r in results])
    row("verdicts published before ICP ran", ["yes" if r.graph_before_icp else "no" for r in results])
    for k, stage in enumerate(("10 Verify", "11 Placement")):
        row(f"{stage} chosen as ICP starts (another run): heading shown (s)",
            [(f"{_s(r.during_icp[k][1])} ({'ICP running' if r.during_icp[k][2] else 'ICP not running throughout'})"
              if len(r.during_icp) > k else "–") for r in results])
    row("every stage done", [_s(r.finished) for r in results])
    row("the worker gave way to the tab for (s, app)", [_s(r.paused) for r in results])
    for k in range(max((len(r.idle) for r in results), default=0)):
        where = "the view Next left the tab on" if k == 0 else results[0].idle[k][0]
        row(f"after all done, on {where}: longest redraw stretch without input (s)",
            [(f"{_s(r.idle[k][1])}" + (f" ({r.idle[k][0]})" if k == 0 else "")) if len(r.idle) > k else "–"
             for r in results])
        row(f"after all done, on {where}: frames per second",
            [f"{r.idle[k][2]:.1f}" if len(r.idle) > k else "–" for r in results])
    print("\nEach Next pressed during the run (from the click until the panel's heading names the stage):\n")
    print("| case | stage asked | stage computing at the press | seconds |")
    print("|---|---|---|---|")
    for r in results:
        for asked, running, s in r.nexts:
            print(f"| {r.case} | {asked} | {label(running) if running else '–'} | {s:.2f} |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3, help="re-runs per parameter change")
    ap.add_argument("--part", choices=("both", "rerun", "responsive"), default="both")
    ap.add_argument("--case", choices=("both", "demo", "awkward"), default="both",
                    help="the responsiveness part's case(s); the re-run part is on the demo")
    ap.add_argument("--nexts", type=int, default=4, help="presses of Next during the first run")
    ap.add_argument("--idle", type=float, default=8.0, help="seconds of frame sampling per view once done")
    args = ap.parse_args()
    print(f"treereg from {Path(treereg_core.__file__).resolve().parent.parent}")
    cases = ("demo", "awkward") if args.case == "both" else (args.case,)
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path="/usr/bin/chromium", headless=True, args=ARGS)
        try:
            if args.part in ("both", "responsive"):
                print_responsive([responsive(browser, c, args.nexts, args.idle) for c in cases], args.idle)
            if args.part in ("both", "rerun"):
                print_rerun(rerun_rows(browser, args.repeats), args.repeats)
        finally:
            browser.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
