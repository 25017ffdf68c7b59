"""Every stage on every pair the app offers, in headless Chromium (issue 29): `treereg view` on the
demo's three stations and a station of another tree (four scans, six pairs, some of them failed).
Each stage's "Pair" list is walked to its end; the page must never say "Drawing failed" and the
server must print no traceback. A small window. (Three scans, whose pairs the pipeline chooses
otherwise, are walked stage by stage and pair by pair without a browser in test_app_pairs; a
walk of their own here took 53-61 s of the suite.)

The demo's three stations carry hostile file names. A scan's name is untrusted text (colleagues' files,
shared drives, public data sets, uploads from any tab); viser renders markdown with raw HTML
unsanitised and plotly renders HTML in titles: before `treereg_viewer.text`, a scan named
`<iframe srcdoc=…>.ply` ran its script in every tab on every stage. After each stage and pair, and
after the exports' summary and an upload from a second tab, the page is searched for what the names
would make: a script's mark, a changed title, an iframe, an image, a link, bold or code.
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
from treereg_core.text import shown as printable  # noqa: E402
from treereg_viewer.labels import label  # noqa: E402

W, H = 1024, 640

#: A file name cannot hold "/" (the entities can): the iframe's script sets a mark in its parent.
IFRAME = '<iframe srcdoc="&lt;script&gt;parent.__pwned=1&lt;&#47;script&gt;">.ply'
#: An image whose error handler runs script, a markdown link, emphasis and an autolinked address.
IMG = '<img src=x onerror="window.__pwned=2"> *b* [a](https:x.org) www.example.com.ply'
#: A newline that would start a line of its own, a code span, a markdown image, an HTML tag.
LINE = "line\n✓ verified `c` ![i](y.png) <b>bold.ply"
HOSTILE = (IFRAME, IMG, LINE)
#: Uploaded from a second tab: every connected tab shows its name.
UPLOADED = '<img src=x onerror="window.__pwned=3">up.ply'

#: What the names would make if they were markup, and whether a script ran.
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


def injected(page, title: str) -> dict:
    """What the names made on the page as it stands (empty: nothing)."""
    found = page.evaluate(INJECTED)
    now = found.pop("title")
    bad = {k: v for k, v in found.items() if v}
    if now != title:
        bad["title"] = now
    return bad


#: Whether the panel's heading starts with the given text (the stage and the pair drawn).
HEADING = "([head]) => [...document.querySelectorAll('h1, h2, h3, h4')].some(e => e.innerText.startsWith(head))"


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """`treereg view` on the scans (the server's output collected); yields (url, pair labels, output)."""
    root = tmp_path_factory.mktemp("pairs")
    for name, hostile in zip((s.name for s in demo_case().scans), HOSTILE):  # under hostile names
        shutil.copy(DEMO_DIR / name, root / hostile)
    other = other_tree()
    write_scan(root / other.name, other.points, dtype="float32")
    names = [*HOSTILE, other.name]
    # With these four the pipeline registers all six pairs (test_app_pairs, which also walks three scans).
    pairs = [f"{printable(names[j])} → {printable(names[i])}" for i in range(len(names)) for j in range(i + 1, len(names))]
    output: list[str] = []
    for url, _, _ in view(names, cwd=root, output=output):
        yield url, pairs, output


def test_every_stage_draws_every_offered_pair(served, browser):
    url, pairs, output = served
    context, page, blocked = open_page(browser, url, width=W, height=H)
    title = page.evaluate("() => document.title")
    close_toast(page)
    wait_stages_done(page)
    # The names read as given, one line each (the newline shown as \n), in the verdict line.
    text = page.evaluate("() => document.body.innerText")
    assert all(printable(n) in text for n in HOSTILE), text[:800]
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
            if made := injected(page, title):
                failed[head] = made
    page.wait_for_timeout(500)  # a traceback is printed before its one line reaches the page
    assert not failed, failed
    assert not [line for line in output if "Traceback" in line], "".join(output)[-3000:]
    _exports_and_an_upload_show_names_as_text(browser, url, page, title)
    assert not blocked
    context.close()


def _exports_and_an_upload_show_names_as_text(browser, url: str, page, title: str) -> None:
    """The exports' summary names the scans; a scan uploaded from a second tab is named in both."""
    expect = playwright_api.expect
    page.get_by_role("tab", name="Files").click()
    with page.expect_download(timeout=60_000):
        page.get_by_role("button", name="Download transforms.json").click()
    expect(page.get_by_text(re.compile(r"^Exported the transforms of")).first).to_be_visible()
    assert not injected(page, title), injected(page, title)
    other, page2, blocked = open_page(browser, url, width=W, height=H)
    page2.get_by_role("tab", name="Scans").click()
    with page2.expect_file_chooser() as chooser:
        page2.get_by_role("button", name="Add a scan file").click()
    chooser.value.set_files(files=[{"name": UPLOADED, "mimeType": "application/octet-stream",
                                    "buffer": (DEMO_DIR / "scan3.ply").read_bytes()}])
    for p in (page, page2):
        expect(p.get_by_text(re.compile(re.escape(f"Added {UPLOADED}")))).to_be_visible(timeout=90_000)
        assert not injected(p, title), injected(p, title)
    assert not blocked
    other.close()
