"""The `treereg` command line: one module per subcommand, each with `add(subparsers)` and `run(args)`.

Errors a user can fix (bad scan files, bad parameters, an output that cannot be written) print one
line and exit with status 2; Ctrl-C prints one line and exits with status 130, SIGTERM likewise with
status 143 (128 + 15, what a shell reports for a command ended by SIGTERM), leaving every file as it
was (all writes are atomic). Warnings about input (rows dropped) are printed as sentences; any other
warning that still reaches here is one "treereg: warning:" line without a source path, or dropped
when it only concerns a library's developers.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import importlib
import os
import signal
import sys
import threading
import warnings
from typing import Any, Callable, Iterator

from treereg_core._version import __version__
from treereg_core.errors import ConfigError, OutputError, ScanError, ScanWarning
from treereg_core.text import shown

from . import progress

#: The subcommands (modules of this package), in the order `treereg --help` lists them.
COMMANDS = ("simulate", "register", "batch", "evaluate", "params", "view")


def command_in(argv: list[str]) -> str | None:
    """The subcommand `argv` names (its first word not an option), when it is one of `COMMANDS`."""
    word = next((a for a in argv if not a.startswith("-")), None)
    return word if word in COMMANDS else None


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The command line's parser. Given `argv` that names a subcommand, only that subcommand's
    module is imported (`treereg register` loads no app, batch or simulator code); otherwise every
    one, for `--help` and for a mistyped command's error."""
    parser = argparse.ArgumentParser(
        prog="treereg",
        description="Marker-free registration of multi-station TLS scans of a single tree.",
    )
    parser.add_argument("--version", action="version", version=f"treereg {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    only = command_in(argv) if argv is not None else None
    for name in COMMANDS:
        if only is None or name == only:
            importlib.import_module(f"{__package__}.{name}").add(sub)
    return parser


def say(text: str) -> None:
    """One line on stderr, starting on a fresh line (a progress bar may be half drawn); a file or scan
    name in `text` cannot break the line or reach the terminal as a control (`text.shown`)."""
    progress.end_line()
    print(f"treereg: {shown(text)}", file=sys.stderr, flush=True)


#: Warnings for a library's developers (an API to change), not about the user's input: not shown.
DEVELOPER_WARNINGS = (DeprecationWarning, PendingDeprecationWarning, FutureWarning, ImportWarning, ResourceWarning)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread as Ctrl-C is: every clean-up that Ctrl-C runs (temporary
    files, batch workers, the app's upload folder) runs for it too. `str()` is the signal's name."""

    def __str__(self) -> str:
        return "SIGTERM"


def _raise_terminated(signum: int, frame: object) -> None:
    raise Terminated()


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """While inside, SIGTERM raises `Terminated` in the main thread (elsewhere no signal arrives:
    nothing is installed); the previous handler is put back on the way out."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def warning_line(message: Warning | str, category: type[Warning]) -> str | None:
    """The one line a warning becomes (None: not shown): its message only, never the file and line of
    code it came from, which a user cannot act on."""
    if issubclass(category, DEVELOPER_WARNINGS):  # (a ScanWarning is a UserWarning: always shown)
        return None
    text = " ".join(str(message).split())  # one line, whatever the library put in it
    return f"warning: {text}" if text else None


def _warning_printer() -> Callable[..., None]:
    """`warnings.showwarning` for one command: each distinct message once (a numpy warning inside a
    loop would otherwise repeat per call site)."""
    shown: set[str] = set()
    lock = threading.Lock()  # the app's threads warn too

    def show(message: Any, category: type[Warning], filename: str, lineno: int, file: Any = None,
             line: str | None = None) -> None:
        text = warning_line(message, category)
        with lock:
            if text is None or text in shown:
                return
            shown.add(text)
        say(text)

    return show


def _names_printable() -> None:
    """A file name that is not UTF-8 (its bytes kept as lone surrogates) prints escaped, not as a
    UnicodeEncodeError after the whole run (stdout is strict outside the C locale). Names are shown
    through `text.shown`, which writes a lone surrogate as this does (`\\udcff`); this is the net
    for any text that still reaches a stream unshown."""
    for stream in (sys.stdout, sys.stderr):
        if getattr(stream, "errors", None) == "strict" and hasattr(stream, "reconfigure"):
            stream.reconfigure(errors="backslashreplace")


#: The errors of a write to a stream that cannot take more (a full disk or device, a quota, an I/O
#: failure): one line and exit 2 rather than a traceback.
OUTPUT_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO})


def _quiet_stdout() -> None:
    """Send the rest of stdout (and what its buffer holds) to /dev/null: nothing left to fail at exit."""
    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def main(argv: list[str] | None = None) -> int:
    _names_printable()
    if threading.active_count() == 1:  # the process's own start, not a caller's (tests call main too)
        from treereg_core.parallel import fewer_malloc_arenas
        fewer_malloc_arenas()
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    with warnings.catch_warnings(), sigterm_as_interrupt():
        warnings.simplefilter("always", ScanWarning)  # one per file, not one per line of code
        warnings.showwarning = _warning_printer()
        try:
            code = int(args.func(args) or 0)
            sys.stdout.flush()  # here, where a full disk can still be said, not at exit
            return code
        except (ScanError, ConfigError, OutputError) as e:
            say(f"error: {e}")
            return 2
        except Terminated:
            say("terminated (SIGTERM); no file was left half-written or replaced by a partial result")
            return 143
        except KeyboardInterrupt:
            say("interrupted (Ctrl-C); no file was left half-written or replaced by a partial result")
            return 130
        except BrokenPipeError:  # `treereg params | head`: the reader has all it wanted
            _quiet_stdout()  # nothing left to flush at exit
            return 141  # as a shell reports a command ended by SIGPIPE
        except OSError as e:
            # Files are written through io.atomic (an OutputError); what is left is a stream:
            # `treereg ... > /dev/full`, or a disk that filled under the redirected output.
            if e.errno not in OUTPUT_ERRNOS:
                raise
            _quiet_stdout()
            with contextlib.suppress(OSError):  # stderr may be the full one
                say(f"error: cannot write the output ({e.strerror or e}); what was printed is incomplete")
            return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
