"""End to end in headless Chromium: `treereg view` on the bundled demo, driven like a user.

Debian's chromium (`/usr/bin/chromium`) through Playwright for Python, no browser download, and an
offline guard (only http://127.0.0.1 may load). WebGL runs on SwiftShader. One server and one browser
for the module; the walk-through steps through every stage, changes a parameter and re-runs, uploads
a bad file, exports transforms.json and checks screenshots' pixels.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.browser

playwright_api = pytest.importorskip("playwright.sync_api")
from conftest import CHROMIUM, CHROMIUM_ARGS  # noqa: E402

if not CHROMIUM.exists():
    pytest.skip(f"{CHROMIUM} is not installed", allow_module_level=True)

from treereg_core.io.scans import read_points  # noqa: E402
from treereg_core.geometry.rigid import mean_displacement, rotation_error_deg  # noqa: E402
from treereg_core.io.transforms import read_transforms  # noqa: E402
from treereg_core.demo import DEMO_DIR  # noqa: E402
from treereg_viewer.palette import scan_color  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
LAUNCH_ARGS = CHROMIUM_ARGS
ROT_TOL_DEG = 0.5
DISP_TOL_M = 0.03
#: Screenshots are saved here for people (and the README) to look at.
SHOT_DIR = Path(os.environ.get("TREEREG_SHOTS", "/tmp/treereg-browser-shots"))


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """`treereg view --port 0 --out DIR` on the demo, as a user starts it; yields (url, out dir, seconds to URL)."""
    out = tmp_path_factory.mktemp("exports")
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""), PYTHONUNBUFFERED="1")
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "treereg_cli", "view", "--port", "0", "--out", str(out)],
        cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    url, lines = None, []
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and proc.poll() is None:
        line = proc.stdout.readline()
        lines.append(line)
        m = re.search(r"treereg view: (http://127\.0\.0\.1:\d+/)", line)
        if m:
            url = m.group(1)
            break
    if url is None:
        proc.kill()
        pytest.fail("treereg view did not start:\n" + "".join(lines))
    yield url, out, time.perf_counter() - t0, t0
    proc.terminate()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()


@pytest.fixture(scope="module")
def browser():
    with playwright_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=LAUNCH_ARGS)
        yield b
        b.close()


def _open(browser, url, scene=True):
    """A new browser context on `url`, offline-guarded; waits for the GUI (and the scans, if `scene`)."""
    context = browser.new_context(viewport={"width": 1700, "height": 1000}, accept_downloads=True)
    blocked: list[str] = []

    def guard(route):  # the app must load nothing but its own server
        if route.request.url.startswith(("http://127.0.0.1", "ws://127.0.0.1")):
            route.continue_()
        else:
            blocked.append(route.request.url)
            route.abort()

    context.route("**/*", guard)
    page = context.new_page()
    page.goto(url)
    playwright_api.expect(page.get_by_role("button", name="Run", exact=True)).to_be_visible(timeout=30_000)
    if scene:
        page.wait_for_function(
            "() => !!window.__viserMutable?.nodeRefFromName['/scans/s2/points'] && "
            "window.__viserTestpoints.rendererInfo.render.frame > 0", timeout=30_000)
    return context, page, blocked


class _Laps:
    """Seconds since the start of a test at named points (shown with `pytest -s`)."""

    def __init__(self) -> None:
        self.t0 = time.perf_counter()

    def __call__(self, label: str) -> None:
        print(f"  {time.perf_counter() - self.t0:6.1f} s  {label}")


def _close_toast(page):
    """The 'Software WebGL rendering detected' notice covers the top of the scene."""
    toast = page.get_by_text("Software WebGL rendering detected")
    if toast.count():
        toast.locator("xpath=ancestor::div[contains(@class,'Notification-root')][1]").get_by_role("button").click()


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
        "() => [...document.querySelectorAll('p, div')].some(e => /✓ 10 Result/.test(e.textContent) && "
        "!/[○…✗]/.test(e.textContent) && /1 Scans/.test(e.textContent))", timeout=timeout_ms)


def _param_input(page, label):
    """The text input of a parameter (viser's text inputs are not tied to their label element)."""
    return page.locator("label", has_text=re.compile(f"^{re.escape(label)}$")).locator(
        "xpath=ancestor::div[.//input][1]//input").first


def _go(page, label):
    """Pick a stage in the selector, like a user."""
    page.get_by_label("Stage", exact=True).click()
    page.get_by_role("option", name=label, exact=True).click()


def test_walk_through_the_demo(served, browser):
    url, out_dir, url_seconds, t_start = served
    expect = playwright_api.expect
    lap = _Laps()
    context, page, blocked = _open(browser, url)
    visible_seconds = time.perf_counter() - t_start
    lap("page open, scans drawn")
    _close_toast(page)
    _wait_all_done(page)
    ready_seconds = time.perf_counter() - t_start
    lap("every stage done")
    print(f"\ndemo: URL after {url_seconds:.1f} s, scans drawn in the browser after {visible_seconds:.1f} s, "
          f"every stage done after {ready_seconds:.1f} s")

    # Step through every stage with Next; each shows its own panel.
    titles = ["1 Scans", "2 Projection", "3 Matching", "4 Coarse", "5 Slices", "6 Arcs", "7 Fits", "8 Fine", "9 ICP",
              "10 Result"]
    expect(page.get_by_role("heading", name=titles[0])).to_be_visible()
    for k in range(1, len(titles)):
        page.get_by_role("button", name="Next", exact=True).click()
        expect(page.get_by_role("heading", name=re.compile("^" + re.escape(titles[k]) + "(:|$)"))).to_be_visible(timeout=20_000)
        if k == 1:  # the image panel (docked left) shows each scan's projection image in its colour
            panel = _screenshot(page, "stage1_projection")[:, :560]
            for i in range(3):
                assert _colour_pixels(panel, scan_color(i), tol=40) > 300, f"projection of scan {i + 1} missing"
        if k == 2:
            expect(page.get_by_text("Similarity", exact=False).first).to_be_visible()
        if k == 7:
            _screenshot(page, "stage8_fine")
    lap("stepped through every stage")
    result = _screenshot(page, "stage7_result")
    scene = result[:, 580:1300]  # between the docked panel (560 px) and the control panel
    counts = [_colour_pixels(scene, scan_color(i)) for i in range(3)]
    assert all(c > 200 for c in counts), f"scan colours in the final overlay: {counts}"
    lap("screenshots checked")

    # Change a fine-stage parameter and re-run: only fine and evaluation run again.
    _go(page, "8 Fine")
    expect(page.get_by_role("heading", name=re.compile("^8 Fine"))).to_be_visible()
    box = _param_input(page, "max iterations")
    box.fill("2")
    box.press("Enter")
    expect(page.get_by_text(re.compile("Parameters changed: 8 Fine, 10 Result must re-run"))).to_be_visible(timeout=10_000)
    t0 = time.perf_counter()
    page.get_by_role("button", name="Run", exact=True).click()
    expect(page.get_by_text(re.compile(r"Ran 8 Fine, 10 Result in [\d.]+ s"))).to_be_visible(timeout=60_000)
    print(f"fine + evaluation re-run seen in the browser after {time.perf_counter() - t0:.1f} s: "
          f"{page.get_by_text(re.compile('Ran 8 Fine')).first.inner_text()}")
    lap("parameter changed and re-run")

    # A bad upload: a message, nothing else changes.
    page.get_by_role("tab", name="Scans").click()
    with page.expect_file_chooser() as chooser:
        page.get_by_role("button", name="Add a scan file").click()
    chooser.value.set_files(files=[{"name": "broken.ply", "mimeType": "application/octet-stream",
                                    "buffer": b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n"}])
    # The message names the file the user picked (not the temporary copy the server read).
    expect(page.get_by_text(re.compile("Upload rejected — broken.ply: "))).to_be_visible(timeout=15_000)
    assert "treereg-upload-" not in page.evaluate("() => document.body.innerText")
    expect(page.get_by_label(re.compile("^4: "))).to_have_count(0)
    _wait_all_done(page, 5_000)  # every stage is still done
    lap("bad upload rejected")

    # Export: download transforms.json and compare with the demo's truth.
    page.get_by_role("tab", name="Files").click()
    page.get_by_role("button", name="Download transforms.json").click()
    with page.expect_download() as dl:
        page.get_by_role("link", name=re.compile("transforms.json")).first.click()
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
    assert (out_dir / "transforms.json").is_file() and (out_dir / "merged.ply").is_file()  # --out
    assert not blocked, f"the page tried to load {blocked}"
    lap("exported and checked")
    context.close()


def test_two_tabs_see_one_state(served, browser):
    url = served[0]
    expect = playwright_api.expect
    lap = _Laps()
    ctx1, page1, _ = _open(browser, url, scene=False)
    lap("tab 1 open")
    ctx2, page2, _ = _open(browser, url, scene=False)
    lap("tab 2 open")
    page1.get_by_label("Stage", exact=True).click()
    lap("tab 1 dropdown open")
    page1.get_by_role("option", name="4 Coarse", exact=True).click()  # one tab steps; the other follows
    lap("tab 1 stepped")
    expect(page2.get_by_role("heading", name=re.compile("^4 Coarse"))).to_be_visible(timeout=10_000)
    expect(page2.get_by_label("Stage", exact=True)).to_have_value("4 Coarse")
    ctx1.close()
    ctx2.close()
