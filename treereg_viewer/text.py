"""Text from outside, escaped where the app shows it.

viser renders markdown with raw HTML unsanitised (an `<iframe srcdoc=…>` in a file name ran script in
every tab) and GitHub-flavoured extras (links, images, autolinked `www.` and `http://` addresses),
and plotly renders a subset of HTML in titles and hover text. Scan names, file names, parameter
values and the core's messages (which quote them) come from colleagues' files, shared drives and
uploads: each goes through one of these functions wherever the app puts it into markdown or HTML.

- `md(text)`: for markdown (panels, tables, the status and verdict lines, notifications' bodies
  when rendered as markdown). Every ASCII punctuation character is backslash-escaped, which
  CommonMark defines as that character, literally: no tag, entity, link, image, emphasis, code
  span or table cell break can start inside the text, and it reads exactly as given; GFM's
  autolinked addresses are split by an empty `<wbr>`.
- `html(text)`: for plotly's titles, axis titles and hover text (HTML entities, which plotly decodes:
  numeric ones for quotes and `%`, see `html`).

Both first show control characters as escapes (`treereg_core.text.shown`): a newline in a name
cannot start a markdown block, and the text stays one line.
"""

from __future__ import annotations

import html as _html
import re

from treereg_core.text import shown

#: ASCII punctuation: each may be backslash-escaped in CommonMark, and then is only itself.
_PUNCTUATION = re.compile(r"([!-/:-@\[-`{-~])")


#: Where GitHub-flavoured markdown would find a link in plain text: "www.", a scheme's ":" (https:,
#: mailto:) and an e-mail's "@". Its autolinking runs on the parsed text, after backslash escapes
#: are resolved, so there an empty <wbr> splits the text instead (nothing is added to what a person
#: copies).
_AUTOLINK = re.compile(r"(?i)(www)(?=\\\.)|(\\[:@])")


def md(text: object) -> str:
    """`text` as markdown that shows exactly its characters (controls as escapes) and makes no
    element but an empty <wbr>: `md("<img src=x onerror=alert(1)>")` renders as that text, not an image."""
    escaped = _PUNCTUATION.sub(r"\\\1", shown(text))
    return _AUTOLINK.sub(lambda m: (m.group(1) or m.group(2)) + "<wbr>", escaped)


def html(text: object) -> str:
    """`text` as HTML text (plotly titles and hover text): `<`, `>`, `&` as entities; quotes and `%` as
    numeric ones. plotly decodes numeric entities but only a few named ones (no `&quot;`, which it
    showed as such), and reads `%{y}` in a hover template as a value: `&#37;` keeps it text."""
    return _html.escape(shown(text), quote=False).replace('"', "&#34;").replace("'", "&#39;").replace("%", "&#37;")


def md_sentence(text: object) -> str:
    """A message from the core as one escaped sentence: its first letter capitalised, a full stop."""
    s = str(text)
    return md(s[:1].upper() + s[1:]) + "."
