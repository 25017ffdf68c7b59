"""Text from outside (file names, scan names inside files, manifest cells, messages quoting them)
made safe to show: the one place control characters are turned into visible escapes.

A scan name comes from a colleague's file, a shared drive or a public data set. Shown as it is, a
newline in it forges a line of output ("scan3.ply: verified"), an escape sequence drives the
terminal (sets its title, clears the screen) and a right-to-left override reverses what a reader
sees. `shown` keeps every printable character and writes the others as Python would escape them
(`\\n`, `\\x1b`, `\\u202e`), so the text stays readable, one line, and tells what was there.

The app's markdown and HTML escaping (`treereg_viewer.text`) starts from `shown`.
"""

from __future__ import annotations

import re

#: Characters that are not text to show: C0 and C1 controls, DEL, the bidirectional overrides,
#: embeddings and isolates, line and paragraph separators, the byte-order mark, and lone
#: surrogates (the undecodable bytes of a non-UTF-8 file name).
_HIDDEN = re.compile("[\x00-\x1f\x7f-\x9f\u2028\u2029\u202a-\u202e\u2066-\u2069\u200e\u200f\u061c\ufeff"
                     "\ud800-\udfff]")

_NAMED = {"\n": "\\n", "\r": "\\r", "\t": "\\t"}


def _escape(m: re.Match[str]) -> str:
    c = m.group()
    if c in _NAMED:
        return _NAMED[c]
    code = ord(c)
    return f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}"


def shown(text: object) -> str:
    """`text` as one line of printable characters: controls, bidirectional overrides and
    undecodable bytes written as escapes (`"a\\nb"` -> `"a\\\\nb"`); everything else kept."""
    return _HIDDEN.sub(_escape, str(text))
