"""Every stage on every pair the app offers, in headless Chromium (issue 29): `treereg view` on the
demo's three stations, and on those plus a station of another tree (four scans, six pairs, some of
them failed). Each stage's "Pair" list is walked to its end; the page must never say "Drawing
failed" and the server must print no traceback. One app per scan count, a small window.
"""

from __future__ import annotations

import re
import shutil

import pytest

pytestmark = pytest.mark.browser

playwright_api = pytest.importorskip("playwright.sync_api")
from browser import choose, close_toast, go, open_page, view, wait_stages_done  # noqa: E402
from conftest import CHROMIUM  # noqa: E402

if not CHROMIUM.exists():
    pytest.skip(f"{CHROMIUM} is not installed", allow_module_level=True)

from test_app_pairs import other_tree  # noqa: E402
from treereg_core.demo import DEMO_DIR, demo_case  # noqa: E402
from treereg_core.io.scans import write_scan  # noqa: E402
from treereg_core.stages import STAGE_NAMES, stage  # noqa: E402
from treereg_viewer.labels import label  # noqa: E402

W, H = 1024, 640

#: Whether the panel's heading starts with the given text (the stage and the pair drawn).
HEADING = "([head]) => [...document.querySelectorAll('h1, h2, h3, h4')].some(e => e.innerText.startsWith(head))"


@pytest.fixture(scope="module", params=[3, 4], ids=["3 scans", "4 scans"])
def served(request, tmp_path_factory):
    """`treereg view` on the scans (the server's output collected); yields (url, pair labels, output)."""
    root = tmp_path_factory.mktemp("pairs")
    names = [s.name for s in demo_case().scans]
    for name in names:
        shutil.copy(DEMO_DIR / name, root / name)
    if request.param == 4:
        other = other_tree()
        write_scan(root / other.name, other.points, dtype="float32")
        names.append(other.name)
    # With three scans every pair; with these four the pipeline registers all six too (test_app_pairs).
    pairs = [f"{names[j]} → {names[i]}" for i in range(len(names)) for j in range(i + 1, len(names))]
    output: list[str] = []
    for url, _, _ in view(names, cwd=root, output=output):
        yield url, pairs, output


def test_every_stage_draws_every_offered_pair(served, browser):
    url, pairs, output = served
    context, page, blocked = open_page(browser, url, width=W, height=H)
    close_toast(page)
    wait_stages_done(page)
    go(page, label("matching"))  # what the "Pair" list offers, as a person opens it
    page.get_by_label("Pair", exact=True).click()
    assert page.get_by_role("option").all_inner_texts() == pairs
    page.keyboard.press("Escape")
    failed, shown, seen = {}, pairs[0], ""
    for name in STAGE_NAMES:
        go(page, label(name))
        # Every stage's list shows the pair last chosen: walk from it (there and back), one pick fewer.
        walk = (pairs if shown == pairs[0] else pairs[::-1]) if stage(name).per == "pair" else (None,)
        for pair in walk:
            if pair is not None and pair != shown:
                choose(page, "Pair", pair)
                shown = pair
            head = f"{label(name)}: {pair}" if pair is not None else label(name)
            try:
                page.wait_for_function(HEADING, arg=[head], timeout=30_000)
            except playwright_api.TimeoutError:
                failed[head] = "not drawn"
            said = re.search(r"Drawing failed[^\n]*", page.evaluate("() => document.body.innerText"))
            if said and said.group(0) != seen:  # the status line keeps saying it until the next message
                failed[head] = seen = said.group(0)
    page.wait_for_timeout(500)  # a traceback is printed before its one line reaches the page
    assert not failed, failed
    assert not [line for line in output if "Traceback" in line], "".join(output)[-3000:]
    assert not blocked
    context.close()
