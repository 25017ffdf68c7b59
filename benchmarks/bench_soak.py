"""Soak of the app at the size issue 10 asks for: 5 browser tabs stepping and running for 60 s while
one of them uploads a scan, runs and removes it, 20 times; the server's memory must stay within 20%.

The default `pytest` runs the same test (tests/test_soak.py) shorter (see its module docstring): at
full size it takes longer than the whole test suite may. This script runs it at full size in headless
Chromium and prints a markdown table (times in seconds: a soak has no baseline to be a ratio of).

    python benchmarks/bench_soak.py                     # 60 s, 20 cycles
    python benchmarks/bench_soak.py --seconds 20 --cycles 5 --out /tmp/soak.md
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import Report  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def main() -> int:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=60.0, help="how long the tabs step and run (default 60)")
    ap.add_argument("--cycles", type=int, default=20, help="upload/run/remove cycles (default 20)")
    ap.add_argument("--out", type=Path, help="also write the report to this file")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        result = Path(tmp) / "soak.json"
        env = dict(os.environ, TREEREG_SOAK_TABS="5", TREEREG_SOAK_SECONDS=str(args.seconds), TREEREG_SOAK_CYCLES=str(args.cycles),
                   TREEREG_SOAK_RESULT=str(result))
        t0 = time.perf_counter()
        run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-s", "-p", "no:cacheprovider", "tests/test_soak.py"],
                             cwd=REPO, env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if not result.exists():
            print(run.stdout[-5000:] + run.stderr[-2000:], file=sys.stderr)
            return 1
        r = json.loads(result.read_text())
    cycles = sorted(r["cycle_s"])
    load = os.getloadavg()
    rep = Report()
    rep.say(f"### Soak: {r['tabs']} tabs for {args.seconds:g} s, {r['cycles']} upload/run/remove cycles "
            f"(`python benchmarks/bench_soak.py`)")
    rep.say()
    rep.say("| measure | value |")
    rep.say("|---|---|")
    rep.say(f"| tabs stepping and pressing Run | {r['tabs'] - 1} (+1 doing the cycles) |")
    rep.say(f"| step/Run presses sent | {r['actions']} over {r['stepping_s']:.0f} s |")
    rep.say(f"| upload/run/remove cycles | {r['cycles']} (median {cycles[len(cycles) // 2]:.1f} s, max {cycles[-1]:.1f} s) |")
    rep.say(f"| server RSS after the warm-up (every stage drawn, one cycle) | {r['rss_baseline_mb']:.0f} MB |")
    rep.say(f"| server RSS, peak during the soak | {r['rss_peak_mb']:.0f} MB |")
    rep.say(f"| server RSS at the end | {r['rss_final_mb']:.0f} MB ({100 * (r['rss_final_mb'] / r['rss_baseline_mb'] - 1):+.1f}%) |")
    rep.say(f"| test time / wall time with Python start | {r['test_s']:.0f} s / {wall:.0f} s |")
    rep.say(f"| machine load (1, 5, 15 min) at the end | {load[0]:.1f}, {load[1]:.1f}, {load[2]:.1f} on {os.cpu_count()} cores |")
    rep.say()
    rep.say("PASS" if run.returncode == 0 else f"FAIL (pytest exit {run.returncode})")
    rep.save(args.out)
    return run.returncode


if __name__ == "__main__":
    sys.exit(main())
