"""Screenshots of every stage of the app, as a person sees it, at the window sizes people use.

Serves the bundled demo (or a seeded awkward simulated tree) in this process, opens it in headless
Chromium (Debian's /usr/bin/chromium, SwiftShader), waits until every stage is done, then for each
window size steps to every stage and saves a screenshot `<size>_<k>_<stage>.png` into --out. Look at
them before calling a view done: can a class read it, does each number say what it is compared with?

    python benchmarks/app_screens.py --out assets/screens [--sizes 1280x720 1700x1000] [--case demo]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import viser  # noqa: E402
from playwright.sync_api import sync_playwright  # noqa: E402

from treereg_core.demo import demo_case  # noqa: E402
from treereg_viewer.app import TreeregApp  # noqa: E402
from treereg_viewer.controller import Controller  # noqa: E402
from treereg_viewer.labels import label  # noqa: E402
from treereg_viewer.stages import STAGE_NAMES  # noqa: E402

ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync",
        "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
DONE = ("() => [...document.querySelectorAll('p, div')].some(e => /✓ 13 Result/.test(e.textContent) && "
        "!/[○…]/.test(e.textContent) && /1 Scans/.test(e.textContent)) && "
        "!/Running/.test(document.body.innerText)")


def case(name: str):
    if name == "demo":
        d = demo_case()
        return list(d.scans), d.truth
    from treereg_core.simulate.cases import benchmark_cases

    c = benchmark_cases(24, 0)[0].build()  # leaves and ground
    return list(c.scans), c.truth


def settle(page, quiet_ms: int = 400, timeout_s: float = 20.0) -> None:
    """Rendering is on demand: wait until no new frame was drawn for `quiet_ms`."""
    frame = "() => window.__viserTestpoints?.rendererInfo?.render?.frame ?? 0"
    deadline = time.monotonic() + timeout_s
    last = page.evaluate(frame)
    while time.monotonic() < deadline:
        page.wait_for_timeout(quiet_ms)
        now = page.evaluate(frame)
        if now == last:
            return
        last = now


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--sizes", nargs="*", default=["1280x720", "1700x1000"])
    ap.add_argument("--case", choices=("demo", "awkward"), default="demo")
    ap.add_argument("--stages", nargs="*", default=list(STAGE_NAMES))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    scans, truth = case(args.case)
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = TreeregApp(server, Controller(scans, truth=truth), tabs="each")
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path="/usr/bin/chromium", headless=True, args=ARGS)
            for size in args.sizes:
                w, h = (int(v) for v in size.split("x"))
                page = browser.new_page(viewport={"width": w, "height": h})
                page.set_default_timeout(300_000)
                page.goto(f"http://127.0.0.1:{server.get_port()}/")
                page.wait_for_function(DONE, timeout=600_000)
                toast = page.get_by_text("Software WebGL rendering detected")
                if toast.count():
                    toast.locator("xpath=ancestor::div[contains(@class,'Notification-root')][1]").get_by_role(
                        "button").click()
                for k, name in enumerate(STAGE_NAMES):
                    if name not in args.stages:
                        continue
                    page.get_by_label("Stage", exact=True).click()
                    page.get_by_role("option", name=label(name), exact=True).click()
                    page.get_by_role("heading", name=label(name)).first.wait_for()
                    page.mouse.move(w // 2, h - 5)
                    settle(page)
                    path = args.out / f"{size}_{k + 1:02d}_{name}.png"
                    page.screenshot(path=str(path))
                    print(path, flush=True)
                page.close()
            browser.close()
    finally:
        app.close()
        server.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
