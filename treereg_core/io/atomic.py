"""Every file treereg writes goes through here: its destination is checked first, then it is written
atomically (a temporary file beside the target, renamed over it only when complete).

- A crash, an error or Ctrl-C mid-write never leaves a half-written file under the target's name,
  and the temporary file is removed.
- Only regular files are ever replaced. A symbolic link is written *through*: its target gets the
  new content and the link stays. A folder, FIFO, device or socket is refused, never replaced.
- `check_output_file` / `check_output_dir` say what is wrong with a destination (a folder given as
  a file, a parent that is a file, a folder that cannot be written) *before* any computation, so
  a long run never ends in an error about where its result should go. Problems are
  `errors.OutputError`: one line naming the path.
- `batch()` groups several writes (a case folder, a set of exports): every file is written to its
  temporary first, and only when all succeeded are they renamed, with Ctrl-C held off for those
  few microseconds. An interrupted or failed batch leaves every previous file as it was.
- `remove_atomic` removes a file of ours that a new result makes stale, with the batch: only when
  every write of the batch succeeded, right after its renames.
- `check_distinct` refuses, before anything is read, an output that is one of the inputs (the same
  file, also through a symbolic or hard link) or two outputs that are one file.
- Temporaries are named `.<target>.treereg<pid>.<random>.tmp`. A process killed mid-write (SIGKILL,
  a power cut) cannot remove its own; the next write into that folder removes them when the
  process named by the pid no longer runs and the file is a minute old (`remove_stale_temporaries`).
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import stat
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable, Iterable, Iterator, Sequence

from ..errors import OutputError

_local = threading.local()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _kind(mode: int) -> str:
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def _reason(e: OSError) -> str:
    return (e.strerror or str(e) or type(e).__name__).lower()


# ---- checks ------------------------------------------------------------------------------------
def _check_can_create_in(folder: Path, label: str) -> None:
    """`folder` exists or can be made, and files can be created in it."""
    existing = folder
    while not os.path.lexists(existing):
        existing = existing.parent
    if existing.is_symlink() and not existing.exists():
        raise OutputError(label, f"cannot create the folder {folder}: {existing} is a broken symbolic link")
    if not existing.is_dir():
        raise OutputError(label, f"cannot create the folder {folder}: {existing} is a file, not a folder")
    # The only truthful test (permissions, read-only file systems, root on /sys...): make a file.
    try:
        fd, probe = _mkstemp(existing, "treereg-check")
    except OSError as e:
        what = "a file" if existing == folder else f"the folder {folder}"
        raise OutputError(label, f"cannot create {what} in {existing} ({_reason(e)})") from None
    os.close(fd)
    os.unlink(probe)


def check_output_file(path: str | Path, label: str | None = None, example: str | None = None) -> Path:
    """The file that writing `path` will create or replace (a symbolic link's target), checked.

    Raises `OutputError` when `path` is a folder, a FIFO, a device or a socket, a read-only file, a
    link that loops, or when its folder cannot be created or written. Call it before any
    computation; `write_atomic` checks again when it writes. `example` is a file name to suggest
    when `path` is a folder.
    """
    p = Path(path)
    label = label or str(p)
    target = Path(os.path.realpath(p))
    if os.path.lexists(target):
        try:
            mode = os.stat(target).st_mode
        except OSError as e:  # a loop of links
            raise OutputError(label, f"cannot be followed to a file ({_reason(e)})") from None
        if stat.S_ISDIR(mode):
            raise OutputError(label, f"is a folder; give a file name (e.g. {p / example})" if example
                              else "is a folder; give the name of a file (in it, or beside it)")
        if not stat.S_ISREG(mode):
            raise OutputError(label, f"is {_kind(mode)}; treereg only replaces regular files")
        # No write bit for anyone says "keep this" even to root, for whom access() is always yes.
        if not os.access(target, os.W_OK) or not mode & 0o222:
            raise OutputError(label, "is read-only; treereg does not replace it")
    _check_can_create_in(target.parent, label)
    return target


def check_output_dir(path: str | Path, label: str | None = None) -> Path:
    """The folder `path` (followed through links), checked: it is, or can be made, a folder we can write in."""
    p = Path(path)
    label = label or str(p)
    target = Path(os.path.realpath(p))
    if os.path.lexists(target) and not target.is_dir():
        try:
            mode = os.stat(target).st_mode
        except OSError as e:
            raise OutputError(label, f"cannot be followed to a folder ({_reason(e)})") from None
        raise OutputError(label, "is a file, not a folder" if stat.S_ISREG(mode) else f"is {_kind(mode)}, not a folder")
    _check_can_create_in(target, label)
    return target


def _identity(path: str | Path) -> tuple:
    """What makes two paths one file: an existing file's device and inode (so symbolic and hard links
    to it count), else the path with every link resolved (a file yet to be written)."""
    try:
        st = os.stat(path)
    except OSError:
        return ("path", os.path.realpath(path))
    return ("inode", st.st_dev, st.st_ino)


def is_one_of(path: str | Path, files: Iterable[str | Path]) -> bool:
    """`path` is one of `files` (the same file, also through a symbolic or hard link)."""
    key = _identity(path)
    return any(_identity(f) == key for f in files)


def check_distinct(outputs: Sequence[tuple[str, str | Path]], inputs: Iterable[str | Path] = (),
                   advice: str = "choose another name") -> None:
    """No output is an input and no two outputs are one file; else `OutputError` naming the output.

    `outputs` are (what, path): `what` says which output it is in the message ("--merged", "the
    export"). Call it before anything is read: a long run must not end by replacing a scan.
    """
    sources = [(_identity(p), p) for p in inputs]
    seen: dict[tuple, str] = {}
    for what, path in outputs:
        key = _identity(path)
        for k, src in sources:
            if k == key:
                link = "" if str(src) == str(path) else " (the same file)"
                raise OutputError(str(path), f"{what} is the input {src}{link}; treereg never replaces an "
                                  f"input: {advice}")
        if key in seen:
            raise OutputError(str(path), f"{seen[key]} and {what} are the same file; each output needs its own name")
        seen[key] = what


# ---- temporaries -------------------------------------------------------------------------------
#: Our temporaries' names (see `_mkstemp`): the writing process's pid, then mkstemp's 8 random characters.
_TEMPORARY = re.compile(r"^\..+\.treereg(\d{1,10})\.[a-z0-9_]{8}\.tmp$")
#: A temporary this old (seconds since its last write) whose process is gone is stale.
STALE_AFTER_S = 60.0


def _mkstemp(folder: Path, name: str) -> tuple[int, str]:
    """A new temporary in `folder` for `name`, named so that `remove_stale_temporaries` knows it as ours."""
    return tempfile.mkstemp(prefix=f".{name}.treereg{os.getpid()}.", suffix=".tmp", dir=folder)


def _running(pid: int) -> bool:
    """A process `pid` exists on this machine (another user's too); when unsure, yes."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (OSError, OverflowError):  # not ours to signal (it exists), or no such pid possible: keep
        pass
    return True


def remove_stale_temporaries(folder: str | Path) -> list[Path]:
    """Remove what a killed treereg left in `folder`: files named as our temporaries, regular files of
    this user, untouched for `STALE_AFTER_S`, whose writing process no longer runs (a pid reused
    by another process keeps its file: the safe side). Never anything else. Returns the removed."""
    removed: list[Path] = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for e in entries:
        m = _TEMPORARY.match(e.name)
        if m is None or int(m.group(1)) == os.getpid() or _running(int(m.group(1))):
            continue
        try:
            st = e.stat(follow_symlinks=False)
            if (not stat.S_ISREG(st.st_mode) or st.st_uid != os.geteuid()
                    or time.time() - st.st_mtime < STALE_AFTER_S):
                continue
            os.unlink(e.path)
        except OSError:
            continue
        removed.append(Path(e.path))
    return removed


# ---- writing -----------------------------------------------------------------------------------
class _Batch:
    def __init__(self) -> None:
        self.pending: list[tuple[Path, Path]] = []  # (temporary, target)
        self.removals: list[Path] = []  # stale files of ours, removed with the renames


@contextlib.contextmanager
def batch() -> Iterator[None]:
    """Group the writes made inside (on this thread): all or none of them replace their targets."""
    outer = getattr(_local, "batch", None)
    if outer is not None:  # nested: the outermost batch commits
        yield
        return
    b = _Batch()
    _local.batch = b
    try:
        yield
    except BaseException:
        for tmp, _ in b.pending:
            tmp.unlink(missing_ok=True)
        raise
    finally:
        _local.batch = None
    with _interrupts_held():
        for tmp, target in b.pending:
            os.replace(tmp, target)
        for target in b.removals:
            _unlink(target)


@contextlib.contextmanager
def _interrupts_held() -> Iterator[None]:
    """Ctrl-C or SIGTERM during the final renames waits until they are done, then is delivered to the
    handler that was in force (main thread only; elsewhere no signal arrives)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    held = (signal.SIGINT, signal.SIGTERM)
    previous = {s: signal.signal(s, lambda signum, frame: caught.append(signum)) for s in held}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    for signum in dict.fromkeys(caught):  # once each, in the order they came
        signal.raise_signal(signum)


def write_atomic(path: str | Path, write: Callable[[Path], None]) -> Path:
    """Run `write(tmp)` on a temporary file beside the target of `path`, then rename it over the target.

    The target is `path`, or the file a symbolic link `path` points to. Raises `OutputError` (and
    leaves everything as it was) when it cannot be written; inside `batch()` the rename waits for
    the batch. Returns `path`.
    """
    path = Path(path)
    target = check_output_file(path)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(target.parent)
        fd, tmp_name = _mkstemp(target.parent, target.name)
    except OSError as e:
        raise OutputError(str(path), f"cannot be written ({_reason(e)})") from None
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        write(tmp)
        # mkstemp makes the file private (0600): keep the mode of the file replaced, else what open() gives.
        mode = stat.S_IMODE(os.stat(target).st_mode) if target.exists() else 0o666 & ~_umask()
        os.chmod(tmp, mode)
        b = getattr(_local, "batch", None)
        if b is not None:
            b.pending.append((tmp, target))
        else:
            os.replace(tmp, target)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise OutputError(str(path), f"could not be written ({_reason(e)}); nothing was replaced") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def _unlink(path: Path) -> None:
    try:
        path.unlink(missing_ok=True)
    except OSError as e:
        raise OutputError(str(path), f"could not be removed ({_reason(e)})") from None


def remove_atomic(path: str | Path) -> Path | None:
    """Remove `path`, a file of ours a new result makes stale: inside `batch()` together with the
    batch's renames (a failed or interrupted batch removes nothing), else now. Only a regular file
    is removed, never a symbolic link (a link the user made is theirs), folder or other kind; its
    folder must let us (`check_output_file`). Returns `path` when there was a file to remove."""
    path = Path(path)
    try:
        st = os.lstat(path)
    except OSError:  # nothing there (or nothing we can see): nothing to remove
        return None
    if not stat.S_ISREG(st.st_mode):
        return None
    check_output_file(path)  # read-only or in a folder we cannot write: said now, before any rename
    b = getattr(_local, "batch", None)
    if b is not None:
        b.removals.append(path)
    else:
        _unlink(path)
    return path


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write `text` to `path` atomically."""
    return write_atomic(path, lambda tmp: tmp.write_text(text))


def write_bytes_atomic(path: str | Path, data: bytes) -> Path:
    """Write `data` to `path` atomically."""
    return write_atomic(path, lambda tmp: tmp.write_bytes(data))
