"""Helpers of the browser tests: `treereg view` started as a user starts it, a page opened on it
(offline-guarded), stepping like a user, and what a person reading the page must never meet
(a table wider than its panel, "nan", a sentence said twice).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Iterator

import pytest

REPO = Path(__file__).resolve().parent.parent


def view(args: list[str], cwd: Path = REPO, output: list[str] | None = None) -> Iterator[tuple[str, float, float]]:
    """`treereg view --port 0 ARGS` started as a user starts it (from `cwd`); yields (url, seconds to
    the URL, start time) and stops the app afterwards. Given `output`, every line the server prints
    (stdout and stderr) is appended to it as it comes (a traceback there is a bug)."""
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""), PYTHONUNBUFFERED="1")
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "treereg_cli", "view", "--port", "0", *args],
        cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
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
    if output is not None:
        output += lines
        threading.Thread(target=lambda: output.extend(iter(proc.stdout.readline, "")), daemon=True).start()
    yield url, time.perf_counter() - t0, t0
    proc.terminate()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()


def offline(context) -> list[str]:
    """Only the app's own server may answer the context's pages; returns what they tried to load
    from elsewhere (the app must load nothing else)."""
    blocked: list[str] = []

    def guard(route):
        if route.request.url.startswith(("http://127.0.0.1", "ws://127.0.0.1")):
            route.continue_()
        else:
            blocked.append(route.request.url)
            route.abort()

    context.route("**/*", guard)
    return blocked


def open_page(browser, url: str, scene: bool = True, width: int = 1700, height: int = 1000):
    """A new browser context on `url`, offline-guarded; waits for the GUI (and the scans, if `scene`).
    Returns (context, page, the URLs the page tried to load from elsewhere)."""
    from playwright.sync_api import expect

    context = browser.new_context(viewport={"width": width, "height": height}, accept_downloads=True)
    blocked = offline(context)
    page = context.new_page()
    # The machine is shared: SwiftShader and the app compete with other work for two cores.
    page.set_default_timeout(90_000)
    expect.set_options(timeout=60_000)
    page.goto(url)
    expect(page.get_by_role("button", name="Run", exact=True)).to_be_visible(timeout=90_000)
    if scene:
        page.wait_for_function(
            "() => !!window.__viserMutable?.nodeRefFromName['/scans/s2/points'] && "
            "window.__viserTestpoints.rendererInfo.render.frame > 0", timeout=90_000)
    return context, page, blocked


def close_toast(page) -> None:
    """The 'Software WebGL rendering detected' notice covers the top of the scene."""
    toast = page.get_by_text("Software WebGL rendering detected")
    if toast.count():
        toast.locator("xpath=ancestor::div[contains(@class,'Notification-root')][1]").get_by_role("button").click()


def go(page, label: str) -> None:
    """Pick a stage in the selector, like a user."""
    page.get_by_label("Stage", exact=True).click()
    page.get_by_role("option", name=label, exact=True).click()


def choose(page, label: str, option: str) -> None:
    """Pick `option` in the dropdown labelled `label`. A list the app re-rendered while it was open
    closes (seen once in CI: the option detached for 90 s): opened again, as a person would."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    for attempt in range(3):
        page.get_by_label(label, exact=True).click()
        try:
            page.get_by_role("option", name=option, exact=True).click(timeout=15_000)
            return
        except PlaywrightTimeout:  # the last attempt raises it
            if attempt == 2:
                raise


def wait_stages_done(page, timeout_ms: int = 240_000) -> None:
    """Every stage has run (none stale or running; a scan may have failed its verdict)."""
    page.wait_for_function(
        "() => [...document.querySelectorAll('p, div')].some(e => /✓ 13 Result/.test(e.textContent) && "
        "!/[○…]/.test(e.textContent) && /1 Scans/.test(e.textContent))", timeout=timeout_ms)


#: Every table of the page whose content is wider than the box it sits in (its parent): the table's
#: first header cell's text and both widths. The docked panels are the tables' containers.
CLIPPED_TABLES = """() => [...document.querySelectorAll('table')].filter(t => t.offsetParent !== null)
  .map(t => [t.querySelector('th, td')?.textContent ?? '', t.scrollWidth, t.parentElement.clientWidth,
             t.getBoundingClientRect().right - t.parentElement.getBoundingClientRect().right])
  .filter(([_, sw, cw, beyond]) => sw > cw + 1 || beyond > 1)"""

#: The text of each visible panel of the app (the docked left panel and the control panel).
PANEL_TEXTS = """() => [...document.querySelectorAll('table, p, li, h1, h2, h3, h4')]
  .filter(e => e.offsetParent !== null).map(e => e.innerText)"""


def repeated_sentences(texts: list[str], min_chars: int = 30) -> list[str]:
    """Sentences (or clauses between ';') said twice within one text: a hint that repeats itself."""
    out = []
    for text in texts:
        parts = [p.strip() for p in re.split(r"[.;:]\s+|\n", text) if len(p.strip()) >= min_chars]
        seen: set[str] = set()
        for p in parts:
            key = p.lower()
            if key in seen:
                out.append(p)
            seen.add(key)
    return out


def reading_problems(page) -> list[str]:
    """What a person must never meet on the page as it stands: a table wider than its panel (clipped
    or scrolling sideways), "nan" shown as a number, a sentence repeated within one paragraph."""
    problems = [f"table '{head[:30]}' is {sw} px wide in a {cw} px box" for head, sw, cw, *_ in page.evaluate(CLIPPED_TABLES)]
    texts = page.evaluate(PANEL_TEXTS)
    problems += [f"'nan' in: {t[:120]!r}" for t in texts if re.search(r"\bnan\b", t, re.IGNORECASE)]
    problems += [f"said twice: {s[:120]!r}" for s in repeated_sentences(texts)]
    return problems


def drawn(page, name: str) -> bool:
    """Whether the scene node `name` is in the 3-D scene now (the client keeps a removed node's
    name, detached from the scene)."""
    return bool(page.evaluate("(n) => !!window.__viserMutable.nodeRefFromName[n]?.parent", name))


#: What a plot in the docked panel must never show (issue 32 item 4, at 1280 x 720 and 1920 x 1080):
#: its title, subplot titles, axis titles or legend cut by the plot's edges (3 px allowed: a legend's
#: border), or two of them over each other (a legend's entries among themselves excepted). Plotly's
#: own text elements, measured by their bounding boxes.
PLOT_PROBLEMS = """() => {
  const R = e => e.getBoundingClientRect();
  const seen = r => r.width > 0.5 && r.height > 0.5;
  const inter = (a, b) => Math.max(0, Math.min(a.right, b.right) - Math.max(a.left, b.left)) *
                          Math.max(0, Math.min(a.bottom, b.bottom) - Math.max(a.top, b.top));
  const out = [];
  for (const plot of document.querySelectorAll('.js-plotly-plot')) {
    if (plot.offsetParent === null || !seen(R(plot))) continue;
    const box = R(plot);
    const name = (plot.querySelector('.gtitle')?.textContent || plot.querySelector('.annotation-text')?.textContent
                  || 'a plot').slice(0, 40);
    const texts = [...plot.querySelectorAll('text')].filter(
      e => /^(gtitle|x\\d*title|y\\d*title|annotation-text|legendtext)$/.test(e.getAttribute('class') || ''));
    const items = [...texts, ...plot.querySelectorAll('.legend .bg')].map(e => {
      const cls = e.getAttribute('class') || '';
      return [cls === 'bg' ? 'legend' : cls === 'legendtext' ? 'legend text' : cls, (e.textContent || '').slice(0, 30), R(e)];
    }).filter(([, , r]) => seen(r));
    for (const [kind, text, r] of items) {
      if (kind !== 'legend text' && (r.left < box.left - 3 || r.right > box.right + 3 || r.top < box.top - 3 ||
                                     r.bottom > box.bottom + 3))
        out.push(`${name}: ${kind} '${text}' cut by the plot's edge`);
    }
    for (let i = 0; i < items.length; i++) for (let j = i + 1; j < items.length; j++) {
      const [ka, ta, a] = items[i], [kb, tb, b] = items[j];
      if (!(ka.startsWith('legend') && kb.startsWith('legend')) && inter(a, b) > 4)
        out.push(`${name}: ${ka} '${ta}' over ${kb} '${tb}'`);
    }
  }
  return out;
}"""


def layout_problems(page) -> list[str]:
    """`reading_problems` and every plot's `PLOT_PROBLEMS`."""
    return reading_problems(page) + page.evaluate(PLOT_PROBLEMS)
