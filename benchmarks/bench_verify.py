"""Verification benchmark: is every scan placed with evidence or refused?

Every case runs `treereg register`'s path (the pipeline, through the verify and placement stages).
A registration is *right* when it is within 0.5 deg and 3 cm of the truth (rotation error, mean
displacement of the scan's points); scans of another tree have no right transform.

Prints markdown tables:
1. the confusion table per family of cases, for scans (their final placement) and for pairs:
   verified-and-right, verified-but-wrong, refused-but-right, refused-and-wrong (refused =
   unverified or failed);
2. the same for other thresholds of the verdict (recomputed from the recorded evidence: the
   hypotheses and poses do not depend on them), to choose the defaults;
3. the evidence of every pair that is refused-but-right or verified-but-wrong, and of the leaf-on pairs;
4. many stations around one tree: every scan's error, joint placement against its pair with scan 1;
5. the time of `treereg register` on 3 and 6 scans of ~300k points against a baseline revision.

Families: the seeded benchmark set (`simulate.benchmark_cases`, a third awkward); two different
trees of look-alike height (within 15%); three stations where the third sees another tree; crowns
alike after a half, third or quarter turn and the same with their symmetry broken
(`simulate.symmetric`); a station's scan mirrored (x -> -x); leaf-on crowns (the simulator's leaves, and stations from rtls_pc_tree.xyz);
six stations around one tree. `--families` runs some of them.

    python benchmarks/bench_verify.py                 # full run
    python benchmarks/bench_verify.py --n 3 --small --real-seeds 1 --no-timing   # quick look
    python benchmarks/bench_verify.py --loosest --no-timing   # the wrong scans, every threshold at its loosest
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from common import REAL_TREES, Report, error_of, md_table, parser  # noqa: E402

from treereg_core.geometry.rigid import invert, mean_displacement, rotation_error_deg  # noqa: E402
from treereg_core.io.scans import write_scan  # noqa: E402
from treereg_core.params import PRESETS, Params, loosest, thresholds  # noqa: E402
from treereg_core.pipeline import Pipeline  # noqa: E402
from treereg_core.scan import Scan  # noqa: E402
from treereg_core.simulate.cases import CaseSpec, SimulatedCase, benchmark_cases, simulate_case  # noqa: E402
from treereg_core.simulate.symmetric import symmetric_case  # noqa: E402
from treereg_core.verify.evidence import VERIFIED, Evidence, judge  # noqa: E402

MAX_ROT_DEG = 0.5
MAX_DISP_M = 0.03
CLOSE_DISP_M = 0.015
REPO = Path(__file__).resolve().parents[1]


@dataclass
class Outcome:
    """One scan's placement or one pair's registration, judged against the truth."""

    family: str
    case: str
    what: str
    verdict: str
    right: bool | None  # None: no right answer exists (another tree)
    rot_deg: float = float("nan")
    disp_m: float = float("nan")
    evidence: Evidence | None = None
    reasons: tuple[str, ...] = ()
    sway_true_m: float = float("nan")  # wind: how far the crown's top had moved between the pair's stations
    condition: str = ""  # wind / mixed pixels: the setting the case was simulated at

    @property
    def verified(self) -> bool:
        return self.verdict == VERIFIED

    @property
    def close(self) -> bool:
        """Within 0.5 deg and 1.5 cm (the wind criteria)."""
        return bool(self.right) and self.rot_deg < MAX_ROT_DEG and self.disp_m < CLOSE_DISP_M


def _rename(scan: Scan, name: str) -> Scan:
    return Scan(scan.points, name, scan.angular_step_deg, None, scan.step_estimated)


def run(family: str, label: str, scans: list[Scan], truth: dict[str, np.ndarray], params: Params,
        case: SimulatedCase | None = None, condition: str = "") -> tuple[list[Outcome], Pipeline]:
    """One case through the pipeline to the placement; its scans and pairs judged against `truth`
    (a scan missing from `truth` has no right transform). With the simulated `case`, each pair
    records how far the crown's top had moved between its stations (wind)."""
    pipe = Pipeline(scans, params, {k: v for k, v in truth.items()})
    pipe.run("graph")
    out: list[Outcome] = []
    graph, ver = pipe.output("graph"), pipe.output("verify")
    ref = scans[0].name
    for i, s in enumerate(scans[1:], start=1):
        pl = graph.items[i] if graph is not None else None
        verdict = pl.verdict if pl is not None else "failed"
        if s.name not in truth:
            out.append(Outcome(family, label, f"scan {s.name}", verdict, None, reasons=pl.reasons if pl else ()))
            continue
        T_true = invert(truth[ref]) @ truth[s.name]
        if pl is None or pl.T_ref_scan is None:
            out.append(Outcome(family, label, f"scan {s.name}", verdict, False, reasons=pl.reasons if pl else ()))
            continue
        rot, disp = rotation_error_deg(pl.T_ref_scan, T_true), mean_displacement(pl.T_ref_scan, T_true, s.points)
        out.append(Outcome(family, label, f"scan {s.name}", verdict, rot < MAX_ROT_DEG and disp < MAX_DISP_M, rot, disp,
                           reasons=pl.reasons))
    for k, p in enumerate(pipe.pairs):
        a, b = scans[p.ref], scans[p.tgt]
        it = ver.items[k] if ver is not None else None
        ev = getattr(it, "evidence", None)
        verdict = getattr(it, "verdict", "failed")
        what = f"pair {b.name}->{a.name}"
        if a.name not in truth or b.name not in truth:
            out.append(Outcome(family, label, what, verdict, None, evidence=ev, reasons=getattr(it, "reasons", ())))
            continue
        T_true = invert(truth[a.name]) @ truth[b.name]
        T = getattr(it, "T_ref_target", None)
        if T is None:
            out.append(Outcome(family, label, what, verdict, False, evidence=ev))
            continue
        rot, disp = rotation_error_deg(T, T_true), mean_displacement(T, T_true, b.points)
        sway = float(np.linalg.norm(case.relative_sway_m(p.tgt, p.ref))) if case is not None else float("nan")
        out.append(Outcome(family, label, what, verdict, rot < MAX_ROT_DEG and disp < MAX_DISP_M, rot, disp, ev,
                           getattr(it, "reasons", ()), sway, condition))
    for o in out:
        o.condition = condition
    return out, pipe


def confusion(rows: list[Outcome]) -> list[str]:
    """verified-and-right, verified-but-wrong, refused-but-right, refused-and-wrong (+ share of right verified)."""
    vr = sum(r.verified and r.right is True for r in rows)
    vw = sum(r.verified and r.right is not True for r in rows)
    rr = sum(not r.verified and r.right is True for r in rows)
    rw = sum(not r.verified and r.right is not True for r in rows)
    share = f"{vr / (vr + rr):.0%}" if vr + rr else "-"
    return [str(len(rows)), str(vr), f"**{vw}**" if vw else "0", str(rr), str(rw), share]


CONFUSION_HEADER = ("family", "what", "count", "verified and right", "verified but wrong", "refused but right",
                    "refused and wrong", "right ones verified")


def confusion_table(rows: list[Outcome]) -> str:
    families = list(dict.fromkeys(r.family for r in rows))
    out = []
    for f in families + ["**all**"]:
        for kind in ("scan", "pair"):
            sel = [r for r in rows if (f == "**all**" or r.family == f) and r.what.startswith(kind)]
            if sel:
                out.append([f, kind + "s", *confusion(sel)])
    return md_table(CONFUSION_HEADER, out)


#: Other thresholds tried on the recorded evidence of the pairs: (label, changes to VerifyParams).
SWEEP: tuple[tuple[str, dict], ...] = (
    ("defaults", {}),
    ("min_consistency 0.90", {"min_consistency": 0.90}),
    ("min_consistency 0.98", {"min_consistency": 0.98}),
    ("min_margin 0.0", {"min_margin": 0.0}),
    ("min_margin 0.08", {"min_margin": 0.08}),
    ("chance_factor 1.0", {"chance_factor": 1.0}),
    ("chance_factor 4.0", {"chance_factor": 4.0}),
    ("max_residual_factor 1.5", {"max_residual_factor": 1.5}),
    ("consistency alone (no margin, support, residual)", {"min_margin": 0.0, "chance_factor": 1.0, "max_residual_factor": 100.0}),
)


def sweep_table(rows: list[Outcome], params: Params) -> str:
    pairs = [r for r in rows if r.what.startswith("pair") and r.evidence is not None]
    out = []
    for label, change in SWEEP:
        vp = replace(params.verify, **change)
        judged = [replace(r, verdict=judge(r.evidence, verify=vp, coarse=params.coarse, acceptance=params.acceptance)[0])
                  for r in pairs]
        out.append([label, *confusion(judged)])
    return md_table(("thresholds (pairs)", "count", "verified and right", "verified but wrong", "refused but right",
                     "refused and wrong", "right ones verified"), out)


def evidence_table(rows: list[Outcome]) -> str:
    out = []
    for r in rows:
        e = r.evidence
        if e is None:
            out.append([r.family, r.case, r.what, r.verdict, "-" if r.right is None else ("yes" if r.right else "no"),
                        f"{r.rot_deg:.2f} / {r.disp_m * 1000:.1f}" if np.isfinite(r.rot_deg) else "", "", "", "", "", "",
                        "; ".join(r.reasons)[:120]])
            continue
        out.append([r.family, r.case, r.what, r.verdict, "-" if r.right is None else ("yes" if r.right else "no"),
                    f"{r.rot_deg:.2f} / {r.disp_m * 1000:.1f}" if np.isfinite(r.rot_deg) else "",
                    f"{e.inliers} / {e.chance_inliers}", f"{e.consistency:.3f} ({e.seen_by_both})",
                    f"{e.margin:.3f} ({e.rival})", f"{e.residual_m * 1000:.1f} / {e.noise_m * 1000:.1f}",
                    e.chosen, "; ".join(r.reasons)[:120]])
    return md_table(("family", "case", "what", "verdict", "right", "rot (deg) / disp (mm)", "inliers / chance",
                     "consistency (seen)", "margin (rival)", "residual / noise (mm)", "hypothesis", "why not verified"), out)


def different_trees(n: int, seed: int, wind_m: float = 0.0) -> list[tuple[str, list[Scan], dict]]:
    """Pairs of scans of two different trees of look-alike height (within 15%)."""
    rng = np.random.default_rng(seed + 77)
    out = []
    for k in range(n):
        h = float(rng.uniform(8.0, 13.0))
        step = round(0.04 * h / 11.0, 4)
        a = CaseSpec(seed=seed * 1000 + 500 + k, height_m=h, angular_step_deg=(step, step), wind_m=wind_m).build()
        b = CaseSpec(seed=seed * 1000 + 600 + k, height_m=round(h * float(rng.uniform(0.87, 1.13)), 2),
                     angular_step_deg=(step, step), wind_m=wind_m).build()
        scans = [a.scans[0], _rename(b.scans[1], "other_tree.ply")]
        out.append((f"d{k:02d}", scans, {a.scans[0].name: np.eye(4)}))
    return out


def intruders(n: int, seed: int, wind_m: float = 0.0) -> list[tuple[str, list[Scan], dict]]:
    """Three stations where the third sees another tree entirely."""
    out = []
    for k in range(n):
        a = CaseSpec(seed=seed * 1000 + 700 + k, height_m=10.0, angular_step_deg=(0.04, 0.04), wind_m=wind_m).build()
        b = CaseSpec(seed=seed * 1000 + 800 + k, height_m=10.5, angular_step_deg=(0.04, 0.04), wind_m=wind_m).build()
        scans = [a.scans[0], a.scans[1], _rename(b.scans[2], "intruder.ply")]
        out.append((f"i{k:02d}", scans, {a.scans[0].name: a.T_ref_scan[0], a.scans[1].name: a.T_ref_scan[1]}))
    return out


def mirrored(n: int, seed: int) -> list[tuple[str, list[Scan], dict]]:
    """A station's scan mirrored (x -> -x in its scanner frame): the reference and a mirrored
    target, and (every other case) a third, right station beside them. A mirror image has no right
    rigid transform."""
    out = []
    for k in range(n):
        a = CaseSpec(seed=seed * 1000 + 1100 + k, height_m=10.0 + k % 3, angular_step_deg=(0.04, 0.04)).build()
        pts = np.array(a.scans[1].points)
        pts[:, 0] *= -1.0
        mirror = Scan.from_points(pts, "mirrored.ply", angular_step_deg=a.scans[1].angular_step_deg)
        scans = [a.scans[0], mirror] if k % 2 == 0 else [a.scans[0], a.scans[2], mirror]
        truth = {a.scans[0].name: a.T_ref_scan[0]} | ({} if k % 2 == 0 else {a.scans[2].name: a.T_ref_scan[2]})
        out.append((f"r{k:02d}", scans, truth))
    return out


def leaf_on(n: int, seed: int, real_step: float) -> list[tuple[str, list[Scan], dict]]:
    out = []
    for k in range(n):
        case = CaseSpec(seed=seed * 1000 + 900 + k, leaves=True, height_m=11.0, angular_step_deg=(0.05, 0.05)).build()
        out.append((f"leaves s{k}", list(case.scans), case.truth()))
    path = REAL_TREES / "rtls_pc_tree.xyz"
    if path.exists():
        for k in range(n):
            case = simulate_case(seed=k, from_points=str(path), angular_step_deg=(real_step, real_step))
            out.append((f"rtls_pc_tree s{k}", list(case.scans), case.truth()))
    return out


def multi_station(n: int, seed: int, stations: int = 6) -> list[tuple[str, SimulatedCase]]:
    out = []
    for k in range(n):
        case = CaseSpec(seed=seed * 1000 + 950 + k, n_stations=stations, height_m=11.0,
                        angular_step_deg=(0.04, 0.04), station_distance_m=(8.0, 12.0)).build()
        out.append((f"m{k:02d}", case))
    return out


def multi_table(cases: list[tuple[str, SimulatedCase]], params: Params) -> tuple[str, list[Outcome]]:
    """Per scan: the joint placement's error and its pair with scan 1 alone (fine), against the truth."""
    rows, outcomes, joint_all, pair_all = [], [], [], []
    for label, case in cases:
        res, pipe = run("six stations", label, list(case.scans), case.truth(), params)
        outcomes += res
        graph, fine = pipe.output("graph"), pipe.output("fine")
        for i in range(1, len(case.scans)):
            e_joint = error_of(graph.items[i].T_ref_scan, case, i) if graph.items[i].T_ref_scan is not None else None
            k = next(n for n, p in enumerate(pipe.pairs) if (p.ref, p.tgt) == (0, i))
            f = fine.items[k] if fine is not None else None
            e_pair = error_of(f.T_ref_target, case, i) if f is not None and f.ok else None
            sep = (case.stations[i].azimuth_deg - case.stations[0].azimuth_deg + 180.0) % 360.0 - 180.0
            rows.append([label, case.scans[i].name, f"{abs(sep):.0f}", graph.items[i].verdict,
                         f"{e_joint.rot_deg:.3f} / {e_joint.disp_m * 1000:.2f}" if e_joint else "-",
                         f"{e_pair.rot_deg:.3f} / {e_pair.disp_m * 1000:.2f}" if e_pair else "-",
                         ", ".join(str(v + 1) for v in graph.items[i].via)])
            if e_joint:
                joint_all.append(e_joint.disp_m)
            if e_pair:
                pair_all.append(e_pair.disp_m)
        print(f"  multi-station {label} done", file=sys.stderr, flush=True)
    table = md_table(("case", "scan", "azimuth from scan 1 (deg)", "verdict", "joint: rot (deg) / disp (mm)",
                      "pair with scan 1 alone: rot / disp", "placed through"), rows)
    j, p = np.array(joint_all), np.array(pair_all)
    table += (f"\n\nJoint placement: median {np.median(j) * 1000:.2f} mm, worst {j.max() * 1000:.2f} mm over "
              f"{len(j)} scans; each scan's pair with scan 1 alone: median {np.median(p) * 1000:.2f} mm, worst "
              f"{p.max() * 1000:.2f} mm over {len(p)}.") if len(j) and len(p) else ""
    return table, outcomes


#: The families of cases (`--families`).
FAMILIES = ("benchmark", "different", "intruder", "symmetric", "leaf-on", "six", "wind", "mixed", "wind+mixed",
            "wind negatives", "mirrored")
#: The families of wrong scans: what `--loosest` runs (the symmetric family without its controls).
NEGATIVE_FAMILIES = ("different", "intruder", "symmetric", "mirrored", "wind negatives")
#: Top sways (m) of the wind family, and the mixed-pixel rates (share of the edge returns).
SWAYS_M = (0.0, 0.05, 0.10, 0.20, 0.35)
MIXED_RATES = (0.1, 0.25, 0.4, 0.5)
#: Stations per tree of the wind family, in turn: mostly three, and two to six.
WIND_STATIONS = (3, 3, 3, 2, 3, 3, 4, 6)


def _windy_spec(k: int, seed: int, **options) -> CaseSpec:
    """The k-th tree of the wind and mixed-pixel families: 8-12 m, every third leaf-on, 8-15 m away."""
    rng = np.random.default_rng([seed, 31, k])
    h = round(float(rng.uniform(8.0, 12.0)), 2)
    leaves = k % 3 == 2
    step = round(0.04 * h / 10.0 * (1.2 if leaves else 1.0), 4)
    return CaseSpec(seed=seed * 1000 + 1200 + k, height_m=h, angular_step_deg=(step, step), leaves=leaves, **options)


def windy(n: int, seed: int, sways: tuple[float, ...] = SWAYS_M):
    """The same `n` trees at each top sway (a new direction per station): (sway, label, case)."""
    for w in sways:
        for k in range(n):
            case = _windy_spec(k, seed, wind_m=w, n_stations=WIND_STATIONS[k % len(WIND_STATIONS)]).build()
            yield w, f"w{k:02d}{' leaves' if case.spec.leaves else ''}", case


def mixed(n: int, seed: int, rates: tuple[float, ...] = MIXED_RATES, wind_m: float = 0.0):
    """The same `n` trees with this share of their edge returns mixed pixels: (rate, label, case)."""
    for rate in rates:
        for k in range(n):
            case = _windy_spec(k, seed, mixed_pixels=rate, wind_m=wind_m).build()
            yield rate, f"x{k:02d}{' leaves' if case.spec.leaves else ''}", case


def wind_negatives(n: int, seed: int, sways: tuple[float, ...] = (0.10, 0.20)):
    """Under wind: scans of two different trees; a crown alike after a third turn; a station that
    sees another tree."""
    for w in sways:
        for label, scans, truth in different_trees(n, seed, wind_m=w):
            yield w, "different trees (wind)", label, scans, truth
        for k in range(max(1, n // 4)):
            scans, truth = symmetric_case(3, seed=seed + k, wind_m=w)
            yield w, "symmetric crowns (wind)", f"3-fold s{seed + k}", scans, truth
        for label, scans, truth in intruders(max(1, n // 4), seed, wind_m=w):
            yield w, "third station sees another tree (wind)", label, scans, truth


def condition_table(rows: list[Outcome], what: str) -> str:
    """Pairs per condition (top sway, mixed-pixel rate): right and verified (and within 0.5 deg / 1.5
    cm), verified but wrong, refused but right, refused and wrong; the errors of the verified."""
    out = []
    for cond in dict.fromkeys(r.condition for r in rows):
        sel = [r for r in rows if r.condition == cond and r.what.startswith("pair") and r.right is not None]
        if not sel:
            continue
        vr = [r for r in sel if r.verified and r.right]
        vw = sum(r.verified and not r.right for r in sel)
        rr = sum(not r.verified and r.right for r in sel)
        rw = sum(not r.verified and not r.right for r in sel)
        close = sum(r.verified and r.close for r in sel)
        d = np.array([r.disp_m for r in vr]) * 1000
        a = np.array([r.rot_deg for r in vr])
        out.append([cond, len(sel), len(vr), f"**{vw}**" if vw else "0", rr, rw,
                    f"{close} ({close / len(sel):.0%})",
                    f"{np.median(d):.1f} / {d.max():.1f}" if len(d) else "-",
                    f"{a.max():.2f}" if len(a) else "-"])
    return md_table((what, "pairs", "verified and right", "verified but wrong", "refused but right",
                     "refused and wrong", "verified within 0.5° and 1.5 cm", "verified: median / max disp (mm)",
                     "verified: max rot (deg)"), out)


def refusal_table(rows: list[Outcome]) -> str:
    """Why the right pairs that were refused were refused (first reason, shortened)."""
    out = []
    for r in rows:
        if r.what.startswith("pair") and r.right and not r.verified:
            out.append([r.condition, r.case, r.what, f"{r.sway_true_m:.2f}" if np.isfinite(r.sway_true_m) else "-",
                        f"{r.rot_deg:.2f} / {r.disp_m * 1000:.1f}", "; ".join(r.reasons)[:160]])
    return md_table(("condition", "case", "pair", "crown moved (m, simulated)", "rot (deg) / disp (mm)", "why refused"),
                    out) if out else "None."


def sway_table(rows: list[Outcome]) -> str:
    """The crown's motion the verification reports against the simulated one, on verified right pairs."""
    sel = [r for r in rows if r.what.startswith("pair") and r.verified and r.right and r.evidence is not None
           and np.isfinite(r.sway_true_m) and r.sway_true_m > 0]
    out = []
    for cond in dict.fromkeys(r.condition for r in sel):
        s = [r for r in sel if r.condition == cond]
        true = np.array([r.sway_true_m for r in s])
        rep = np.array([r.evidence.sway_m for r in s])
        err = np.abs(rep - true)
        within = np.sum(err <= np.maximum(0.3 * true, 0.02))
        out.append([cond, len(s), f"{np.median(true):.3f}", f"{np.median(rep):.3f}", f"{np.median(err) * 100:.1f}",
                    f"{err.max() * 100:.1f}", f"{within} / {len(s)}"])
    return md_table(("top sway (m)", "verified right pairs", "simulated motion, median (m)", "reported, median (m)",
                     "|reported - simulated|, median (cm)", "max (cm)", "within 30% or 2 cm"), out)


def symmetric_crowns(n: int, seed: int):
    """Crowns alike after a half, third or quarter turn (`simulate.symmetric`): a registration is
    right only by luck and must not be verified at a wrong heading; and the same crowns with their
    symmetry broken (each branch turned by up to 40 deg), which must register and verify."""
    for fold in (2, 3, 4):
        for k in range(n):
            scans, truth = symmetric_case(fold, seed=seed + k)
            yield "symmetric crowns", f"{fold}-fold s{seed + k}", scans, truth
            scans, truth = symmetric_case(fold, whorl_jitter_deg=40.0, seed=seed + k)
            yield "symmetry broken (control)", f"{fold}-fold jittered s{seed + k}", scans, truth


def _register_seconds(python_path: Path, files: list[Path], out: Path) -> float:
    env = dict(os.environ, PYTHONPATH=str(python_path))
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "treereg_cli", "register", *map(str, files), "--out", str(out)],
                   cwd=python_path, env=env, capture_output=True, check=False)
    return time.perf_counter() - t0


def _checkout(rev: str, where: Path) -> Path:
    """The tree of revision `rev` extracted into `where` (a folder of its own)."""
    where.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(["git", "-C", str(REPO), "archive", rev], capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(where)], input=archive, check=True)
    return where


def _scan_outcomes(doc: dict, case: SimulatedCase) -> list[tuple[str, bool]]:
    """(verdict, right) of every non-reference scan of a transform file written by `treereg register`."""
    out = []
    quality = doc.get("quality", {}).get("scans", {})
    for k, s in enumerate(case.scans[1:], start=1):
        T = doc["transforms"].get(s.name)  # with --keep-unverified, best guesses too
        verdict = quality.get(s.name, {}).get("verdict", "verified" if T is not None else "unverified")
        if T is None and s.name in doc.get("unverified", {}):
            T = doc["unverified"][s.name]["matrix"]
        if T is None:
            out.append(("failed", False))
            continue
        T = np.asarray(T, dtype=float)
        right = rotation_error_deg(T, case.T_ref_scan[k]) < MAX_ROT_DEG and \
            mean_displacement(T, case.T_ref_scan[k], s.points) < MAX_DISP_M
        out.append((verdict, bool(right)))
    return out


def before_after(baseline_rev: str, cases: list[tuple[str, SimulatedCase]]) -> str:
    """`treereg register` of `baseline_rev` and of this checkout on the same case files, per condition:
    the scans verified and right, verified but wrong, refused but right (each command's own verdicts)."""
    rows: dict[str, dict[str, list[tuple[str, bool]]]] = {}
    with tempfile.TemporaryDirectory(prefix="treereg-bench-before-") as tmp:
        base = _checkout(baseline_rev, Path(tmp) / "baseline")
        for n, (cond, case) in enumerate(cases):
            d = Path(tmp) / f"case{n}"
            files = [write_scan(d / s.name, s.points, dtype="float32") for s in case.scans]
            for label, tree in (("before", base), ("after", REPO)):
                out = d / f"{label}.json"
                env = dict(os.environ, PYTHONPATH=str(tree))
                subprocess.run([sys.executable, "-m", "treereg_cli", "register", *map(str, files), "--out", str(out),
                                "--keep-unverified"], cwd=tree, env=env, capture_output=True, check=False)
                got = _scan_outcomes(json.loads(out.read_text()), case) if out.exists() else \
                    [("failed", False)] * (len(case.scans) - 1)
                rows.setdefault(cond, {}).setdefault(label, []).extend(got)
            print(f"  before/after {cond} case {n + 1}/{len(cases)} done", file=sys.stderr, flush=True)

    def counts(v: list[tuple[str, bool]]) -> str:
        vr = sum(x == "verified" and r for x, r in v)
        vw = sum(x == "verified" and not r for x, r in v)
        rr = sum(x != "verified" and r for x, r in v)
        return f"{vr} / {f'**{vw}**' if vw else 0} / {rr}"

    table = [[cond, len(v["after"]), counts(v["before"]), counts(v["after"])] for cond, v in rows.items()]
    return md_table(("condition", "scans", f"before ({baseline_rev}): verified right / verified wrong / refused right",
                     "now: verified right / verified wrong / refused right"), table)


def timing(baseline_rev: str, seed: int, target_points: int = 300_000, repeats: int = 2) -> str:
    """`treereg register` on 3 and 6 scans of ~`target_points` points, and 3 scans in wind (a 20 cm top
    sway): this checkout against `baseline_rev`."""
    with tempfile.TemporaryDirectory(prefix="treereg-bench-verify-") as tmp:
        base = _checkout(baseline_rev, Path(tmp) / "baseline")
        rows = []
        for n, wind in ((3, 0.0), (6, 0.0), (3, 0.2)):
            spec = CaseSpec(seed=seed, n_stations=n, height_m=13.0, angular_step_deg=(0.03, 0.03), wind_m=wind)
            n0 = np.mean([s.n_points for s in spec.build(None).scans])
            step = round(0.03 * float(np.sqrt(n0 / target_points)), 4)
            case = replace(spec, angular_step_deg=(step, step)).build(None)
            files = []
            for s in case.scans:
                files.append(write_scan(Path(tmp) / f"{n}_{wind}_{s.name}", s.points, dtype="float32"))
            t_base = min(_register_seconds(base, files, Path(tmp) / "b.json") for _ in range(repeats))
            t_now = min(_register_seconds(REPO, files, Path(tmp) / "n.json") for _ in range(repeats))
            pts = ", ".join(f"{s.n_points // 1000}k" for s in case.scans)
            what = f"{n} scans ({pts})" + (f", wind {wind * 100:.0f} cm" if wind else "")
            rows.append([what, f"{t_base:.1f}", f"{t_now:.1f}", f"{t_now / t_base:.2f}"])
        return md_table(("case", f"baseline {baseline_rev} (s)", "now (s)", "ratio"), rows)


def negatives(a, fam: set[str]):
    """(family, label, scans, truth, condition) of the negative families in `fam`: every case holds a
    scan with no right transform (the symmetric family without its symmetry-broken controls)."""
    for label, scans, truth in different_trees(a.different, a.seed) if "different" in fam else ():
        yield "different trees", label, scans, truth, ""
    for label, scans, truth in intruders(max(1, a.different // 2), a.seed) if "intruder" in fam else ():
        yield "third station sees another tree", label, scans, truth, ""
    for family, label, scans, truth in symmetric_crowns(a.symmetric, a.seed) if "symmetric" in fam else ():
        if family == "symmetric crowns":
            yield family, label, scans, truth, ""
    for label, scans, truth in mirrored(a.mirrored, a.seed) if "mirrored" in fam else ():
        yield "mirrored scan", label, scans, truth, ""
    for w, family, label, scans, truth in wind_negatives(a.windy, a.seed) if "wind negatives" in fam else ():
        yield family, label, scans, truth, f"{w:.2f}"


#: Verdict thresholds past their allowed range (the issue's loosened config among them), judged on the
#: evidence recorded at the loosest allowed values: what the ranges keep out.
BEYOND: tuple[tuple[str, dict], ...] = (
    ("min_consistency 0.85, min_margin 0.01, chance_factor 1.5 (issue 17)",
     {"min_consistency": 0.85, "min_margin": 0.01, "chance_factor": 1.5}),
    ("min_consistency 0.90", {"min_consistency": 0.90}),
    ("min_margin 0.01", {"min_margin": 0.01}),
    ("min_margin 0.0", {"min_margin": 0.0}),
    ("chance_factor 1.0", {"chance_factor": 1.0}),
    ("max_residual_factor 10", {"max_residual_factor": 10.0}),
    ("min_margin 0.0, chance_factor 1.0", {"min_margin": 0.0, "chance_factor": 1.0}),
)


def beyond_table(rows: list[Outcome], params: Params) -> str:
    """The wrong pairs (no right transform, or not right) verified when one threshold is set past its range."""
    pairs = [r for r in rows if r.what.startswith("pair") and r.evidence is not None and r.right is not True]
    out = [["at the loosest allowed", str(sum(r.verified for r in pairs))]]
    for label, change in BEYOND:
        vp = replace(params.verify, **change)
        n = sum(judge(r.evidence, verify=vp, coarse=params.coarse, acceptance=params.acceptance)[0] == VERIFIED
                for r in pairs)
        out.append([label, f"**{n}**" if n else "0"])
    return md_table((f"thresholds (the other ones at their loosest; {len(pairs)} wrong pairs)", "verified but wrong"), out)


def loosest_run(a) -> int:
    """The negative families with every verification threshold at its loosest allowed value: the
    confusion table (0 verified but wrong is the point) and the evidence of any verified wrong one."""
    report = Report()
    params = loosest(PRESETS["robust"])
    fam = set(a.families) & set(NEGATIVE_FAMILIES)
    rows: list[Outcome] = []
    for family, label, scans, truth, cond in negatives(a, fam):
        rows += run(family, label, scans, truth, params, condition=cond)[0]
        print(f"  {family} {cond} {label} done", file=sys.stderr, flush=True)
    say = report.say
    say("### Thresholds at their loosest")
    say()
    say(md_table(("threshold", "default", "loosest allowed"), [
        [key, f"{f.default:g}", f"{f.metadata['min' if f.metadata['looser'] == 'lower' else 'max']:g}"]
        for key, f in thresholds()]))
    say()
    say("### The negative families under the loosest thresholds")
    say()
    say(confusion_table(rows))
    say()
    say("### One step beyond the ranges: the wrong pairs' recorded evidence judged again")
    say()
    say(beyond_table(rows, params))
    wrong = [r for r in rows if r.verified and r.right is not True]
    say()
    say("Verified but wrong, their evidence:" if wrong else "None verified.")
    if wrong:
        say()
        say(evidence_table([r for r in wrong if r.what.startswith("pair")] or wrong))
    report.save(a.out)
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = parser(__doc__, real_seeds=4)
    ap.add_argument("--baseline", default="HEAD~1", help="revision whose `treereg register` times are the baseline")
    ap.add_argument("--different", type=int, default=8, help="pairs of different trees")
    ap.add_argument("--multi", type=int, default=3, help="cases of six stations")
    ap.add_argument("--symmetric", type=int, default=2, help="cases per symmetry (2-, 3-, 4-fold crowns) and controls")
    ap.add_argument("--families", nargs="*", default=list(FAMILIES), choices=list(FAMILIES), help="which families to run")
    ap.add_argument("--windy", type=int, default=8, help="trees per top sway and per mixed-pixel rate")
    ap.add_argument("--before", metavar="REV", help="also run `treereg register` of REV and of this checkout on the "
                    "first --before-n trees of each wind and mixed-pixel condition (scans, each its own verdicts)")
    ap.add_argument("--before-n", type=int, default=4)
    ap.add_argument("--mirrored", type=int, default=8, help="cases with a mirrored scan")
    ap.add_argument("--loosest", action="store_true", help="only the negative families (" + ", ".join(NEGATIVE_FAMILIES)
                    + "), with every verification threshold at its loosest allowed value: none may be verified")
    a = ap.parse_args(argv)
    if a.loosest:
        return loosest_run(a)
    report = Report()
    say = report.say
    params = PRESETS["robust"]
    rows: list[Outcome] = []
    fam = set(a.families)
    for i, spec in enumerate(benchmark_cases(a.n, a.seed, small=a.small) if "benchmark" in fam else ()):
        case = spec.build(None)
        rows += run("benchmark set", f"c{i:02d}", list(case.scans), case.truth(), params)[0]
        print(f"  case {i + 1}/{a.n} done", file=sys.stderr, flush=True)
    for label, scans, truth in different_trees(a.different, a.seed) if "different" in fam else ():
        rows += run("different trees", label, scans, truth, params)[0]
    for label, scans, truth in intruders(max(1, a.different // 2), a.seed) if "intruder" in fam else ():
        rows += run("third station sees another tree", label, scans, truth, params)[0]
    for family, label, scans, truth in symmetric_crowns(a.symmetric, a.seed) if "symmetric" in fam else ():
        rows += run(family, label, scans, truth, params)[0]
    for label, scans, truth in mirrored(a.mirrored, a.seed) if "mirrored" in fam else ():
        rows += run("mirrored scan", label, scans, truth, params)[0]
    leaf_rows: list[Outcome] = []
    for label, scans, truth in leaf_on(a.real_seeds, a.seed, a.real_step) if "leaf-on" in fam else ():
        leaf_rows += run("leaf-on crowns", label, scans, truth, params)[0]
    rows += leaf_rows
    multi, multi_rows = multi_table(multi_station(a.multi, a.seed), params) if "six" in fam else ("Not run.", [])
    rows += multi_rows
    wind_rows: list[Outcome] = []
    for w, label, case in windy(a.windy, a.seed) if "wind" in fam else ():
        wind_rows += run("wind", label, list(case.scans), case.truth(), params, case, f"{w:.2f}")[0]
        print(f"  wind {w:.2f} {label} done", file=sys.stderr, flush=True)
    mixed_rows: list[Outcome] = []
    for rate, label, case in mixed(a.windy, a.seed) if "mixed" in fam else ():
        mixed_rows += run("mixed pixels", label, list(case.scans), case.truth(), params, case, f"{rate:.0%}")[0]
        print(f"  mixed {rate:.2f} {label} done", file=sys.stderr, flush=True)
    both_rows: list[Outcome] = []
    for w in (0.05, 0.10) if "wind+mixed" in fam else ():
        for rate, label, case in mixed(a.windy, a.seed, rates=(0.4,), wind_m=w):
            both_rows += run("wind and mixed pixels", label, list(case.scans), case.truth(), params, case,
                             f"{w:.2f} m, {rate:.0%}")[0]
            print(f"  wind {w:.2f} + mixed {rate:.2f} {label} done", file=sys.stderr, flush=True)
    neg_rows: list[Outcome] = []
    for w, family, label, scans, truth in wind_negatives(a.windy, a.seed) if "wind negatives" in fam else ():
        neg_rows += run(family, label, scans, truth, params, condition=f"{w:.2f}")[0]
        print(f"  {family} {w:.2f} {label} done", file=sys.stderr, flush=True)
    rows += wind_rows + mixed_rows + both_rows + neg_rows

    say("## Verification: confusion table (`treereg register`'s path to the placement)")
    say()
    say(f"Right = within {MAX_ROT_DEG} deg and {MAX_DISP_M * 100:.0f} cm of the truth; a scan of another tree has no "
        "right transform. Refused = unverified or failed. Scans: their final (joint) placement; pairs: every "
        "registered pair's own fine result.")
    say()
    say(confusion_table(rows))
    say()
    say("## Thresholds: the verdict of the pairs recomputed from their recorded evidence")
    say()
    say(sweep_table(rows, params))
    say()
    say("## Evidence of the pairs refused though right, verified though wrong, and of every leaf-on pair")
    say()
    odd = [r for r in rows if r.what.startswith("pair") and ((r.verified and r.right is not True)
                                                           or (not r.verified and r.right is True))]
    say(evidence_table(odd + [r for r in leaf_rows if r.what.startswith("pair") and r not in odd]) if odd or leaf_rows
        else "None.")
    say()
    say("## Six stations around one tree (evenly spread: scan 4 opposite scan 1)")
    say()
    say(multi)
    if wind_rows or mixed_rows or both_rows:
        say()
        say("## Wind and mixed pixels")
        say()
        say(f"Pairs against the truth (right = within {MAX_ROT_DEG} deg and {MAX_DISP_M * 100:.0f} cm). Wind: before each "
            "station scans, the stem bends as a cantilever with this top sway in a direction of the station's own; "
            "small branches flutter by up to half of it, leaves a little more. Mixed pixels: this share of the edge "
            "returns strung out 2-80 cm behind the edge along their ray.")
        for title, sel, what in (("Wind", wind_rows, "top sway (m)"), ("Mixed pixels", mixed_rows, "mixed-pixel rate"),
                                 ("Wind and mixed pixels together", both_rows, "top sway, mixed-pixel rate")):
            if sel:
                say()
                say(f"### {title}")
                say()
                say(condition_table(sel, what))
        say()
        say("### The crown's motion reported against the simulated (verified right pairs)")
        say()
        say(sway_table(wind_rows + both_rows))
        say()
        say("### Right pairs refused, and why")
        say()
        say(refusal_table(wind_rows + mixed_rows + both_rows))
    if a.before:
        say()
        say(f"## Wind and mixed pixels: `treereg register` before ({a.before}) and now, same files")
        say()
        picked = [(f"top sway {w:.2f} m", c) for w, lab, c in windy(a.before_n, a.seed)]
        picked += [(f"mixed pixels {r:.0%}", c) for r, lab, c in mixed(a.before_n, a.seed)]
        say(before_after(a.before, picked))
    if not a.no_timing:
        say()
        say("## Time of `treereg register` (wall, fresh process, reading the files included)")
        say()
        say(timing(a.baseline, a.seed))
    report.save(a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
