"""How long after pressing Run a parameter change of the arcs, fits or evaluation stage shows its
result in the browser, on the bundled demo (issue 13: at most 1 s).

The app serves the demo (a viewer per tab) in this process; headless Chromium (Debian's
/usr/bin/chromium, SwiftShader) opens it, waits until every stage is done, then for each change:
steps to the stage, types the new value, presses Run and times until the status line marks the
stage done again (the app publishes each stage as it finishes, so the stage is shown before the
later ones have run). The baseline, in the same process: the same stages run by the `Pipeline`
alone, without app or browser. Prints a markdown table; the ratio is browser / pipeline.

    python benchmarks/bench_app_rerun.py [--repeats 3]
"""

from __future__ import annotations

import argparse
import re
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import viser  # noqa: E402
from playwright.sync_api import expect, sync_playwright  # noqa: E402

from treereg_core.demo import demo_case  # noqa: E402
from treereg_core.pipeline import Pipeline  # noqa: E402
from treereg_viewer.app import TreeregApp  # noqa: E402
from treereg_viewer.controller import Controller  # noqa: E402

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


def pipeline_seconds(scans, truth, section: str, field: str, value, stages: tuple[str, ...]) -> float:
    """The baseline: the stages a change re-runs, by the pipeline alone (no app, no browser)."""
    pipe = Pipeline(list(scans), truth=truth)
    pipe.run("evaluation")
    p = pipe.params
    pipe.set_params(replace(p, **{section: replace(getattr(p, section), **{field: value})}))
    t0 = time.perf_counter()
    pipe.run(stages[-1])
    return time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    demo = demo_case()
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = TreeregApp(server, Controller(list(demo.scans), truth=demo.truth), tabs="each")
    rows = []
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path="/usr/bin/chromium", headless=True, args=ARGS)
            page = browser.new_page(viewport={"width": 1600, "height": 1000})
            page.set_default_timeout(120_000)
            page.goto(f"http://127.0.0.1:{server.get_port()}/")
            page.wait_for_function(DONE, timeout=300_000)
            for name, stage, label, section, field, values, stages in CHANGES:
                page.get_by_label("Stage", exact=True).click()
                page.get_by_role("option", name=stage, exact=True).click()
                seen = []
                for k in range(args.repeats):
                    page.wait_for_function(DONE)
                    # Parameters are text inputs, not tied to their label element: the input beside it.
                    box = page.locator("label", has_text=re.compile(f"^{re.escape(label)}$")).filter(visible=True).locator(
                        "xpath=ancestor::div[.//input][1]//input").first
                    box.fill(str(values[k % 2]))
                    box.press("Enter")
                    # The stage is stale (○) now: Run brings it back (✓).
                    expect(page.get_by_text("Parameters changed", exact=False)).to_be_visible(timeout=60_000)
                    t0 = time.perf_counter()
                    page.get_by_role("button", name="Run", exact=True).click()
                    page.wait_for_function(SHOWN, arg=stage)
                    seen.append(time.perf_counter() - t0)
                base = statistics.median(pipeline_seconds(demo.scans, demo.truth, section, field, values[k % 2], stages)
                                         for k in range(args.repeats))
                rows.append((name, stage, statistics.median(seen), min(seen), base))
            browser.close()
    finally:
        app.close()
        server.stop()
    print(f"\nRe-run after a parameter change, the demo (3 scans), median of {args.repeats} "
          "(from pressing Run until the stage shows done in the browser):\n")
    print("| parameter changed | stage shown | seen in the browser (s), median | best (s) | pipeline alone (s) | ratio |")
    print("|---|---|---|---|---|---|")
    for name, stage, med, best, base in rows:
        print(f"| {name} | {stage} | {med:.2f} | {best:.2f} | {base:.2f} | {med / max(base, 1e-9):.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
