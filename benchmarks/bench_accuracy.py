"""Per-pair accuracy of `register` (coarse + fine, the robust default) on the seeded simulated set and
on stations simulated from the real trees, for one or more parameter variants side by side.

What it is for: a change that should keep results "the same or better" (a working resolution, a
faster fine stage) is checked pair by pair, not only by a median. `--save` writes every pair's
errors as JSON; `--compare OLD.json` adds the old errors as a column and counts the pairs that got
worse by more than 0.5 mm or 0.01 deg.

    python benchmarks/bench_accuracy.py --save /tmp/acc_new.json --compare /tmp/acc_old.json
    python benchmarks/bench_accuracy.py --variant resolution.spacing_m=None --variant resolution.spacing_m=0.01
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import Report, parser, real_tree_cases  # noqa: E402

from treereg_core.geometry.rigid import mean_displacement, rotation_error_deg  # noqa: E402
from treereg_core.params import Params  # noqa: E402
from treereg_core.pipeline import register  # noqa: E402
from treereg_core.simulate.cases import benchmark_cases  # noqa: E402

WORSE_M, WORSE_DEG = 5e-4, 0.01


def variant_params(spec: str) -> Params:
    """'section.name=value,section.name=value' over the robust default ('default' = none)."""
    p = Params()
    if spec == "default":
        return p
    for item in spec.split(","):
        key, value = item.split("=", 1)
        section, name = key.split(".", 1)
        p = p.with_value(section, name, None if value == "None" else value)
    return p


def cases(n: int, seed: int, small: bool, real_seeds: int, real_step: float):
    for k, spec in enumerate(benchmark_cases(n, seed, small)):
        yield f"sim {k:02d}{' awkward' if spec.awkward else ''}", spec.build()
    if real_seeds:
        yield from real_tree_cases(real_seeds, real_step)


def main() -> None:
    ap = parser(__doc__, 2)
    ap.add_argument("--variant", action="append", default=[], help="parameters of a variant (repeatable)")
    ap.add_argument("--save", type=Path, help="write every pair's errors (first variant) as JSON")
    ap.add_argument("--compare", type=Path, help="a JSON written by --save, shown beside the first variant")
    args = ap.parse_args()
    variants = args.variant or ["default"]
    old = json.loads(args.compare.read_text()) if args.compare else None
    rep = Report()
    rows: dict[str, dict[str, list[float]]] = {}
    head = ["case", "pair", "points"] + (["old: disp (mm)", "rot (deg)"] if old else [])
    for v in variants:
        head += [f"{v}: disp (mm)", "rot (deg)", "s"]
    rep.say("| " + " | ".join(head) + " |")
    rep.say("|" + "---|" * len(head))
    for label, case in cases(args.n, args.seed, args.small, args.real_seeds, args.real_step):
        results = []
        for v in variants:
            t0 = time.perf_counter()
            reg = register(case.scans, variant_params(v))
            results.append((reg, time.perf_counter() - t0))
        for k in range(1, len(case.scans)):
            name = case.scans[k].name
            key = f"{label} {k + 1}->1"
            cells = [label, f"{k + 1}->1", str(case.scans[k].n_points)]
            if old:
                o = old.get(key)
                cells += [f"{1000 * o[0]:.2f}", f"{o[1]:.3f}"] if o else ["-", "-"]
            for j, (reg, secs) in enumerate(results):
                T = reg.transforms.get(name)
                if T is None:
                    d, r = float("inf"), float("inf")
                else:
                    d = mean_displacement(T, case.T_ref_scan[k], case.scans[k].points)
                    r = rotation_error_deg(T, case.T_ref_scan[k])
                rows.setdefault(variants[j], {})[key] = [d, r, secs / (len(case.scans) - 1)]
                mark = ""
                ref = old.get(key) if old and j == 0 else (rows[variants[0]][key] if j else None)
                if ref is not None and (d > ref[0] + WORSE_M or r > ref[1] + WORSE_DEG):
                    mark = " ↑"
                cells += [f"{1000 * d:.2f}{mark}", f"{r:.3f}", f"{secs:.1f}"]
            rep.say("| " + " | ".join(cells) + " |")
    rep.say("\n| variant | pairs | median disp (mm) | p90 disp (mm) | max disp (mm) | max rot (deg) | worse (> 0.5 mm or 0.01 deg) | median s per pair |")
    rep.say("|---|---|---|---|---|---|---|---|")
    base = old if old else None
    summary = ([("old", old)] if old else []) + list(rows.items())
    for name, res in summary:
        d = np.array([v[0] for v in res.values()])
        r = np.array([v[1] for v in res.values()])
        cmp = base if name != "old" and base else (rows[variants[0]] if name != variants[0] and name != "old" else None)
        worse = "-" if cmp is None else str(sum(1 for k, v in res.items() if k in cmp and
                                                 (v[0] > cmp[k][0] + WORSE_M or v[1] > cmp[k][1] + WORSE_DEG)))
        secs = np.median([v[2] for v in res.values()]) if len(next(iter(res.values()))) > 2 else float("nan")
        rep.say(f"| {name} | {len(d)} | {1000 * np.median(d):.2f} | {1000 * np.quantile(d, 0.9):.2f} | {1000 * d.max():.2f} | "
                f"{r.max():.3f} | {worse} | {secs:.2f} |")
    if args.save:
        args.save.write_text(json.dumps(rows[variants[0]], indent=1))
    rep.save(args.out)


if __name__ == "__main__":
    main()
