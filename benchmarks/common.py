"""What the benchmark scripts share: their options, the report they print and save, the simulated
and real-tree cases, the path `treereg register` takes (`run_case`), and the markdown tables.

Every registration here goes through `treereg_core.pipeline.Pipeline`, the one orchestrator the
command line and the app use; only the experiments on one stage alone (the fine stage from a
perturbed truth, ablations) call that stage's function directly.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from treereg_core.geometry.rigid import mean_displacement, rotation_error_deg  # noqa: E402
from treereg_core.io.atomic import write_text_atomic  # noqa: E402
from treereg_core.params import Params  # noqa: E402
from treereg_core.pipeline import Pipeline  # noqa: E402
from treereg_core.simulate.cases import CaseSpec, SimulatedCase, simulate_case  # noqa: E402

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


def features_of(spec: CaseSpec) -> str:
    """What makes a simulated case awkward, in words ("leaves, ground, tilt 0.3"; "plain")."""
    f = [name for name in ("leaves", "bent", "ground") if getattr(spec, name)]
    if spec.tilt_deg:
        f.append(f"tilt {spec.tilt_deg:g}")
    if spec.lean_deg:
        f.append(f"lean {spec.lean_deg:g}")
    return ", ".join(f) or "plain"


@dataclass
class Err:
    """A transform's error against the truth, and what it cost."""

    rot_deg: float
    disp_m: float
    seconds: float = 0.0
    note: str = ""
    ok: bool = True

    def within(self, max_rot_deg: float, max_disp_m: float) -> bool:
        return self.ok and self.rot_deg < max_rot_deg and self.disp_m < max_disp_m


def error_of(T: np.ndarray, case: SimulatedCase, k: int, seconds: float = 0.0, note: str = "", ok: bool = True) -> Err:
    """Rotation error and mean displacement of scan k's points (as simulated) under `T` against the truth."""
    T_true = case.T_ref_scan[k]
    return Err(rotation_error_deg(T, T_true), mean_displacement(T, T_true, case.scans[k].points), seconds, note, ok)


@dataclass
class CaseRun:
    """One case through the pipeline: the pipeline (its outputs) and the wall time of each stage."""

    pipeline: Pipeline
    seconds: dict[str, float] = field(default_factory=dict)

    def item(self, stage: str, k: int) -> Any:
        """Stage `stage`'s item for scan k (k >= 1: the pair k -> 1)."""
        return self.pipeline.output(stage).items[k - 1]

    def total(self, stages: Sequence[str]) -> float:
        return float(sum(self.seconds.get(s, 0.0) for s in stages))


def run_case(case: SimulatedCase, params: Params, until: str, truth: bool = True,
             pipe: Pipeline | None = None) -> CaseRun:
    """The case through `treereg register`'s path up to `until` (a new pipeline, or `pipe` again after
    its parameters changed: then only the stages the change touched run)."""
    if pipe is None:
        pipe = Pipeline(list(case.scans), params, case.truth() if truth else None)
    else:
        pipe.set_params(params)
    before = pipe.outputs
    t0 = time.perf_counter()
    pipe.run(until)
    wall = time.perf_counter() - t0
    seconds = {s: o.seconds for s, o in pipe.outputs.items() if before.get(s) is not o}
    seconds["wall"] = wall
    return CaseRun(pipe, seconds)


def md_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A markdown table (cells as given: format numbers before)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def summary_row(label: str, errs: Sequence[Err], max_rot_deg: float, max_disp_m: float, baseline_s: float,
                worse: int | None = None) -> list[str]:
    """One method's line of a summary: successes, median/p90/max displacement, rotation, time."""
    d = np.array([e.disp_m for e in errs])
    a = np.array([e.rot_deg for e in errs])
    ok = sum(e.within(max_rot_deg, max_disp_m) for e in errs)
    t = [e.seconds for e in errs if e.seconds]
    return [label, str(len(errs)), f"{ok} ({ok / max(len(errs), 1):.0%})", f"{np.median(d):.4f}",
            f"{np.quantile(d, 0.9):.4f}", f"{d.max():.4f}", f"{np.median(a):.3f}", f"{a.max():.3f}",
            "-" if worse is None else str(worse), f"{np.median(t) / baseline_s:.2f}" if t else "-"]


SUMMARY_HEADER = ("method", "pairs", "success", "median disp (m)", "p90 disp (m)", "max disp (m)", "median rot (deg)",
                  "max rot (deg)", "worse than start", "median time (x)")
