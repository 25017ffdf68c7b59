"""The tuner's loop in headless Chromium (issue 32 item 1): on 7 Arcs a slice picked, an arcs parameter
changed and Run pressed. Meanwhile the last result stays drawn, marked stale; then the new arcs of the
same slice are drawn and framed, the *Slice* list still names it, and *Previous run* draws
the previous run with the parameter and the metrics that changed.

`TREEREG_SHOTS=DIR` saves the screenshots (before.png, after.png: the README's assets/before_after_*.png).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

pytestmark = pytest.mark.browser

playwright_api = pytest.importorskip("playwright.sync_api")
from browser import choose, close_toast, drawn, go, open_page, reading_problems, view, wait_stages_done  # noqa: E402
from conftest import CHROMIUM  # noqa: E402

if not CHROMIUM.exists():
    pytest.skip(f"{CHROMIUM} is not installed", allow_module_level=True)

W, H = 1280, 720
SHOTS = Path(os.environ["TREEREG_SHOTS"]) if os.environ.get("TREEREG_SHOTS") else None

#: Where the points of scene node `name` fall on the canvas as the page's camera shows them now: the
#: share of them inside the 3-D view (between the docked panels) and their extent in pixels (x, y).
ON_SCREEN = """(name) => {
  const m = window.__viserMutable, node = m.nodeRefFromName[name], cam = m.camera;
  if (!node) return null;
  node.updateMatrixWorld(true); cam.updateMatrixWorld();
  const rect = document.querySelector('canvas').getBoundingClientRect();
  const xs = [], ys = [];
  node.traverse((c) => {
    const a = c.geometry?.attributes?.position;
    if (!a) return;
    c.updateMatrixWorld(true);
    const step = Math.max(1, Math.floor(a.count / 500));
    for (let i = 0; i < a.count; i += step) {
      const v = c.position.clone().fromBufferAttribute(a, i).applyMatrix4(c.matrixWorld).project(cam);
      xs.push(rect.left + (v.x + 1) / 2 * rect.width); ys.push(rect.top + (1 - v.y) / 2 * rect.height);
    }
  });
  const panels = [...document.querySelectorAll('.mantine-Paper-root')].filter(e => e.offsetParent !== null)
    .map(e => e.getBoundingClientRect()).filter(r => r.height > 0.5 * window.innerHeight);
  const left = Math.max(rect.left, ...panels.filter(r => r.left < 10).map(r => r.right));
  const right = Math.min(rect.right, ...panels.filter(r => r.left > 10).map(r => r.left));
  const inside = xs.filter((x, i) => x >= left && x <= right && ys[i] >= rect.top && ys[i] <= rect.bottom).length;
  return [inside / Math.max(xs.length, 1), Math.max(...xs) - Math.min(...xs), Math.max(...ys) - Math.min(...ys)];
}"""


@pytest.fixture(scope="module")
def served():
    for url, _, _ in view([]):
        yield url


def _shot(page, name: str) -> None:
    if SHOTS is not None:
        SHOTS.mkdir(parents=True, exist_ok=True)
        page.mouse.move(W // 2, H - 5)  # no tooltip over what is shown
        page.wait_for_timeout(500)
        page.screenshot(path=str(SHOTS / name))


def _arc_nodes(page) -> list[str]:
    return page.evaluate("() => Object.entries(window.__viserMutable.nodeRefFromName)"
                         ".filter(([n, o]) => /^\\/arcs\\/(ref|tgt)\\d+$/.test(n) && o?.parent).map(([n]) => n)")


def _shows(page, k: int, height: str) -> None:
    """Slice k (1-based) at `height` is the one the panel names, the list shows, and the scene draws, framed."""
    expect = playwright_api.expect
    expect(page.get_by_text(re.compile(rf"Shown: slice {k} at {re.escape(height)} m of \d+")).first).to_be_visible()
    expect(page.get_by_label("Slice", exact=True)).to_have_value(re.compile(rf"^slice {k} at {re.escape(height)} m$"))
    page.wait_for_function(f"() => !!window.__viserMutable.nodeRefFromName['/arcs/ref{k - 1}']?.parent")
    assert {n.rsplit("/", 1)[1].removeprefix("ref").removeprefix("tgt") for n in _arc_nodes(page)} == {str(k - 1)}
    page.get_by_role("button", name="Frame the view", exact=True).click()
    page.wait_for_timeout(1500)  # the camera's move is animated
    inside, wide, tall = page.evaluate(ON_SCREEN, f"/arcs/ref{k - 1}")
    assert inside > 0.95 and max(wide, tall) > 120, (inside, wide, tall)  # in view and not a blob


@pytest.mark.slow  # about 40 s: the demo's run, an arcs parameter changed and re-run
def test_an_arcs_parameter_changed_and_run_keeps_the_slice_and_compares(served, browser):
    expect = playwright_api.expect
    context, page, blocked = open_page(browser, served, width=W, height=H)
    close_toast(page)
    wait_stages_done(page)
    go(page, "7 Arcs")
    expect(page.get_by_role("heading", name=re.compile("^7 Arcs"))).to_be_visible()
    slice_list = page.get_by_label("Slice", exact=True)
    expect(slice_list).to_have_value(re.compile(r"^slice \d+ at "))
    busiest = int(re.match(r"slice (\d+)", slice_list.input_value()).group(1))
    slice_list.click()
    options = page.get_by_role("option").all_inner_texts()
    page.keyboard.press("Escape")
    slices = [o for o in options if o.startswith("slice ")]
    pick = slices[(busiest - 1 + 3) % len(slices)]  # not the busiest: the tuner's own choice
    k, height = re.match(r"slice (\d+) at (-?[\d.]+) m", pick).groups()
    choose(page, "Slice", pick)
    _shows(page, int(k), height)
    expect(page.get_by_label("Previous run", exact=True)).to_be_hidden()

    box = page.locator("label", has_text=re.compile("^min points$")).filter(visible=True).locator(
        "xpath=ancestor::div[.//input][1]//input").first
    box.fill("20")
    box.press("Enter")
    # The last result stays drawn, marked stale, on the same slice.
    expect(page.get_by_text(re.compile(r"Stale — the last run's result\. 7 Arcs must run again")).first).to_be_visible()
    expect(page.get_by_text(re.compile(r"arcs\.min_points 15 → 20")).first).to_be_visible()
    _shows(page, int(k), height)
    _shot(page, "before.png")

    page.get_by_role("button", name="Run", exact=True).click()
    expect(page.get_by_text(re.compile(r"Ran 7 Arcs, 8 Fits, 9 Fine.* in [\d.]+ s"))).to_be_visible(timeout=120_000)
    expect(page.get_by_text(re.compile(r"The latest run \(arcs\.min_points 15 → 20\)")).first).to_be_visible()
    _shows(page, int(k), height)  # the same slice, drawn, listed and framed
    expect(page.get_by_role("table").filter(has_text="changed").first).to_be_visible()  # the metrics that moved
    assert not reading_problems(page), reading_problems(page)
    _shot(page, "after.png")

    before_box = page.get_by_label("Previous run", exact=True)
    before_box.check()
    expect(page.get_by_text(re.compile(r"The previous run \(arcs\.min_points 15 → 20\)")).first).to_be_visible()
    expect(page.get_by_text(re.compile(r"smaller than 15 points")).first).to_be_visible()
    _shows(page, int(k), height)
    before_box.uncheck()
    expect(page.get_by_text(re.compile(r"smaller than 20 points")).first).to_be_visible()
    assert not blocked, blocked
    context.close()
