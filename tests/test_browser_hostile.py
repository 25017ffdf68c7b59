"""Hostile scan names in headless Chromium: no script runs, no element is made, the name reads as given.

A scan's file name is untrusted text (colleagues' files, shared drives, public data sets, uploads
from any tab). viser renders markdown with raw HTML unsanitised and plotly renders HTML in titles:
before `treereg_viewer.text`, a scan named `<iframe srcdoc=…>.ply` ran its script in every tab on
every stage. Here the demo's stations are given such names (and one is uploaded from a second tab);
every stage is walked, a pair between two hostile names opened, the exports' summary read, and after
each the page is searched for what the names would make: a script's mark, an iframe, an image, a
link, bold or code from their markup.
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

from treereg_core.demo import DEMO_DIR  # noqa: E402
from treereg_viewer.labels import STAGE_NAMES, label  # noqa: E402

#: A file name cannot hold "/" (the entities can): the iframe's script sets a mark in its parent.
IFRAME = '<iframe srcdoc="&lt;script&gt;parent.__pwned=1&lt;&#47;script&gt;">.ply'
#: An image whose error handler runs script, a markdown link, emphasis and an autolinked address.
IMG = '<img src=x onerror="window.__pwned=2"> *b* [a](https:x.org) www.example.com.ply'
#: A newline that would start a line of its own, a code span, a markdown image, an HTML tag.
LINE = "line\n✓ verified `c` ![i](y.png) <b>bold.ply"  # no "/": a file name cannot hold one
#: Uploaded from the second tab: every connected tab shows its name.
UPLOADED = '<img src=x onerror="window.__pwned=3">up.ply'

#: What the names would make if they were markup, and whether a script ran or the title changed.
INJECTED = """() => ({
  pwned: window.__pwned ?? null,
  title: document.title,
  iframes: document.querySelectorAll('iframe').length,
  images: [...document.querySelectorAll('img')].map(i => i.getAttribute('src') ?? '')
          .filter(s => s === 'x' || s.includes('y.png')),
  links: [...document.querySelectorAll('a')].map(a => a.getAttribute('href') ?? '')
         .filter(h => h.includes('x.org') || h.includes('example.com')),
  marked: [...document.querySelectorAll('b, strong, em, i, code')].map(e => e.textContent)
          .filter(t => t === 'b' || t.startsWith('bold') || t === 'c'),
})"""


def _injected(page) -> dict:
    """What the names made on the page as it stands (empty: nothing)."""
    found = page.evaluate(INJECTED)
    title = found.pop("title")
    bad = {k: v for k, v in found.items() if v}
    if title != TITLE[0]:
        bad["title"] = title
    return bad


#: The page's title before any name was shown (set by the first page opened).
TITLE: list[str] = []


@pytest.fixture(scope="module")
def hostile(tmp_path_factory):
    """`treereg view` on the demo's three stations under hostile file names, as a user starts it."""
    root = tmp_path_factory.mktemp("hostile")
    for src, name in (("scan1.ply", IFRAME), ("scan2.ply", IMG), ("scan3.ply", LINE)):
        shutil.copy(DEMO_DIR / src, root / name)
    for url, _, _ in view([IFRAME, IMG, LINE], cwd=root):
        yield url


def _clean(page, where: str) -> None:
    found = _injected(page)
    assert not found, f"{where}: {found}"


def test_hostile_names_run_no_script_and_make_no_element(hostile, browser):
    expect = playwright_api.expect
    context, page, blocked = open_page(browser, hostile, width=1280, height=720)
    TITLE.append(page.evaluate("() => document.title"))
    close_toast(page)
    wait_stages_done(page)
    text = page.evaluate("() => document.body.innerText")
    # The names read as given, one line each (the newline shown as \n), in the verdict line.
    assert '<img src=x onerror="window.__pwned=2"> *b* [a](https:x.org) www.example.com.ply' in text, text[:800]
    assert "line\\n✓ verified `c` ![i](y.png) <b>bold.ply" in text, text[:800]
    _clean(page, "first view")
    for k, name in enumerate(STAGE_NAMES):
        if k:
            page.get_by_role("button", name="Next", exact=True).click()
        expect(page.get_by_role("heading", name=re.compile("^" + re.escape(label(name)) + "(:|$)"))).to_be_visible(
            timeout=90_000)
        page.wait_for_timeout(300)
        _clean(page, label(name))
    # A pair between two hostile names, on the stages that head their panel with it.
    pair = f"{LINE.replace(chr(10), chr(92) + 'n')} → {IMG}"
    for name in ("coarse", "verify"):
        go(page, label(name))
        choose(page, "Pair", pair)
        expect(page.get_by_role("heading", name=re.compile(re.escape(label(name)) + ": line"))).to_be_visible()
        page.wait_for_timeout(300)
        _clean(page, f"{label(name)}, {pair!r}")
    # The exports' summary names the scans.
    page.get_by_role("tab", name="Files").click()
    with page.expect_download(timeout=60_000):
        page.get_by_role("button", name="Download transforms.json").click()
    expect(page.get_by_text(re.compile(r"^Exported the transforms of")).first).to_be_visible()
    _clean(page, "export summary")

    # An upload from a second tab: the first tab shows its name too, as text.
    other, page2, blocked2 = open_page(browser, hostile, width=1024, height=640)
    page2.get_by_role("tab", name="Scans").click()
    with page2.expect_file_chooser() as chooser:
        page2.get_by_role("button", name="Add a scan file").click()
    chooser.value.set_files(files=[{"name": UPLOADED, "mimeType": "application/octet-stream",
                                    "buffer": (DEMO_DIR / "scan3.ply").read_bytes()}])
    for p in (page, page2):
        expect(p.get_by_text(re.compile(re.escape(f"Added {UPLOADED}")))).to_be_visible(timeout=90_000)
        _clean(p, "after the upload")
    assert not blocked and not blocked2, blocked + blocked2
    other.close()
    context.close()
