"""What the benchmark scripts share: their common options, the report they print and save, and the
stations simulated from the real trees in ../shared/data/real_trees/."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Iterator

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from treereg_core.io.atomic import write_text_atomic  # noqa: E402
from treereg_core.simulate.cases import SimulatedCase, simulate_case  # noqa: E402

REAL_TREES = Path(__file__).resolve().parents[2] / "shared" / "data" / "real_trees"


def parser(doc: str | None, real_seeds: int) -> argparse.ArgumentParser:
    """The options every benchmark takes; a script adds its own."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=24, help="simulated cases (default 24)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--small", action="store_true", help="the small CI cases instead")
    ap.add_argument("--real-seeds", type=int, default=real_seeds, help="station sets per real tree (0 = skip)")
    ap.add_argument("--real-step", type=float, default=0.05, help="angular step for real-tree stations, deg")
    ap.add_argument("--no-timing", action="store_true")
    ap.add_argument("--out", type=Path, help="also write the report to this file")
    return ap


class Report:
    """Markdown printed as it is made, and saved whole (atomically) at the end."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def say(self, text: str = "") -> None:
        print(text, flush=True)
        self.lines.append(text)

    def save(self, path: Path | None) -> None:
        if path is not None:
            write_text_atomic(path, "\n".join(self.lines) + "\n")


def real_tree_cases(seeds: int, step_deg: float) -> Iterator[tuple[str, SimulatedCase]]:
    """(label, case) for `seeds` station sets of every real tree, at `step_deg`."""
    for path in sorted(REAL_TREES.glob("*.xyz")):
        for s in range(seeds):
            yield f"{path.stem} s{s}", simulate_case(seed=s, from_points=str(path), angular_step_deg=(step_deg, step_deg))
        print(f"  real tree {path.stem} done", file=sys.stderr, flush=True)
