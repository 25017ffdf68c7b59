"""A whole-plot survey registered: every station on every stem it shares with its neighbours.

1. Each station reduced to its stems traced up, its ground and a thinned cloud (`stations`).
2. Stem maps matched between every two stations (`prepare.target.stem_map_hypotheses`): how many
   stems they share says who neighbours whom. Pairs: a spanning tree of the most shared stems plus
   each station's `survey.neighbours` best partners (loops to check), never the reference alone.
3. Each pair registered on all the stems and the ground both see (`pair_fit`), with its verdict:
   verified when enough stems spread over the plot agree to `survey.max_residual_m`, unverified
   when too few do or a row-shifted stem map fits as well (a planting), failed when nothing matched.
4. Every station placed from the verified pairs together (`verify.graph.place_scans`, the sparse
   pose graph; a loop that does not close within `survey.max_loop_m` drops its worst pair).

The transforms are of the levelled stations; `Survey.transforms()` gives them as the files give
the scans (`prepare.level.as_given`), as transforms.json wants them.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, replace
from typing import Any, Callable, Sequence, TypeVar

import numpy as np
from scipy.sparse.csgraph import minimum_spanning_tree

from ..params import Params
from ..parallel import one_blas_thread
from ..prepare.level import as_given
from ..prepare.target import stem_map_hypotheses
from ..results import Progress
from ..scan import Scan, ScanHeader
from ..verify.evidence import FAILED, UNVERIFIED, VERIFIED
from ..verify.graph import Edge, Placement, place_scans
from .pair_fit import PairFit, register_pair
from .stations import SurveyStation, survey_station

T = TypeVar("T")
R = TypeVar("R")

#: A pair's stems must spread at least this far (m, the smaller principal spread) to hold its turn.
_MIN_SPREAD_M = 0.5
#: Stem-map hypotheses drawn to screen every two stations, and to match a chosen pair (4x4 survey: the
#: same stems matched from 150 as from 20 000, 0.008 against 0.31 s a pair; 6x6: the same from 1500 as from 4000).
_SCREEN_HYPOTHESES = 150
_PAIR_HYPOTHESES = 1000
#: The joint placement measures an edge on a station's thinned points within this of its scanner.
_SAMPLE_RANGE_M = 20.0


@dataclass(frozen=True, kw_only=True)
class SurveyPair:
    """A registered pair of stations (`i` the reference side, `j` the target side) and its verdict."""

    i: int
    j: int
    shared_stems: int
    fit: PairFit
    verdict: str
    reasons: tuple[str, ...]


@dataclass(frozen=True, kw_only=True, eq=False)
class Survey:
    """A registered survey: its stations, the pairs registered, each station's placement.

    scans : each station's scan without its points (its name, file, steps and pose), in order.
    """

    scans: tuple[ScanHeader, ...]
    stations: tuple[SurveyStation, ...]
    shared: np.ndarray  # n x n: stems the stem maps of two stations share
    pairs: tuple[SurveyPair, ...]
    placements: tuple[Placement, ...]
    seconds: dict[str, float]

    def pair_names(self, p: SurveyPair) -> tuple[str, str]:
        """A pair's (target, reference) station names, as every table and label names the pair."""
        return self.scans[p.j].name, self.scans[p.i].name

    def placed_edges(self) -> dict[tuple[int, int], Edge]:
        """Every pair as the joint placement left it (its loop residual, whether it was used), by (i, j)."""
        return {(e.i, e.j): e for e in (self.placements[0].edges if self.placements else ())}

    def transforms(self) -> dict[str, np.ndarray]:
        """Each placed station's transform onto the first, as their files give the scans."""
        L0 = self.stations[0].T_level
        return {s.name: as_given(pl.T_ref_scan, L0, st.T_level)
                for s, st, pl in zip(self.scans, self.stations, self.placements) if pl.T_ref_scan is not None}

    def verdicts(self) -> dict[str, tuple[str, tuple[str, ...], str]]:
        return {s.name: (pl.verdict, pl.reasons, pl.hint) for s, pl in zip(self.scans, self.placements)}

    def pair_metrics(self) -> dict[str, list[dict[str, object]]]:
        """Every pair's numbers, as transforms.json's "metrics" and `register --details` list them."""
        out: dict[str, list[dict[str, object]]] = {}
        for p in self.pairs:
            f = p.fit
            rows = [("verdict", "", p.verdict), ("shared stems (stem maps)", "", p.shared_stems),
                    ("stems used", "", f.stems_used), ("stem residual", "m", f.residual_m),
                    ("ground residual", "m", f.ground_residual_m), ("ground points", "", f.ground_points),
                    ("crowns agree", "", f.agreement), ("shifted stem map: crowns agree", "", f.runner_up_agreement),
                    ("stems' spread", "m", f.spread_m), ("pose uncertainty 20 m out", "m", f.pose_sd_m)]
            out[" -> ".join(self.pair_names(p))] = [
                {"stage": "survey", "metric": m, "unit": u, "value": v} for m, u, v in rows]
        return out


def register_survey(scans: Sequence[Scan | Callable[[], Scan]], params: Params, *, workers: int = 1,
                    progress: Progress | None = None, client: Any = None) -> Survey:
    """Register a survey's stations onto the first (see the module doc).

    `scans` are the stations, each a Scan or a function that reads it: a station read that way is
    reduced to its summary and its points let go before the next is read, so a survey's memory holds
    `workers` stations' points at a time, not every station's.

    `client`: a Dask client (`batch.runner.dask_client`); the stations are then read and reduced,
    and the pairs registered, on its workers (which must reach the files), each station's summary
    sent to the cluster once. The same transforms as in one process.
    """
    say = progress or (lambda f, t: None)
    sv = params.survey
    seconds: dict[str, float] = {}
    with one_blas_thread(), ThreadPoolExecutor(max(1, workers)) as pool:
        t0 = time.perf_counter()
        say(0.0, "stations: ground and stems")
        reduced = (_each(pool, lambda s: _reduced(s, params), scans, say, 0.0, 0.4,
                         lambda k, _, r: f"{k} of {len(scans)} stations reduced ({r[1].name})") if client is None else
                   client.gather(client.map(_reduced, list(scans), params=params, pure=False)))
        headers = tuple(h for h, _ in reduced)
        stations = tuple(st for _, st in reduced)
        del reduced
        seconds["stations"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        say(0.4, "stem maps")
        n = len(stations)
        usable = [not st.reason for st in stations]
        candidates = [(i, j) for i in range(n) for j in range(i + 1, n) if usable[i] and usable[j]]
        # Every two stations screened on a small draw of hypotheses (who neighbours whom), then the
        # pairs chosen matched again on a larger one, with the next distinct stem map (a planting's rows).
        screened = pool.map(lambda ij: stem_map_hypotheses(stations[ij[0]].stems, stations[ij[1]].stems,
                                                           target=params.target, max_hypotheses=_SCREEN_HYPOTHESES),
                            candidates)
        shared = np.zeros((n, n), dtype=int)
        for (i, j), h in zip(candidates, screened):
            shared[i, j] = shared[j, i] = len(h[0][1]) if h else 0
        chosen = survey_pairs(shared, sv.neighbours, sv.min_stems)
        hyps = dict(zip(chosen, pool.map(
            lambda ij: stem_map_hypotheses(stations[ij[0]].stems, stations[ij[1]].stems, target=params.target, n=2,
                                           max_hypotheses=_PAIR_HYPOTHESES), chosen)))
        seconds["stem maps"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        say(0.5, f"{len(chosen)} pairs on their shared stems")
        if client is None:
            fits = _each(pool, lambda ij: register_pair(stations[ij[0]], stations[ij[1]], hyps[ij], sv), chosen, say,
                         0.5, 0.9, lambda k, ij, _: f"{k} of {len(chosen)} pairs fitted "
                                                    f"({stations[ij[1]].name} -> {stations[ij[0]].name})")
        else:  # each station's summary sent once, not once a pair
            on = client.scatter(list(stations))
            fits = client.gather([client.submit(register_pair, on[i], on[j], hyps[(i, j)], sv, pure=False)
                                  for i, j in chosen])
        seconds["pairs"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    say(0.9, "placing every station")
    pairs = tuple(_judged(i, j, int(shared[i, j]), f, params) for (i, j), f in zip(chosen, fits))
    placements = _place(stations, pairs, shared, params)
    seconds["placement"] = time.perf_counter() - t0
    say(1.0, "done")
    return Survey(scans=headers, stations=stations, shared=shared, pairs=pairs, placements=placements,
                  seconds=seconds)


def _each(pool: ThreadPoolExecutor, fn: Callable[[T], R], items: Sequence[T], say: Progress, start: float, end: float,
          text: Callable[[int, T, R], str]) -> list[R]:
    """`fn` over `items` on the pool, in their order, the progress told (on the calling thread) as each
    finishes, from `start` to `end` of the whole: `text(finished so far, item, its result)`."""
    futures = {pool.submit(fn, it): k for k, it in enumerate(items)}
    for done, f in enumerate(as_completed(futures), 1):
        say(start + (end - start) * done / max(len(items), 1), text(done, items[futures[f]], f.result()))
    return [f.result() for f in futures]


def _reduced(item: Scan | Callable[[], Scan], params: Params) -> tuple[ScanHeader, SurveyStation]:
    """A station read (when given as a reader) and reduced; its points are not kept."""
    scan = item if isinstance(item, Scan) else item()
    return scan.header(), survey_station(scan, params)


def survey_pairs(shared: np.ndarray, neighbours: int, min_stems: int) -> list[tuple[int, int]]:
    """Pairs (i < j) to register: a spanning tree of the most shared stems, then each station's
    `neighbours` partners sharing most (each at least `min_stems`)."""
    n = len(shared)
    s = np.where(shared >= min_stems, shared, 0).astype(float)
    w = np.where(s > 0, s.max() + 1.0 - s, 0.0)  # a maximum spanning tree of the shared stems
    tree = minimum_spanning_tree(np.triu(w)).toarray()
    chosen = {(min(i, j), max(i, j)) for i, j in zip(*np.nonzero(tree))}
    for i in range(n):
        for j in [j for j in np.argsort(-s[i], kind="stable") if j != i and s[i, j] > 0][:neighbours]:
            chosen.add((min(i, int(j)), max(i, int(j))))
    return sorted(chosen)


def _judged(i: int, j: int, shared: int, f: PairFit, params: Params) -> SurveyPair:
    """A pair's verdict from its fit's evidence, each reason naming its threshold."""
    sv = params.survey
    if not f.ok or f.T_ref_target is None:
        return SurveyPair(i=i, j=j, shared_stems=shared, fit=f, verdict=FAILED, reasons=(f.message or "not registered",))
    why = []
    if f.stems_used < sv.min_stems:
        why.append(f"{f.stems_used} of {len(f.stems)} shared stems agree, fewer than survey.min_stems = {sv.min_stems}")
    if not f.residual_m <= sv.max_residual_m:
        why.append(f"the stems' residual is {f.residual_m * 1000:.1f} mm (survey.max_residual_m = {sv.max_residual_m * 1000:g} mm)")
    if not f.pose_sd_m <= sv.max_pose_sd_m:
        why.append(f"its pose is uncertain by {f.pose_sd_m * 1000:.1f} mm 20 m from the scanner (survey.max_pose_sd_m = "
                   f"{sv.max_pose_sd_m * 1000:g} mm): too few or too thin stems in common")
    if not f.spread_m >= _MIN_SPREAD_M:
        why.append(f"the stems used stand nearly in a line ({f.spread_m:.2f} m across it): the turn about them is open")
    if np.isfinite(f.runner_up_agreement) and f.runner_up_agreement >= sv.ambiguity * f.agreement:
        why.append(f"its stem map fits as well shifted by {f.runner_up_shift_m:.1f} m (crowns agree {f.agreement:.0%} "
                   f"against {f.runner_up_agreement:.0%}; survey.ambiguity = {sv.ambiguity:g}): a regular planting")
    return SurveyPair(i=i, j=j, shared_stems=shared, fit=f, verdict=UNVERIFIED if why else VERIFIED, reasons=tuple(why))


def _place(stations: Sequence[SurveyStation], pairs: Sequence[SurveyPair], shared: np.ndarray,
           params: Params) -> tuple[Placement, ...]:
    """Every station placed from the verified pairs (the sparse pose graph); a station with no pair
    says why (no stem shared with any other: another plot, or too few stems)."""
    edges = [Edge(i=p.i, j=p.j, T=p.fit.T_ref_target if p.fit.T_ref_target is not None else np.eye(4),
                  verdict=p.verdict, reasons=p.reasons, weight=_weight(p.fit)) for p in pairs]
    rng = np.random.default_rng(0)
    samples = {}
    for k, st in enumerate(stations):
        near = st.cloud[np.linalg.norm(st.cloud, axis=1) < _SAMPLE_RANGE_M]
        near = near if len(near) else np.zeros((1, 3))
        samples[k] = near[rng.choice(len(near), min(params.graph.sample_points, len(near)), replace=False)]
    placed = place_scans(len(stations), edges, samples, graph=params.graph, max_loop_m=params.survey.max_loop_m)
    out = []
    for k, pl in enumerate(placed):
        if pl.verdict == FAILED and not any(k in (p.i, p.j) for p in pairs):
            st = stations[k]
            why = st.reason or (f"its stems match no other station's stem map (at most {int(shared[k].max())} "
                                f"shared, survey.min_stems = {params.survey.min_stems}): a station of another plot?")
            pl = replace(pl, reasons=(why,), message=why,
                         hint="check that it belongs to this survey; a station needs stems in common with a neighbour")
        out.append(pl)
    if not any(0 in (p.i, p.j) and p.verdict == VERIFIED for p in pairs) and len(stations) > 1:
        # Every placement is onto the first station: without a verified pair of its own, none is
        # placed, and the reason to give is the reference's, not each station's pairs'.
        own = next((r for p in pairs if 0 in (p.i, p.j) for r in p.reasons),
                   stations[0].reason or "its stems match no other station's stem map")
        first = f"the reference {stations[0].name} has no verified pair ({own})"
        hint = "give a station of this survey first (the reference), one that shares stems with its neighbours"
        out = [out[0]] + [replace(pl, reasons=(first,) + pl.reasons, message="; ".join((first,) + pl.reasons), hint=hint)
                          if pl.verdict != VERIFIED else pl for pl in out[1:]]
    return tuple(out)


def _weight(f: PairFit) -> float:
    """An edge's information: the inverse square of its pose's uncertainty (0.05 mm at best: no pair
    is believed beyond the simulator's arithmetic)."""
    sd = f.pose_sd_m if np.isfinite(f.pose_sd_m) else 1.0
    return float(1.0 / max(sd, 5e-5) ** 2)

