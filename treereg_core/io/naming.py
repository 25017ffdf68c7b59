"""Scan names (the keys of transforms.json, the CLI's lines, the merged cloud, the app) and the file
names made from them.

A scan is named by its file's base name (`scan1.ply`) or, in a multi-scan E57/PTX file, by its name
there. Scans whose names would clash - one folder per station, each holding `scan1.ply`, as many
scanners export - are named by the shortest folder suffix that tells each apart (`a/scan1.ply`,
`b/scan1.ply`; deeper when needed: `site1/a/scan1.ply`, `site2/a/scan1.ply`); a scan of a
multi-scan file by its file too (`north.e57#Station 1`, as its `Scan.source` reads). Names that do
not clash are kept as they are.

A name may hold "/": a file named after a scan takes `file_stem(name)`, never the name itself. A
name is given as `text.shown` shows it (a newline in a file name as `\\n`), as `Scan.name` keeps it.
"""

from __future__ import annotations

import os
import re
from pathlib import Path, PurePath
from typing import Sequence

from ..errors import ConfigError
from ..text import shown
from .scans import READ_EXTENSIONS

#: Characters a file name cannot hold on some system (separators, Windows' reserved, controls).
_UNSAFE = re.compile(r'[\x00-\x1f/\\:*?"<>|]')
#: The last suffix of every format we read (".gz" of ".xyz.gz" too): what `file_stem` drops.
_FORMAT_SUFFIXES = frozenset("." + ext.rsplit(".", 1)[-1] for ext in READ_EXTENSIONS)


def scan_names(scans: Sequence[tuple[str | Path, str]]) -> list[str]:
    """One distinct name per scan, in order.

    `scans` holds, per scan, its file and its name as the file gives it (`ScanRecord.name`: the
    file's base name for a single-scan file, else its name in the file). A name shared with
    another scan gets the shortest folder suffix that differs from each of those others' (see the
    module docstring). The same scan given twice is a `ConfigError` naming the file.
    """
    where = [_Where(f, name) for f, name in scans]
    seen: dict[tuple, _Where] = {}
    for w in where:
        if w.identity in seen:
            other = seen[w.identity]
            same = ": the same file" if other.parts != w.parts else ""  # through a link, not a/ and ./a/
            also = f" (also as {other.given}{same})" if other.given != w.given else ""
            scan = f" [{w.inner}]" if w.inner is not None else ""
            raise ConfigError(f"{w.given}{scan}: given twice{also}; give each scan once")
        seen[w.identity] = w
    names = []
    for i, w in enumerate(where):
        rivals = [o for j, o in enumerate(where) if j != i and o.name(1) == w.name(1)]
        depth = 1
        while depth < w.depth_max and any(o.name(depth) == w.name(depth) for o in rivals):
            depth += 1
        names.append(w.name(depth))
    if len(set(names)) != len(names):  # only a name inside a file that reads like a folder path gets here
        raise ConfigError(f"scans must have distinct names, got {names}")
    return names


class _Where:
    """Where a scan is: its file's absolute path (folders as given, links not followed: the name is
    the user's) and, for a scan named inside its file, that name. Its identity is the file itself
    (links followed): a link to a scan is that scan given twice."""

    def __init__(self, file: str | Path, name: str) -> None:
        self.given = str(file)
        self.parts = PurePath(os.path.abspath(file)).parts
        self.inner = None if shown(name) == shown(Path(file).name) else name  # a Scan's name is already shown
        try:
            st = os.stat(file)
            self.identity: tuple = ((st.st_dev, st.st_ino), self.inner)  # hard links too
        except OSError:  # not there (yet): the path with links resolved
            self.identity = (os.path.realpath(file), self.inner)
        self.depth_max = len(self.parts) + (self.inner is not None)  # the whole path: deeper adds nothing

    def name(self, depth: int) -> str:
        """The name from the last `depth` components (file and folders; the name inside the file is
        one), as it is shown: clashes are judged on what a reader sees."""
        if self.inner is None:
            return shown(PurePath(*self.parts[-depth:]).as_posix())
        if depth == 1:
            return shown(self.inner)
        return shown(f"{PurePath(*self.parts[-(depth - 1):]).as_posix()}#{self.inner}")


def file_safe(name: str) -> str:
    """`name` as one file name: "/" and every character some system refuses replaced by "_"
    (`a/scan1.ply` -> `a_scan1.ply`)."""
    return _UNSAFE.sub("_", name) or "_"


def file_stem(name: str) -> str:
    """A scan name as the stem of a file named after it: `file_safe`, the format's extension dropped
    (`scan2.ply` -> `scan2`, `a/scan1.ply` -> `a_scan1`); a name inside an E57 keeps its dots."""
    safe = file_safe(name)
    suffix = Path(safe).suffix
    return safe[:-len(suffix)] if suffix and suffix.lower() in _FORMAT_SUFFIXES and len(suffix) < len(safe) else safe
