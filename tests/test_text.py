"""Text from outside shown as text: `treereg_core.text.shown` (controls as escapes) and the app's
`treereg_viewer.text.md`/`html`, checked with a CommonMark renderer that passes raw HTML through, as
viser's does; then the whole app on scans with hostile names, every stage and every pair, every
markdown it sent rendered and searched for what the names would make."""

from __future__ import annotations

import dataclasses
import html as html_lib
import re

import pytest
import viser
import viser._gui_handles as gui_handles
from markdown_it import MarkdownIt

from treereg_core.demo import demo_case
from treereg_core.text import shown
from treereg_viewer.draw.common import breakable, md_table
from treereg_viewer.text import html, md, md_sentence

#: Names as colleagues' files, shared drives and uploads may bring them.
HOSTILE = [
    '<iframe srcdoc="&lt;script&gt;parent.x=1&lt;&#47;script&gt;">.ply',
    '<img src=x onerror="window.x=2"> *b* [a](https:x.org) www.example.com.ply',
    "line\n✓ verified `c` ![i](y.png) <b>bold.ply",
    "| a | b |\n|---|---|\n# heading\n> quote\n- item\n1. item\n***\n",
    "\\*not bold\\* &amp; &lt;tag&gt; {x} ~~del~~ <!-- comment --> <https://x.org> a@b.org",
    "\x1b]0;title\x07\x1b[2J\u202etxt.ply\r\n\t\x00",
]

#: CommonMark with raw HTML on (viser renders it unsanitised) and GFM tables and strikethrough.
RENDER = MarkdownIt("commonmark", {"html": True}).enable(["table", "strikethrough"])


def _paragraph_text(markdown: str) -> str:
    """The text of a markdown that must render as one paragraph of text (fails on any other element)."""
    out = RENDER.render(markdown).replace("<wbr>", "")  # an empty break opportunity, no element to fear
    m = re.fullmatch(r"<p>(.*)</p>\n", out, re.DOTALL)
    assert m, out
    assert "<" not in m.group(1), out  # no element inside it: every "<" came out as &lt;
    return html_lib.unescape(m.group(1))


def test_shown_writes_controls_as_escapes_and_keeps_everything_else():
    assert shown("scan1.ply") == "scan1.ply"
    assert shown("Fichte ölig – 樹.ply") == "Fichte ölig – 樹.ply"
    assert shown("a\nb") == "a\\nb"
    assert shown("\x1b]0;t\x07") == "\\x1b]0;t\\x07"
    assert shown("\u202eylp.exe") == "\\u202eylp.exe"
    assert shown("caf\udcc3") == "caf\\udcc3"  # an undecodable byte of a non-UTF-8 file name
    for s in HOSTILE:
        assert "\n" not in shown(s) and "\x1b" not in shown(s)


@pytest.mark.parametrize("text", HOSTILE)
def test_md_renders_exactly_the_text_and_no_element(text):
    assert _paragraph_text(md(text)) == shown(text)
    # Inside the app's own markup (bold, a table cell) it stays text too.
    bold = re.fullmatch(r"<p><strong>(.*)</strong></p>\n", RENDER.render(f"**{md(text)}**").replace("<wbr>", ""),
                        re.DOTALL)
    assert bold and "<" not in bold.group(1) and html_lib.unescape(bold.group(1)) == shown(text)
    table = RENDER.render(md_table(("scan", "n"), [(breakable(md(text)), 3)]))
    cells = re.findall(r"<td>(.*?)</td>", table, re.DOTALL)
    assert len(cells) == 2, table  # one row of two cells: the name broke no cell and no row
    assert html_lib.unescape(cells[0].replace("<wbr>", "")) == shown(text), table
    for tag in ("<img", "<iframe", "<a ", "<b>", "<em>", "<code>", "<h1", "<blockquote", "<li", "<del", "<hr"):
        assert tag not in table


def test_md_table_leaves_an_escaped_pipe_as_it_is():
    # viser's GFM tables (micromark) read two backslashes and a '|' as an escaped backslash and a cell
    # break (markdown-it and GitHub do not): a '|' that md escaped must not be escaped again.
    table = md_table(("scan", "n"), [(md("x|y"), 3), ("own|pipe", 4), (md("a\\|b"), 5)])
    assert table.splitlines()[2:] == ["| x\\|y | 3 |", "| own\\|pipe | 4 |", "| a\\\\\\|b | 5 |"]


def test_md_sentence_and_html():
    assert _paragraph_text(md_sentence("the <b>scan</b> failed")) == "The <b>scan</b> failed."
    # plotly decodes numeric entities, and only a few named ones (not &quot;); '%{y}' in a hover
    # template would be a value.
    assert html('<img src=x onerror="a()">') == "&lt;img src=x onerror=&#34;a()&#34;&gt;"
    assert html("it's 100% %{y}") == "it&#39;s 100&#37; &#37;{y}"
    assert html("a\nb") == "a\\nb"


@pytest.fixture(scope="module")
def hostile_app():
    """The app on the demo's stations under hostile names, every markdown and plot it sent recorded."""
    from treereg_viewer.app import TreeregApp
    from treereg_viewer.controller import Controller

    sent: list[str] = []
    parse = gui_handles._parse_markdown

    def record(markdown: str, image_root):  # every markdown element's content passes here
        sent.append(markdown)
        return parse(markdown, image_root)

    gui_handles._parse_markdown = record
    figures: list[str] = []
    prop = gui_handles.GuiPlotlyHandle.figure

    def set_figure(self, fig):
        figures.append(fig.to_json())
        prop.fset(self, fig)

    gui_handles.GuiPlotlyHandle.figure = property(prop.fget, set_figure)
    demo = demo_case()
    scans = [dataclasses.replace(s, name=n) for s, n in zip(demo.scans, HOSTILE[:3])]
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = TreeregApp(server, Controller(scans))
    try:
        assert app.controller.wait_idle(300.0) and app.drawer.wait_idle(60.0)
        yield app, sent, figures
    finally:
        app.close()
        server.stop()
        gui_handles._parse_markdown = parse
        gui_handles.GuiPlotlyHandle.figure = prop


@pytest.mark.slow
def test_hostile_names_make_no_element_on_any_stage_or_pair(hostile_app):
    from treereg_viewer.draw.common import pair_label
    from treereg_viewer.labels import STAGE_NAMES

    app, sent, figures = hostile_app
    snap = app.controller.snapshot
    for k in range(len(snap.pairs)):
        app.viewer.select_target(pair_label(snap, k))
        for name in STAGE_NAMES:
            app.select_stage(name)
            assert app.controller.wait_idle(120.0) and app.drawer.wait_idle(60.0)
    made = []
    for markdown in sent:
        out = RENDER.render(markdown)
        for tag in ("<iframe", "<img", "<a ", "<b>"):
            if tag in out:
                made.append((tag, markdown[:200]))
    assert not made, made
    # Every name reached the page somewhere, as its text (not dropped to pass the check above).
    texts = "\n".join(html_lib.unescape(RENDER.render(m).replace("<wbr>", "")) for m in sent)
    for name in HOSTILE[:3]:
        assert shown(name) in texts, name
    # plotly renders HTML in titles and hover text: the names reach it as entities.
    assert figures and not any(re.search(r"<(img|iframe|b)\b", f) for f in figures)
