"""Shared test helpers. `SHARED` is the `shared/` folder beside the project checkout (CI puts it there);
tests that read it skip, saying why, when it is absent."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
REAL_TREES = SHARED / "data" / "real_trees"


def needs(path: Path) -> pytest.MarkDecorator:
    """Skip the test (with the missing path as the reason) when `path` is not there."""
    return pytest.mark.skipif(not path.exists(), reason=f"{path} is not available (the shared data folder beside the checkout)")

#: Debian's Chromium, driven by Playwright (never `playwright install`: no downloads here).
CHROMIUM = Path("/usr/bin/chromium")
#: Headless, offline, WebGL on SwiftShader (see /work/shared/VISER_NOTES.md).
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
]


def rss_mb(pid: int) -> float:
    """Resident memory of a process, MB (from /proc)."""
    return int(re.search(r"VmRSS:\s+(\d+)", Path(f"/proc/{pid}/status").read_text()).group(1)) / 1024


@pytest.fixture(scope="module")
def browser():
    """Headless Debian Chromium driven by Playwright, one per test module; skips without either."""
    pw = pytest.importorskip("playwright.sync_api")
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} is not installed")
    with pw.sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS)
        yield b
        b.close()


def read(markdown: str) -> str:
    """What a person reads of a markdown element: rendered as viser renders it (CommonMark with raw
    HTML and tables), tags dropped, entities decoded (a scan name escaped for markdown reads as given)."""
    import html

    from markdown_it import MarkdownIt

    out = MarkdownIt("commonmark", {"html": True}).enable(["table", "strikethrough"]).render(markdown)
    return html.unescape(re.sub(r"<[^>]*>", "", out))


@pytest.hookimpl(tryfirst=True)  # before xdist's own, which names each test's group from these marks
def pytest_collection_modifyitems(config, items):
    """Browser and soak tests are slow too: `pytest -m "not slow"` leaves them out (the inner loop).

    Under pytest-xdist with `--dist loadgroup` (README's command: two workers, one per core) a test
    module stays on one worker (its module fixtures — a registration, an app, a Chromium — are made
    once). The browser tests form three groups: held in one group they were the suite's
    long pole (8 of its 10 minutes); a group per module, each of a few tests, xdist started last
    (13.6 minutes). Tests that bound a time (`timed`) run in a pass of their own before, on a
    machine doing nothing else."""
    for item in items:
        if item.get_closest_marker("browser") or item.get_closest_marker("soak"):
            item.add_marker(pytest.mark.slow)
    if not (getattr(config.option, "loadgroup", False) or getattr(config.option, "dist", "no") == "loadgroup"):
        return  # (xdist's workers are told by `loadgroup`, the controller by `dist`)

    def chromium(item) -> bool:
        return item.get_closest_marker("browser") is not None or "browser" in getattr(item, "fixturenames", ())

    # The browser tests in three groups, a module's in one, balanced by their count: each group then
    # counts enough tests that xdist (largest groups first) starts them early instead of leaving
    # their minute-long tests for the end, and the third goes to whichever worker is free first
    # (two groups: 697 s, the one holding the pairs walk and the soak a minute longer).
    count: dict[str, int] = {}
    for item in items:
        if chromium(item):
            count[item.nodeid.split("::")[0]] = count.get(item.nodeid.split("::")[0], 0) + 1
    load, side = [0, 0, 0], {}
    for module in sorted(count, key=lambda m: (-count[m], m)):
        k = load.index(min(load))
        side[module], load[k] = k, load[k] + count[module]
    for item in items:
        module = item.nodeid.split("::")[0]
        item.add_marker(pytest.mark.xdist_group(f"browser-{side[module]}" if chromium(item) else module))
