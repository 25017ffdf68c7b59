"""End to end in headless Chromium: `treereg view` on the bundled demo, driven like a user.

Debian's chromium (`/usr/bin/chromium`) through Playwright for Python, no browser download, and an
offline guard (only http://127.0.0.1 may load). WebGL runs on SwiftShader. One server and one browser
for the module; the walk-through steps through every stage, changes a parameter and re-runs, uploads
a bad file, downloads exports with one click and checks screenshots' pixels. Then the cross-section
inspector (separate arcs at the coarse pose, one ring at the fine pose), two tabs with their own
stages (and one following the other), the fits view's drawn sizes and the guided tour. A scan of
another tree, scans named by folder and the app at 1280 x 720: `test_browser_reading.py`.
"""

from __future__ import annotations

import json
import os
import re
import time
from pathlib import Path

import laspy
import numpy as np
import pytest

pytestmark = pytest.mark.browser

playwright_api = pytest.importorskip("playwright.sync_api")
from browser import choose, close_toast, go, open_page, reading_problems, view  # noqa: E402
from conftest import CHROMIUM  # noqa: E402

if not CHROMIUM.exists():
    pytest.skip(f"{CHROMIUM} is not installed", allow_module_level=True)

from treereg_core.io.scans import read_points  # noqa: E402
from treereg_core.geometry.rigid import mean_displacement, rotation_error_deg  # noqa: E402
from treereg_core.io.transforms import read_transforms  # noqa: E402
from treereg_core.demo import DEMO_DIR  # noqa: E402
from treereg_viewer.palette import scan_color  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
ROT_TOL_DEG = 0.5
DISP_TOL_M = 0.03
#: Screenshots are saved here for people (and the README) to look at.
SHOT_DIR = Path(os.environ.get("TREEREG_SHOTS", "/tmp/treereg-browser-shots"))


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """`treereg view --port 0 --out DIR` on the demo, as a user starts it; yields (url, out dir, seconds to URL)."""
    out = tmp_path_factory.mktemp("exports")
    for url, seconds, t0 in view(["--out", str(out)]):
        yield url, out, seconds, t0


class _Laps:
    """Seconds since the start of a test at named points (shown with `pytest -s`)."""

    def __init__(self) -> None:
        self.t0 = time.perf_counter()

    def __call__(self, label: str) -> None:
        print(f"  {time.perf_counter() - self.t0:6.1f} s  {label}")


def _frame(page) -> int:
    return page.evaluate("() => window.__viserTestpoints.rendererInfo.render.frame")


def _settle(page, quiet_ms: int = 300, timeout_s: float = 8.0) -> None:
    """Rendering is on demand: wait until no new frame was drawn for `quiet_ms`."""
    deadline = time.monotonic() + timeout_s
    last = _frame(page)
    while time.monotonic() < deadline:
        page.wait_for_timeout(quiet_ms)
        now = _frame(page)
        if now == last:
            return
        last = now


def _screenshot(page, name) -> np.ndarray:
    page.mouse.move(5, 995)  # no tooltip over what is shown
    _settle(page)
    SHOT_DIR.mkdir(parents=True, exist_ok=True)
    return _decode_png(page.screenshot(path=str(SHOT_DIR / f"{name}.png")))


def _decode_png(data: bytes) -> np.ndarray:
    import cv2

    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    return np.ascontiguousarray(bgr[..., ::-1])


def _colour_pixels(img: np.ndarray, rgb: tuple[int, int, int], tol: int = 60) -> int:
    """Pixels close to `rgb` (shading makes points lighter or darker than their colour)."""
    d = np.abs(img.astype(np.int32) - np.array(rgb)).max(axis=-1)
    return int((d < tol).sum())


def _wait_all_done(page, timeout_ms=120_000):
    page.wait_for_function(
        "() => [...document.querySelectorAll('p, div')].some(e => /✓ 13 Result/.test(e.textContent) && "
        "!/[○…✗]/.test(e.textContent) && /1 Scans/.test(e.textContent))", timeout=timeout_ms)


def _param_input(page, label):
    """The text input of a parameter (viser's text inputs are not tied to their label element)."""
    return page.locator("label", has_text=re.compile(f"^{re.escape(label)}$")).locator(
        "xpath=ancestor::div[.//input][1]//input").first


def _set_number(page, label, value):
    """Type a parameter's value (a text input: viser's number input drops an exponent's "e")."""
    box = page.locator("label", has_text=re.compile(f"^{re.escape(label)}$")).filter(visible=True).locator(
        "xpath=ancestor::div[.//input][1]//input").first  # several stages may share a label
    box.fill(str(value))
    box.press("Enter")


def test_walk_through_the_demo(served, browser):
    url, out_dir, url_seconds, t_start = served
    expect = playwright_api.expect
    lap = _Laps()
    context, page, blocked = open_page(browser, url)
    visible_seconds = time.perf_counter() - t_start
    lap("page open, scans drawn")
    close_toast(page)
    _wait_all_done(page)
    ready_seconds = time.perf_counter() - t_start
    lap("every stage done")
    print(f"\ndemo: URL after {url_seconds:.1f} s, scans drawn in the browser after {visible_seconds:.1f} s, "
          f"every stage done after {ready_seconds:.1f} s")

    # Step through every stage with Next; each shows its own panel.
    titles = ["1 Scans", "2 Projection", "3 Matching", "4 Coarse", "5 Hypotheses", "6 Slices", "7 Arcs", "8 Fits",
              "9 Fine", "10 Verify", "11 Placement", "12 ICP", "13 Result"]
    expect(page.get_by_role("heading", name=titles[0])).to_be_visible()
    # What a person must never meet at this window size either (tables clipped, "nan", a sentence twice).
    problems = {titles[0]: reading_problems(page)}
    for k in range(1, len(titles)):
        page.get_by_role("button", name="Next", exact=True).click()
        # SwiftShader draws the first transparent meshes (the Fits stage) slowly on a busy machine.
        expect(page.get_by_role("heading", name=re.compile("^" + re.escape(titles[k]) + "(:|$)"))).to_be_visible(timeout=90_000)
        page.wait_for_timeout(300)
        problems[titles[k]] = reading_problems(page)
        if k == 1:  # the image panel (docked left) shows each scan's projection image in its colour
            panel = _screenshot(page, "stage1_projection")[:, :560]
            for i in range(3):
                assert _colour_pixels(panel, scan_color(i), tol=40) > 300, f"projection of scan {i + 1} missing"
            # The slider counts from 1, as the panel's "Step k of n" does.
            n = re.search(r"Step (\d+) of", page.get_by_text(re.compile(r"Step \d+ of \d+")).first.inner_text())
            fid = page.locator("label", has_text=re.compile("^Rotation step$")).first.get_attribute("for")
            slider = page.locator(f"[id='{fid}'] [role=slider]")
            assert n is not None and slider.get_attribute("aria-valuenow") == n.group(1), n.group(0)
            assert slider.get_attribute("aria-valuemin") == "1"
        if k == 2:
            expect(page.get_by_text("Similarity", exact=False).first).to_be_visible()
        if k == 8:
            _screenshot(page, "stage9_fine")
        if k == 10:
            _screenshot(page, "stage11_placement")
    assert not {k: v for k, v in problems.items() if v}, problems
    lap("stepped through every stage")
    result = _screenshot(page, "stage13_result")
    scene = result[:, 580:1300]  # between the docked panel (560 px) and the control panel
    counts = [_colour_pixels(scene, scan_color(i)) for i in range(3)]
    assert all(c > 200 for c in counts), f"scan colours in the final overlay: {counts}"
    lap("screenshots checked")

    # Change a fine-stage parameter and re-run: only fine and evaluation run again.
    go(page, "9 Fine")
    expect(page.get_by_role("heading", name=re.compile("^9 Fine"))).to_be_visible()
    _set_number(page, "max iterations", 2)
    expect(page.get_by_text(re.compile("Parameters changed: 9 Fine, 10 Verify, 11 Placement, 13 Result must re-run"))).to_be_visible(timeout=60_000)
    t0 = time.perf_counter()
    page.get_by_role("button", name="Run", exact=True).click()
    expect(page.get_by_text(re.compile(r"Ran 9 Fine, 10 Verify, 11 Placement, 13 Result in [\d.]+ s"))).to_be_visible(timeout=60_000)
    print(f"fine + evaluation re-run seen in the browser after {time.perf_counter() - t0:.1f} s")
    lap("parameter changed and re-run")

    # A bad upload: a message, nothing else changes.
    page.get_by_role("tab", name="Scans").click()
    with page.expect_file_chooser() as chooser:
        page.get_by_role("button", name="Add a scan file").click()
    chooser.value.set_files(files=[{"name": "broken.ply", "mimeType": "application/octet-stream",
                                    "buffer": b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n"}])
    # The message names the file the user picked (not the temporary copy the server read).
    expect(page.get_by_text(re.compile("Upload rejected — broken.ply: "))).to_be_visible(timeout=60_000)
    assert "treereg-upload-" not in page.evaluate("() => document.body.innerText")
    expect(page.get_by_label(re.compile("^4: "))).to_have_count(0)
    _wait_all_done(page, 5_000)  # every stage is still done
    lap("bad upload rejected")

    # Exports: one click starts each download (no link to click in a notification).
    page.get_by_role("tab", name="Files").click()
    with page.expect_download(timeout=60_000) as dl:
        page.get_by_role("button", name="Download transforms.json").click()
    data = Path(dl.value.path()).read_bytes()
    saved = out_dir / "downloaded_transforms.json"
    saved.write_bytes(data)
    tf = read_transforms(saved)
    demo = DEMO_DIR
    truth = read_transforms(demo / "truth.json")
    assert tf.reference == truth.reference
    assert json.loads(data)["params"]["fine"]["max_iterations"] == 2  # the parameters used
    for name in truth.names[1:]:
        pts = read_points(demo / name)
        rot = rotation_error_deg(tf.matrix(name), truth.matrix(name))
        disp = mean_displacement(tf.matrix(name), truth.matrix(name), pts)
        assert rot < ROT_TOL_DEG and disp < DISP_TOL_M, (name, rot, disp)
    # The merged cloud as LAS: every point carries its scan's number (point_source_id).
    page.get_by_label("Merged cloud format", exact=True).click()
    page.get_by_role("option", name="las", exact=True).click()
    with page.expect_download(timeout=30_000) as dl:
        page.get_by_role("button", name="Download the merged cloud").click()
    assert dl.value.suggested_filename == "merged.las"
    las = laspy.read(dl.value.path())
    ids = np.asarray(las.point_source_id)
    assert [int((ids == k + 1).sum()) for k in range(3)] == [len(read_points(demo / n)) for n in truth.names]
    assert (out_dir / "transforms.json").is_file() and (out_dir / "merged.las").is_file()  # --out
    assert not blocked, f"the page tried to load {blocked}"
    lap("exported with one click and checked")
    context.close()


def _plot(page, k: int = 0):
    """The k-th plot in the docked panel, as an image (a screenshot of that element only)."""
    page.wait_for_timeout(300)
    el = page.locator(".js-plotly-plot").nth(k)
    el.scroll_into_view_if_needed()
    return _decode_png(el.screenshot())


_NODE_SIZE = """(name) => {
  const o = window.__viserMutable.nodeRefFromName[name];
  if (!o) return null;
  o.updateMatrixWorld(true);
  const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
  o.traverse((c) => {
    const a = c.geometry?.attributes?.position;
    if (!a) return;
    const v = c.position.clone();
    for (let i = 0; i < a.count; i++) {
      v.fromBufferAttribute(a, i).applyMatrix4(c.matrixWorld);
      const p = v.toArray();
      for (let k = 0; k < 3; k++) { lo[k] = Math.min(lo[k], p[k]); hi[k] = Math.max(hi[k], p[k]); }
    }
  });
  return [lo, hi];
}"""


def test_cross_section_and_fits_views(served, browser):
    """The trunk's cross-section: at the coarse pose the targets' arcs lie off scan 1's circle, at the
    fine pose they close into one ring; the 2-D view's scan colours move between the two. The fits
    view draws no giant rejected shapes."""
    url = served[0]
    expect = playwright_api.expect
    context, page, _ = open_page(browser, url)
    close_toast(page)
    _wait_all_done(page)
    go(page, "9 Fine")
    choose(page, "Show", "Cross-section")
    expect(page.get_by_role("heading", name=re.compile("^Cross-section at z = "))).to_be_visible(timeout=60_000)
    text = page.evaluate("() => document.body.innerText")
    assert re.search(r"Coarse: separate arcs", text) and re.search(r"Fine: one ring", text), text[:2000]
    _screenshot(page, "cross_section_coarse_fine")
    both = _plot(page, 0)
    masks = {}
    for pose in ("Coarse", "Fine"):
        choose(page, "Registration", pose)
        expect(page.locator(".gtitle, .annotation-text").filter(has_text=re.compile(f"^{pose} ·"))).to_have_count(1, timeout=60_000)
        img = _plot(page, 0)
        masks[pose] = [(np.abs(img.astype(int) - np.array(scan_color(i))).max(axis=-1) < 30) for i in range(3)]
        for i in range(3):
            assert masks[pose][i].sum() > 100, f"scan {i + 1} in the {pose} cross-section: {masks[pose][i].sum()} px"
    # The targets' points and circles move between the coarse and the fine pose; the reference stays.
    for i in (1, 2):
        a, b = masks["Coarse"][i], masks["Fine"][i]
        changed = np.logical_xor(a, b).sum() / max(a.sum(), b.sum())
        assert changed > 0.2, (i, changed)
    assert both.shape[1] > 300
    choose(page, "Show", "Stage details")

    # The fits view: rejected fits hidden by default; shown, none drawn larger than a tree's section.
    go(page, "8 Fits")
    expect(page.get_by_role("heading", name=re.compile("^8 Fits"))).to_be_visible(timeout=60_000)
    page.wait_for_function("() => !!window.__viserMutable.nodeRefFromName['/sections/ref_fits']", timeout=60_000)
    nodes = page.evaluate("() => Object.keys(window.__viserMutable.nodeRefFromName)")
    assert not any(n.endswith("_rejected") for n in nodes)  # hidden by default
    page.get_by_label("Show rejected fits", exact=True).check()
    page.wait_for_function("() => Object.keys(window.__viserMutable.nodeRefFromName).some(n => n.endsWith('_rejected'))",
                           timeout=60_000)
    # Every drawn fit lies within the sliced points it was fitted to, give or take a metre (a circle
    # of 51 m or 3.8 km fitted to a nearly straight arc would reach far beyond them).
    names = page.evaluate("() => Object.keys(window.__viserMutable.nodeRefFromName)")
    sliced = [np.array(page.evaluate(_NODE_SIZE, n)) for n in names if re.fullmatch(r"/sections/(ref|tgt)\d+", n)]
    lo = np.min([b[0] for b in sliced], axis=0) - 1.0
    hi = np.max([b[1] for b in sliced], axis=0) + 1.0
    drawn = 0
    for name in ("/sections/ref_fits", "/sections/tgt_fits", "/sections/ref_rejected", "/sections/tgt_rejected"):
        box = page.evaluate(_NODE_SIZE, name)
        if box is None:
            continue
        assert np.all(np.array(box[0]) >= lo) and np.all(np.array(box[1]) <= hi), (name, box, lo, hi)
        drawn += 1
    assert drawn >= 3
    table = page.evaluate("() => document.body.innerText")
    assert "nan" not in table.split("8 Fits", 1)[-1].lower().split("parameters: sections")[0]
    context.close()


def test_two_tabs_keep_their_own_stage_and_follow_a_presenter(served, browser):
    url = served[0]
    expect = playwright_api.expect
    lap = _Laps()
    ctx1, page1, _ = open_page(browser, url, scene=False)
    ctx2, page2, _ = open_page(browser, url, scene=False)
    lap("two tabs open")
    go(page1, "4 Coarse")
    expect(page1.get_by_role("heading", name=re.compile("^4 Coarse"))).to_be_visible(timeout=60_000)
    page2.wait_for_timeout(500)
    expect(page2.get_by_label("Stage", exact=True)).to_have_value("1 Scans")  # its own stage
    go(page2, "7 Arcs")
    expect(page2.get_by_role("heading", name=re.compile("^7 Arcs"))).to_be_visible(timeout=60_000)
    expect(page1.get_by_label("Stage", exact=True)).to_have_value("4 Coarse")
    lap("each tab on its own stage")
    # Tab 1 presents: tab 2 follows its stage until it unticks "Follow the presenter".
    page1.get_by_role("tab", name="Teach").click()
    page1.get_by_label("Others follow me", exact=True).check()
    expect(page2.get_by_label("Stage", exact=True)).to_have_value("4 Coarse", timeout=60_000)
    expect(page2.get_by_label("Follow the presenter", exact=True)).to_be_checked()
    page1.get_by_role("button", name="Next", exact=True).click()
    expect(page2.get_by_label("Stage", exact=True)).to_have_value("5 Hypotheses", timeout=60_000)
    # The camera follows too: tab 1 frames its view elsewhere, tab 2's camera goes there.
    cam = "() => window.__viserMutable.camera.position.toArray()"
    before = np.array(page2.evaluate(cam))
    box = page1.locator("canvas").first.bounding_box()
    page1.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    page1.mouse.down()
    page1.mouse.move(box["x"] + box["width"] / 2 + 120, box["y"] + box["height"] / 2 + 30, steps=8)
    page1.mouse.up()
    page1.wait_for_timeout(1000)
    there = page1.evaluate(cam)
    assert np.linalg.norm(np.array(there) - before) > 0.5  # tab 1's camera moved
    # ... and tab 2's camera arrives where tab 1's stopped.
    page2.wait_for_function(f"(b) => {{ const p = ({cam})(); return Math.hypot(p[0]-b[0], p[1]-b[1], p[2]-b[2]) < 0.05; }}",
                            arg=there, timeout=60_000)
    page2.get_by_label("Follow the presenter", exact=True).uncheck()
    page1.get_by_role("button", name="Next", exact=True).click()
    expect(page1.get_by_label("Stage", exact=True)).to_have_value("6 Slices")
    page2.wait_for_timeout(800)
    expect(page2.get_by_label("Stage", exact=True)).to_have_value("5 Hypotheses")
    lap("followed, then on its own again")
    ctx1.close()
    ctx2.close()


def test_the_tour_walks_the_stages(served, browser):
    """Teach tab → Start the tour: each step sets the stage and says why and what to try."""
    url = served[0]
    expect = playwright_api.expect
    context, page, _ = open_page(browser, url)
    close_toast(page)
    _wait_all_done(page)
    # From the result, where the scans are drawn registered: the tour's first steps must show them
    # apart again, each in its own frame (a redrawn scan frame once kept its registered pose).
    go(page, "13 Result")
    expect(page.get_by_role("heading", name=re.compile("^13 Result"))).to_be_visible(timeout=60_000)
    where = "() => window.__viserMutable.nodeRefFromName['/scans/s1']?.position.toArray()"
    page.wait_for_function(f"() => {{ const p = ({where})(); return p && Math.hypot(...p) > 0.5; }}", timeout=60_000)
    page.get_by_role("tab", name="Teach").click()
    page.get_by_role("button", name="Start the tour", exact=True).click()
    for k, (stage, title) in enumerate((("1 Scans", "One tree, several stations"), ("2 Projection", "Rotating projection"),
                                        ("3 Matching", "Matching the most similar views"))):
        expect(page.get_by_role("heading", name=re.compile(f"Tour · step {k + 1} of \\d+: {title}"))).to_be_visible(timeout=60_000)
        expect(page.get_by_label("Stage", exact=True)).to_have_value(stage)
        expect(page.get_by_text("Try:", exact=False).first).to_be_visible()
        page.wait_for_function(f"() => {{ const p = ({where})(); return p && Math.hypot(...p) < 1e-6; }}", timeout=60_000)
        _screenshot(page, f"tour_step{k + 1}")
        page.get_by_role("button", name="Next ▶", exact=True).click()
    expect(page.get_by_role("heading", name=re.compile("Tour · step 4 of"))).to_be_visible(timeout=60_000)
    page.get_by_role("button", name="End tour", exact=True).click()
    expect(page.get_by_role("heading", name=re.compile("Tour · step"))).to_have_count(0)
    context.close()


@pytest.fixture(scope="module")
def windy(tmp_path_factory):
    """`treereg view` on two stations of a tree scanned in wind (the crown swayed 15 cm between them)."""
    from treereg_core.simulate.cases import CaseSpec, write_case

    case_dir = tmp_path_factory.mktemp("windy")
    write_case(CaseSpec(seed=101, height_m=8.5, angular_step_deg=(0.05, 0.05), n_stations=2, wind_m=0.15).build(),
               case_dir, dtype="float32")
    for url, _, _ in view([str(case_dir / "scan1.ply"), str(case_dir / "scan2.ply")]):
        yield url


def test_wind_shows_the_stem_profile_and_the_crown_motion(windy, browser):
    """A pair scanned in wind: the Fine stage says how far the crown moved and plots the target's stem
    offset against height; Result colours what moved with the wind apart from what does not fit."""
    expect = playwright_api.expect
    context, page, blocked = open_page(browser, windy, scene=False)
    close_toast(page)
    page.wait_for_function(
        "() => [...document.querySelectorAll('p, div')].some(e => /✓ 13 Result/.test(e.textContent) && "
        "!/[○…✗]/.test(e.textContent))", timeout=240_000)
    expect(page.get_by_text(re.compile(r"✓ 2 scan2\.ply"))).to_be_visible()
    go(page, "9 Fine")
    expect(page.get_by_text(re.compile(r"The crown moved 0\.\d\d m"))).to_be_visible()
    # The plot: its title and axis titles are SVG text in the panel.
    expect(page.get_by_text("scan2.ply's stem against scan1.ply's, by height")).to_be_visible()
    expect(page.get_by_text("height above the stem's base (m)")).to_be_visible()
    expect(page.get_by_text(re.compile(r"the stems agree up to \d+\.\d m"))).to_be_visible()
    _screenshot(page, "wind_fine_profile")
    go(page, "13 Result")
    page.get_by_label("Colour by", exact=True).click()
    page.get_by_role("option", name=re.compile("distance", re.I)).first.click()
    expect(page.get_by_text(re.compile(r"Pink: moved with the wind"))).to_be_visible()
    shot = _screenshot(page, "wind_result_moved")
    from treereg_viewer.palette import MOVED
    assert _colour_pixels(shot, MOVED, tol=40) > 50  # the crown's moved points are drawn pink
    assert not blocked
    context.close()
