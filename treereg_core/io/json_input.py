"""Reading the JSON files a user hands treereg (parameter files, transform and truth files).

Whatever the file is (missing, a folder, unreadable, binary, far too large, nested deeper than
Python's parser recurses), the problem becomes one `ConfigError` naming the file.
"""

from __future__ import annotations

import json
import stat
from pathlib import Path
from typing import Any

from ..errors import ConfigError

#: A parameter or transform file is a few kB; anything much larger is the wrong file.
MAX_JSON_BYTES = 64 * 1024 * 1024


def parse_json(data: bytes | str, source: str) -> Any:
    """The JSON value in `data` (bytes are UTF-8); `source` names it in errors."""
    if len(data) > MAX_JSON_BYTES:
        raise ConfigError(f"{source}: is {len(data) / 1e6:,.0f} MB, far too large for a treereg JSON file")
    try:
        text = data.decode("utf-8-sig") if isinstance(data, bytes) else data
        return json.loads(text)
    except UnicodeDecodeError:
        raise ConfigError(f"{source}: not a text file (not UTF-8), so not a JSON file") from None
    except json.JSONDecodeError as e:
        raise ConfigError(f"{source}: not valid JSON ({e})") from None
    except RecursionError:
        raise ConfigError(f"{source}: nested too deeply to be a treereg JSON file") from None


def read_user_bytes(path: str | Path, kind: str, max_bytes: int = MAX_JSON_BYTES) -> bytes:
    """The bytes of a small file a user hands in (`kind` says what it should be, for the message):
    missing, a folder, a FIFO or device, unreadable or over `max_bytes` is one `ConfigError` naming it."""
    path = Path(path)
    try:
        st = path.stat()
        if stat.S_ISDIR(st.st_mode):
            raise ConfigError(f"{path}: is a folder, not a {kind}")
        if not stat.S_ISREG(st.st_mode):  # a FIFO or a device would block or never end
            raise ConfigError(f"{path}: is not a regular file, so not a {kind}")
        size = st.st_size
        if size > max_bytes:
            raise ConfigError(f"{path}: is {size / 1e6:,.0f} MB, far too large for a {kind}")
        return path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such {kind}") from None
    except OSError as e:
        raise ConfigError(f"{path}: cannot be read ({(e.strerror or type(e).__name__).lower()})") from None


def load_json(path: str | Path, kind: str) -> Any:
    """Read the JSON file `path`; `kind` says what it should be ("parameter file", "transform file")."""
    return parse_json(read_user_bytes(path, kind), str(Path(path)))
