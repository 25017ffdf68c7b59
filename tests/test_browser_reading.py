"""The app as a person reads it, in headless Chromium on a 1280 x 720 laptop screen (issue 18).

`treereg view a/scan1.ply b/scan1.ply c/scan1.ply`: one folder per station with the same file name
in each, as many scanners export; a and b are the demo's first two stations, c is a scan of another
tree. Stepping through every stage: no table wider than its panel, no "nan", no sentence said twice,
the 3-D view at least half the window; every check beside its threshold; the other tree failed as
"not the same tree" and not drawn registered; the tour's words are the page's; a class following
the presenter sees its stage and its tour card.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest

pytestmark = pytest.mark.browser

playwright_api = pytest.importorskip("playwright.sync_api")
from browser import choose, close_toast, drawn, go, open_page, reading_problems, view, wait_stages_done  # noqa: E402
from conftest import CHROMIUM  # noqa: E402

if not CHROMIUM.exists():
    pytest.skip(f"{CHROMIUM} is not installed", allow_module_level=True)

from treereg_core.demo import DEMO_DIR  # noqa: E402
from treereg_viewer.labels import STAGE_NAMES, label  # noqa: E402
from treereg_viewer.tour import STEPS  # noqa: E402

W, H = 1280, 720


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    """The app on a/scan1.ply, b/scan1.ply (the demo's stations 1 and 2) and c/scan1.ply (another tree)."""
    from treereg_core.io.scans import write_scan
    from treereg_core.simulate.cases import CaseSpec

    root = tmp_path_factory.mktemp("stations")
    for folder, name in (("a", "scan1.ply"), ("b", "scan2.ply")):
        (root / folder).mkdir()
        shutil.copy(DEMO_DIR / name, root / folder / "scan1.ply")
    (root / "c").mkdir()
    # Measured: at chance-level support, 0.30 and 0.61 consistent against the demo's stations 1 and 2;
    # on an AMD EPYC 0.91 and 0.73 (a pose between two different trees is arbitrary, and the last bits
    # of the CPU's arithmetic pick it): at least one pair fails as another tree, and so does the scan.
    other = CaseSpec(seed=607, height_m=13.89, angular_step_deg=(0.0449, 0.0449)).build().scans[1]
    write_scan(root / "c" / "scan1.ply", other.points, dtype="float32")
    for url, _, _ in view(["a/scan1.ply", "b/scan1.ply", "c/scan1.ply"], cwd=root):
        yield url


def _text(page) -> str:
    """What the page shows: its text and the values in its inputs (a dropdown shows its choice in one)."""
    return page.evaluate("() => document.body.innerText + '\\n' + "
                         "[...document.querySelectorAll('input')].map(e => e.value).join('\\n')")


def test_every_stage_reads_at_1280x720(folders, browser):
    expect = playwright_api.expect
    context, page, blocked = open_page(browser, folders, width=W, height=H)
    close_toast(page)
    wait_stages_done(page)
    # The scans are named by their folders, everywhere (the header's verdict line here).
    expect(page.get_by_text(re.compile(r"✓ 1 a/scan1\.ply · ✓ 2 b/scan1\.ply · ✗ 3 c/scan1\.ply"))).to_be_visible()
    canvas = page.locator("canvas").first.bounding_box()
    assert canvas["width"] >= W / 2, f"the 3-D view is {canvas['width']:.0f} px of a {W} px window"
    problems, other_tree_of = {}, None
    for k, name in enumerate(STAGE_NAMES):
        if k:
            page.get_by_role("button", name="Next", exact=True).click()
        expect(page.get_by_role("heading", name=re.compile("^" + re.escape(label(name)) + "(:|$)"))).to_be_visible(
            timeout=90_000)
        page.wait_for_timeout(300)  # the panel's table arrives with the heading's update; let it lay out
        if found := reading_problems(page):
            problems[label(name)] = found
        text = _text(page)
        if name == "hypotheses":  # the margin against its threshold, one rival drawn
            assert re.search(r"margin \(≥ 0\.03\)", text) and re.search(r"0\.\d{3} [✓✗]", text), text[:400]
            assert drawn(page, "/hypotheses/rival") and not drawn(page, "/hypotheses/candidate1")
        if name in ("arcs", "sections", "fine"):  # one slice at a time, with a control to go to another
            assert re.search(r"Shown: slice \d+ at -?\d+\.\d\d m of \d+", text), text[:400]
            expect(page.get_by_label("Slice", exact=True)).to_have_value(re.compile(r"^slice \d+ at "))
        if name == "fine":  # against the Fits stage: how far the fine pose moved the tie points
            assert "Black lines: how far the fine pose moved" in text
            assert drawn(page, "/fine/offsets")
        if name == "verify":  # every check beside its threshold and the parameter that sets it
            expect(page.get_by_role("columnheader", name="threshold")).to_be_visible()
            expect(page.get_by_role("columnheader", name="measured")).to_be_visible()
            assert re.search(r"✓\s*free-space consistency\s*verify\.min_consistency\s*0\.9\d+\s*≥ 0\.95",
                             text), text
        if name == "graph":  # the other tree: failed as not the same tree, not drawn registered
            found = re.search(r"does not show the same tree as ([ab]/scan1\.ply)", text)
            assert found, text[:600]
            other_tree_of = found.group(1)
            assert "✗ failed" in text
            # (its 3-D label, "✗ c/scan1.ply: failed, not placed", is drawn text: test_viewer checks it)
            page.wait_for_function("() => !window.__viserMutable.nodeRefFromName['/scans/s2/points']?.parent && "
                                   "!!window.__viserMutable.nodeRefFromName['/scans/s1/points']?.parent")
    # The other tree's own checks: its support and free space, at chance level, and no generic hint.
    go(page, label("verify"))
    choose(page, "Pair", f"c/scan1.ply → {other_tree_of}")
    expect(page.get_by_role("heading", name=f"10 Verify: c/scan1.ply → {other_tree_of}", exact=False)).to_be_visible()
    page.wait_for_timeout(300)
    text = _text(page)
    assert "✗ failed" in text and f"does not show the same tree as {other_tree_of}" in text, text[:600]
    assert "add a station" not in text and "pick another hypothesis" not in text
    if found := reading_problems(page):
        problems["10 Verify, c"] = found
    assert not problems, problems
    # The export leaves the failed scan out, and says so.
    page.get_by_role("tab", name="Files").click()
    with page.expect_download(timeout=60_000) as dl:
        page.get_by_role("button", name="Download transforms.json").click()
    doc = json.loads(Path(dl.value.path()).read_text())
    assert sorted(doc["transforms"]) == ["a/scan1.ply", "b/scan1.ply"], sorted(doc["transforms"])
    assert doc["quality"]["scans"]["c/scan1.ply"]["verdict"] == "failed"
    expect(page.get_by_text(re.compile(r"Not exported: c/scan1\.ply")).first).to_be_visible()
    assert not blocked
    context.close()


def test_the_tour_says_what_the_page_shows(folders, browser):
    """Each tour step's controls (named in *italics*) are on the page it leads to, and the Verify
    step's words are the table's columns."""
    context, page, _ = open_page(browser, folders, scene=False, width=W, height=H)
    close_toast(page)
    wait_stages_done(page)
    page.get_by_role("tab", name="Teach").click()
    page.get_by_role("button", name="Start the tour", exact=True).click()
    missing = []
    for k, step in enumerate(STEPS):
        playwright_api.expect(page.get_by_role("heading", name=re.compile(f"Tour · step {k + 1} of "))).to_be_visible()
        page.wait_for_timeout(300)
        text = _text(page)
        names = re.findall(r"\*([^*]+)\*", step.try_this)
        missing += [f"step {k + 1} ({step.title}): *{n}*" for n in names if n not in text]
        if step.stage == "verify":
            assert "measured value against its threshold" in step.try_this
            assert re.search(r"check \(set by\)\s+measured\s+threshold", text), text[:500]
        if k < len(STEPS) - 1:
            page.get_by_role("button", name="Next ▶", exact=True).click()
    assert not missing, missing
    context.close()


def test_a_class_follows_the_presenters_stage_and_tour(folders, browser):
    expect = playwright_api.expect
    ctx1, teacher, _ = open_page(browser, folders, scene=False, width=W, height=H)
    ctx2, pupil, _ = open_page(browser, folders, scene=False, width=W, height=H)
    wait_stages_done(teacher)
    teacher.get_by_role("tab", name="Teach").click()
    teacher.get_by_label("Others follow me", exact=True).check()
    expect(pupil.get_by_label("Follow the presenter", exact=True)).to_be_checked()
    go(teacher, "6 Slices")
    expect(pupil.get_by_label("Stage", exact=True)).to_have_value("6 Slices")
    # The stage list says where the class is: the bold entry is the stage shown.
    pupil.wait_for_function("() => [...document.querySelectorAll('strong')].some(e => e.textContent === '6 Slices') && "
                            "![...document.querySelectorAll('strong')].some(e => e.textContent === '1 Scans')")
    expect(pupil.get_by_role("heading", name=re.compile("^6 Slices"))).to_be_visible()
    # The tour's card: the class reads it too; the presenter leads its steps.
    teacher.get_by_role("button", name="Start the tour", exact=True).click()
    teacher.get_by_role("button", name="Next ▶", exact=True).click()
    expect(pupil.get_by_role("heading", name=re.compile(r"Tour · step 2 of \d+: Rotating projection"))).to_be_visible()
    expect(pupil.get_by_role("button", name="Next ▶", exact=True)).to_be_hidden()
    pupil.wait_for_function("() => [...document.querySelectorAll('strong')].some(e => e.textContent === '2 Projection')")
    pupil.get_by_label("Follow the presenter", exact=True).uncheck()
    expect(pupil.get_by_role("heading", name=re.compile("Tour · step"))).to_be_hidden()
    ctx1.close()
    ctx2.close()
