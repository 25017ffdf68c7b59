"""The classroom in headless Chromium (issue 32 items 2 and 3), on one `treereg view` server and one
browser for the module:

- projector mode: the page's text measured 1.6 times its normal size (and the 3-D labels drawn at 1.6
  times theirs), no table, plot title or legend cut at 1280 x 720; PageDown steps to the next stage,
  PageUp back; in the tour → goes to its next step;
- presenting: a tab that follows cannot change the presenter's parameters (its inputs and Run greyed
  out) nor take the lead; a tab on its own that changes one is named in the presenter's tab, which can
  undo it; the presenter hands the lead over.

`TREEREG_SHOTS=DIR` saves the screenshot of projector mode (projector_mode.png: README's
assets/projector_mode.png).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

pytestmark = pytest.mark.browser

playwright_api = pytest.importorskip("playwright.sync_api")
from browser import close_toast, go, open_page, reading_problems, view  # noqa: E402
from conftest import CHROMIUM  # noqa: E402

if not CHROMIUM.exists():
    pytest.skip(f"{CHROMIUM} is not installed", allow_module_level=True)

W, H = 1280, 720
SHOTS = Path(os.environ["TREEREG_SHOTS"]) if os.environ.get("TREEREG_SHOTS") else None

#: The rendered font size (px) of the control panel's first paragraph (the app's one-line heading).
TEXT_PX = """() => {
  const p = [...document.querySelectorAll('p')].find(e => e.offsetParent !== null && /marker-free registration/.test(e.textContent));
  return p ? parseFloat(getComputedStyle(p).fontSize) : null;
}"""

#: The font size (CSS px) of the scanners' 3-D label as viser's label renderer draws a screen-space
#: label: 12 px at font_screen_scale 1 (viser's client, label/LabelRenderer.tsx), from the scene tree.
LABEL_PX = """() => {
  const tree = window.__viserSceneTree?.getState() ?? {};
  const name = Object.keys(tree).find(k => /^\\/scans\\/s\\d+\\/station\\/name$/.test(k));
  const props = name ? tree[name]?.message?.props : null;
  return props ? 12 * props.font_screen_scale : null;
}"""


@pytest.fixture(scope="module")
def served():
    for url, _, _ in view([]):
        yield url


@pytest.fixture(scope="module")
def first(served, browser):
    """The first tab, shared by the module's tests (a page takes seconds to open while the demo runs):
    projector mode's, then the presenter's."""
    context, page, blocked = open_page(browser, served, scene=False, width=W, height=H)
    if SHOTS is not None:
        close_toast(page)
    yield page
    assert not blocked, blocked
    context.close()


def _stage(page, label: str) -> None:
    playwright_api.expect(page.get_by_label("Stage", exact=True)).to_have_value(label)


def _tab_name(page) -> str:
    """The name the app gave this tab ("tab 3"), as its Teach tab says."""
    text = page.get_by_text(re.compile(r"This tab is tab \d+")).first.inner_text()
    return re.search(r"This tab is (tab \d+)", text).group(1)


def test_projector_mode_scales_the_text_and_the_keys_step(first):
    expect = playwright_api.expect
    page = first
    normal = page.evaluate(TEXT_PX)
    page.wait_for_function(f"() => ({LABEL_PX})() !== null")
    normal_label = page.evaluate(LABEL_PX)
    page.get_by_role("tab", name="Teach").click()
    page.get_by_label("Projector mode", exact=True).check()
    page.wait_for_function(f"(n) => ({TEXT_PX})() >= 1.6 * n", arg=normal)
    assert page.evaluate(TEXT_PX) / normal >= 1.6, (normal, page.evaluate(TEXT_PX))
    page.wait_for_function(f"(n) => ({LABEL_PX})() >= 1.6 * n - 1e-9", arg=normal_label)

    # PageDown: the next stage; PageUp: back (a clicker sends these).
    _stage(page, "1 Scans")
    page.get_by_text(re.compile("marker-free registration")).first.click()  # the page has the focus, no input
    page.keyboard.press("PageDown")
    _stage(page, "2 Projection")
    page.keyboard.press("PageUp")
    _stage(page, "1 Scans")

    # Readable at 1280 x 720 in projector mode: no table wider than its panel, no "nan", no sentence
    # twice (what the larger text changes: plotly's text keeps its size, checked by the layout tests).
    problems = {}
    for name in ("1 Scans", "4 Coarse"):
        go(page, name)
        expect(page.get_by_role("heading", name=re.compile("^" + re.escape(name)))).to_be_visible()
        expect(page.get_by_role("table").first).to_be_visible()
        if found := reading_problems(page):
            problems[name] = found
    if SHOTS is not None:
        page.mouse.move(W // 2, H - 5)
        page.wait_for_timeout(500)
        SHOTS.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(SHOTS / "projector_mode.png"))
    assert not problems, problems

    # The tour: → goes to its next step.
    page.get_by_role("tab", name="Teach").click()
    page.get_by_role("button", name="Start the tour", exact=True).click()
    expect(page.get_by_role("heading", name=re.compile(r"Tour · step 1 of \d+"))).to_be_visible()
    page.keyboard.press("ArrowRight")
    expect(page.get_by_role("heading", name=re.compile(r"Tour · step 2 of \d+"))).to_be_visible()
    page.keyboard.press("PageUp")
    expect(page.get_by_role("heading", name=re.compile(r"Tour · step 1 of \d+"))).to_be_visible()
    page.get_by_role("button", name="End tour", exact=True).click()


def test_a_follower_cannot_change_the_presenters_parameters_or_take_the_lead(served, browser, first):
    expect = playwright_api.expect
    teacher = first  # in projector mode: the tab on the room's screen
    ctx2, pupil, _ = open_page(browser, served, scene=False, width=W, height=H)
    teacher.get_by_role("tab", name="Teach").click()
    pupil.get_by_role("tab", name="Teach").click()
    pupil_name = _tab_name(pupil)
    teacher.get_by_label("Others follow me", exact=True).check()
    expect(pupil.get_by_label("Follow the presenter", exact=True)).to_be_checked()
    # The lead is the presenter's: the pupil's "Others follow me" is greyed out, and says who leads.
    expect(pupil.get_by_label("Others follow me", exact=True)).to_be_disabled()
    expect(pupil.get_by_text(re.compile(r"tab \d+ presents\. Only it can hand the lead over")).first).to_be_visible()

    # On 7 Arcs the pupil follows, its parameters and Run greyed out.
    for page in (teacher, pupil):
        page.get_by_role("tab", name="Stage").click()
    go(teacher, "7 Arcs")
    _stage(pupil, "7 Arcs")

    def min_points(page):
        return page.locator("label", has_text=re.compile("^min points$")).filter(visible=True).locator(
            "xpath=ancestor::div[.//input][1]//input").first

    expect(min_points(teacher)).to_have_value("15")
    expect(min_points(pupil)).to_be_disabled()
    expect(pupil.get_by_role("button", name="Run", exact=True)).to_be_disabled()
    expect(pupil.get_by_text(re.compile("While you follow, the parameters and Run are the presenter's")).first)\
        .to_be_visible()
    # PageDown in a following tab does not step it (the presenter leads).
    pupil.get_by_text(re.compile("marker-free registration")).first.click()
    pupil.keyboard.press("PageDown")
    pupil.wait_for_timeout(500)
    _stage(pupil, "7 Arcs")
    expect(min_points(teacher)).to_have_value("15")

    # On its own the pupil may change a parameter: the teacher's tab names the tab and the change, and undoes it.
    pupil.get_by_label("Follow the presenter", exact=True).uncheck()
    expect(min_points(pupil)).to_be_enabled()
    min_points(pupil).fill("20")
    min_points(pupil).press("Enter")
    expect(teacher.get_by_text(f"Changed by {pupil_name}: arcs.min_points 15 → 20.")).to_be_visible()
    expect(min_points(teacher)).to_have_value("20")
    teacher.get_by_role("button", name="Undo that change", exact=True).click()
    expect(min_points(teacher)).to_have_value("15")
    expect(min_points(pupil)).to_have_value("15")
    expect(pupil.get_by_text(re.compile(r"Changed by tab \d+: undid")).first).to_be_visible()

    # The presenter hands the lead over: the pupil presents, the teacher follows it.
    pupil.get_by_label("Follow the presenter", exact=True).check()
    for page in (teacher, pupil):
        page.get_by_role("tab", name="Teach").click()
    teacher.get_by_label("Hand the lead to", exact=True).click()
    teacher.get_by_role("option", name=pupil_name, exact=True).click()
    teacher.get_by_role("button", name="Hand over the lead", exact=True).click()
    expect(pupil.get_by_label("Others follow me", exact=True)).to_be_checked()
    expect(pupil.get_by_label("Others follow me", exact=True)).to_be_enabled()
    expect(teacher.get_by_label("Follow the presenter", exact=True)).to_be_checked()
    expect(teacher.get_by_label("Others follow me", exact=True)).to_be_disabled()
    teacher.get_by_role("tab", name="Stage").click()
    expect(min_points(teacher)).to_be_disabled()
    go(pupil, "6 Slices")
    _stage(teacher, "6 Slices")
    ctx2.close()
