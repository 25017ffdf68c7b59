"""The layout at 1280 x 720 (a 150 %-zoomed projector) and 1920 x 1080, in headless Chromium (issue 32
item 4): on every stage and in the cross-section inspector no plot's title, subplot titles, axis
titles or legend are cut or lie over each other (their bounding boxes, `browser.PLOT_PROBLEMS`), no
table is wider than its panel, no "nan"; and the Run under a stage's parameters is there while the
last of them is edited.
"""

from __future__ import annotations

import re

import pytest

pytestmark = pytest.mark.browser

playwright_api = pytest.importorskip("playwright.sync_api")
from browser import close_toast, go, layout_problems, open_page, view, wait_stages_done  # noqa: E402
from conftest import CHROMIUM  # noqa: E402

if not CHROMIUM.exists():
    pytest.skip(f"{CHROMIUM} is not installed", allow_module_level=True)

from treereg_viewer.labels import STAGE_NAMES, label  # noqa: E402
from treereg_viewer.stage_panel import RUN_BELOW  # noqa: E402


@pytest.fixture(scope="module")
def served():
    for url, _, _ in view([]):
        yield url


@pytest.mark.slow  # about 45 s a size: every stage stepped through, the cross-section drawn
@pytest.mark.parametrize("width, height", [(1280, 720), (1920, 1080)])
def test_no_plot_title_legend_or_table_is_cut_or_overlaps(served, browser, width, height):
    expect = playwright_api.expect
    context, page, blocked = open_page(browser, served, width=width, height=height)
    close_toast(page)
    wait_stages_done(page)
    problems = {}
    for k, name in enumerate(STAGE_NAMES):
        if k:
            page.get_by_role("button", name="Next", exact=True).click()
        expect(page.get_by_role("heading", name=re.compile("^" + re.escape(label(name)) + "(:|$)"))).to_be_visible(
            timeout=90_000)
        if name in ("coarse", "matching", "fine", "graph", "evaluation"):  # the stages with plots: drawn
            page.wait_for_function("() => [...document.querySelectorAll('.js-plotly-plot')].some(p => p.offsetParent "
                                   "!== null && p.querySelector('.main-svg'))", timeout=60_000)
        page.wait_for_timeout(500)
        if found := layout_problems(page):
            problems[label(name)] = found
    page.get_by_label("Show", exact=True).click()
    page.get_by_role("option", name="Cross-section", exact=True).click()
    expect(page.get_by_role("heading", name=re.compile("^Cross-section at z = "))).to_be_visible(timeout=60_000)
    page.wait_for_function("() => document.querySelectorAll('.js-plotly-plot .main-svg').length >= 3", timeout=60_000)
    page.wait_for_timeout(500)
    if found := layout_problems(page):
        problems["cross-section"] = found
    assert not problems, problems
    assert not blocked, blocked
    context.close()


def test_run_is_at_hand_under_the_last_parameter(served, browser):
    """At 1280 x 720 the Run at the top is scrolled away while 9 Fine's last parameter is edited: a
    Run stands right under the parameters, and runs."""
    expect = playwright_api.expect
    context, page, _ = open_page(browser, served, scene=False, width=1280, height=720)
    close_toast(page)
    wait_stages_done(page)
    go(page, "9 Fine")
    expect(page.get_by_role("heading", name=re.compile("^9 Fine"))).to_be_visible()
    inputs = page.locator("input").filter(visible=True)
    last = inputs.nth(inputs.count() - 1)
    last.scroll_into_view_if_needed()
    top_run = page.get_by_role("button", name="Run", exact=True).bounding_box()
    assert top_run["y"] + top_run["height"] < 0 or top_run["y"] > 720  # scrolled out of view
    below = page.get_by_role("button", name=RUN_BELOW, exact=True)
    gap = below.bounding_box()["y"] - (last.bounding_box()["y"] + last.bounding_box()["height"])
    assert 0 < gap < 120, gap  # right under the parameters
    below.click()
    expect(page.get_by_text(re.compile(r"Ran 9 Fine, 10 Verify, 11 Placement, 13 Result in [\d.]+ s"))).to_be_visible(
        timeout=120_000)
    context.close()
