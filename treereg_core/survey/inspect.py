"""A registered survey as the app shows it: the station map in 3-D, a pair inspected, a stem of the
plot seen from every station that sees it. Geometry only (numpy); the app draws what these give.

Everything is in the reference station's levelled frame, where the placements put the stations
(`Placement.T_ref_scan` maps a station's levelled points there):

* `survey_map`: every placed station's voxel-thinned cloud (within `MAP_REACH_M` of its scanner)
  placed and decimated to a total point budget (shared in proportion to the clouds), each station's scanner, each registered pair as a link
  between the two scanners (its verdict, and whether the placement used it), and the plot's stems —
  the stations' stems at breast height placed and grouped across stations (`PlotStem.views`).
* `inspect_pair`: a pair's verdict, the checks it rests on (each number beside its threshold) and
  the sections of its shared stems from both stations, the target's under the pair's own fit.
* `inspect_stem`: a plot stem's sections from every station that sees it, placed, with their
  circles and their heights above the ground.
* `SurveyMap.pick`: the link or stem a click along a ray meant.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.rigid import apply_transform
from ..params import SurveyParams
from .register import _MIN_SPREAD_M, Survey, SurveyPair

#: Stems of two stations whose breast-height centres stand nearer than this once placed are one stem.
SAME_STEM_M = 0.3
#: Points the map draws at most by default (all stations together): fluid in Chromium on a laptop.
DEFAULT_MAP_POINTS = 300_000
#: The map draws each station's points within this of its scanner, across the ground (m): beyond, a
#: station's points are thin rings of ground and far crowns its neighbours see better.
MAP_REACH_M = 15.0
#: The breast height (m above the ground) a stem's section is shown at, and its label.
BREAST_HEIGHT_M = 1.3
#: How a link is drawn: used by the placement, verified but dropped by a loop, unverified, failed.
LINK_STATES = ("used", "dropped", "unverified", "failed")


@dataclass(frozen=True, kw_only=True, eq=False)
class MapLink:
    """Pair `index` of the survey (`survey.pairs[index]`) as a link between its two scanners."""

    index: int
    i: int
    j: int
    verdict: str
    state: str  # one of LINK_STATES
    ends: np.ndarray  # 2 x 3: the two scanners, placed (NaN where a station is not placed)
    loop_residual_m: float

    @property
    def mid(self) -> np.ndarray:
        return np.asarray(self.ends.mean(axis=0), dtype=float)


@dataclass(frozen=True, kw_only=True, eq=False)
class PlotStem:
    """One stem of the plot: where it stands at breast height (placed), its radius, and which station
    sees it as which of its stems: `views` holds (station, stem column index) pairs, one per station."""

    index: int
    xyz: np.ndarray
    radius_m: float
    views: tuple[tuple[int, int], ...]

    @property
    def stations(self) -> tuple[int, ...]:
        return tuple(k for k, _ in self.views)


@dataclass(frozen=True, kw_only=True, eq=False)
class SurveyMap:
    """What the map draws (see the module doc). `points` (float32) are placed; `station_of` says
    whose each is. `input_points` is what the stations' files held, `cloud_points` their thinned clouds
    within reach of their scanners (what the budget is shared from)."""

    names: tuple[str, ...]
    verdicts: tuple[str, ...]
    scanners: np.ndarray  # n x 3, NaN rows for a station not placed
    points: np.ndarray
    station_of: np.ndarray
    input_points: int
    cloud_points: int
    links: tuple[MapLink, ...]
    stems: tuple[PlotStem, ...]

    @property
    def placed(self) -> np.ndarray:
        return np.asarray(np.isfinite(self.scanners).all(axis=1), dtype=bool)

    def pick(self, origin: np.ndarray, direction: np.ndarray, max_angle_deg: float = 1.5) -> tuple[str, int] | None:
        """What a click along the ray meant: ("link", pair index) for a link's mid-point, ("stem", stem
        index) for a stem at breast height, None for neither. The candidate nearest the ray's line
        (as an angle, so near and far ones are alike on screen) wins."""
        o, d = np.asarray(origin, float), np.asarray(direction, float)
        d = d / max(float(np.linalg.norm(d)), 1e-12)
        cands: list[tuple[float, str, int]] = []
        for kind, at, idx in (("link", [ln.mid for ln in self.links], [ln.index for ln in self.links]),
                              ("stem", [s.xyz for s in self.stems], [s.index for s in self.stems])):
            if not at:
                continue
            rel = np.asarray(at, float) - o
            along = rel @ d
            perp = np.linalg.norm(rel - np.outer(along, d), axis=1)
            angle = np.degrees(np.arctan2(perp, np.maximum(along, 1e-9)))
            for a, ok, k in zip(angle, along > 0, idx):
                if ok and np.isfinite(a) and a <= max_angle_deg:
                    cands.append((float(a), kind, int(k)))
        if not cands:
            return None
        _, kind, k = min(cands)
        return kind, k


def link_state(survey: Survey, pair: SurveyPair) -> tuple[str, float]:
    """How a pair is drawn (one of LINK_STATES) and its residual in the joint placement (NaN when not in it)."""
    ed = survey.placed_edges().get((pair.i, pair.j))
    loop = float(ed.loop_error_m) if ed is not None else float("nan")
    if pair.verdict == "verified":
        return ("used" if ed is not None and ed.used else "dropped"), loop
    return pair.verdict, loop


def placements(survey: Survey) -> dict[int, np.ndarray]:
    """Each placed station's T_ref_scan (levelled station -> levelled reference), by station index."""
    return {k: np.asarray(pl.T_ref_scan, float) for k, pl in enumerate(survey.placements) if pl.T_ref_scan is not None}


def survey_map(survey: Survey, max_points: int = DEFAULT_MAP_POINTS, reach_m: float = MAP_REACH_M) -> SurveyMap:
    """The station map of `survey`: each station's cloud within `reach_m` of its scanner (across the
    ground), decimated so that all together hold at most `max_points` (see the module doc)."""
    placed = placements(survey)
    n = len(survey.stations)
    scanners = np.full((n, 3), np.nan)
    for k, T in placed.items():
        scanners[k] = T[:3, 3]
    near = {k: np.flatnonzero(np.hypot(survey.stations[k].cloud[:, 0], survey.stations[k].cloud[:, 1]) <= reach_m)
            for k in placed}
    total = sum(len(v) for v in near.values())
    rng = np.random.default_rng(0)
    pts, who = [], []
    for k, T in placed.items():
        c = survey.stations[k].cloud[near[k]]
        take = len(c) if total <= max_points else int(max_points * len(c) / max(total, 1))
        idx = np.sort(rng.choice(len(c), take, replace=False)) if take < len(c) else np.arange(len(c))
        pts.append(apply_transform(T, c[idx].astype(float)).astype(np.float32))
        who.append(np.full(len(idx), k, dtype=np.int32))
    links = []
    for k, p in enumerate(survey.pairs):
        state, loop = link_state(survey, p)
        links.append(MapLink(index=k, i=int(p.i), j=int(p.j), verdict=p.verdict, state=state,
                             ends=np.vstack([scanners[p.i], scanners[p.j]]), loop_residual_m=loop))
    return SurveyMap(names=tuple(s.name for s in survey.scans),
                     verdicts=tuple("reference" if k == 0 else pl.verdict for k, pl in enumerate(survey.placements)),
                     scanners=scanners, points=np.concatenate(pts) if pts else np.zeros((0, 3), np.float32),
                     station_of=np.concatenate(who) if who else np.zeros(0, np.int32),
                     input_points=int(sum(st.n_points for st in survey.stations)), cloud_points=int(total),
                     links=tuple(links), stems=plot_stems(survey))


@dataclass
class _Group:
    at: list[np.ndarray]
    radii: list[float]
    views: list[tuple[int, int]]

    @property
    def centre(self) -> np.ndarray:
        return np.asarray(np.mean(self.at, axis=0), dtype=float)


def plot_stems(survey: Survey) -> tuple[PlotStem, ...]:
    """Every placed station's stems at breast height in the reference frame, grouped across stations:
    a stem joins the group whose centre is nearest within `SAME_STEM_M` and that no view of its own
    station holds yet (two stems of one station are never one). Seen by most stations first."""
    groups: list[_Group] = []
    for k, T in placements(survey).items():
        st = survey.stations[k]
        if not len(st.stems):
            continue
        z = st.ground_z(st.stems.xy) + BREAST_HEIGHT_M
        xyz = apply_transform(T, np.column_stack([st.stems.xy, z]))
        for c, (p, r) in enumerate(zip(xyz, st.stems.radius_m)):
            best, best_d = None, SAME_STEM_M
            for g in groups:
                if any(v[0] == k for v in g.views):
                    continue
                d = float(np.hypot(*(g.centre[:2] - p[:2])))
                if d < best_d:
                    best, best_d = g, d
            if best is None:
                groups.append(_Group(at=[p], radii=[float(r)], views=[(k, c)]))
            else:
                best.at.append(p)
                best.radii.append(float(r))
                best.views.append((k, c))
    groups.sort(key=lambda g: (-len(g.views), float(g.centre[0]), float(g.centre[1])))
    return tuple(PlotStem(index=i, xyz=g.centre, radius_m=float(np.median(g.radii)), views=tuple(sorted(g.views)))
                 for i, g in enumerate(groups))


@dataclass(frozen=True, kw_only=True)
class Check:
    """One number a pair's verdict rests on, beside its threshold: `ok` says whether it passes."""

    what: str
    value: str
    threshold: str
    ok: bool


@dataclass(frozen=True, kw_only=True, eq=False)
class PairInspection:
    """Pair `index` inspected: its stations, verdict and reasons, the checks (each beside its
    threshold), its other numbers, and the sections of its shared stems from both stations — the
    reference's placed, the target's under the pair's own fit and then placed with the reference
    (`station_of` says whose each point is; `used` whether its stem was used by the fit)."""

    index: int
    i: int
    j: int
    verdict: str
    state: str
    reasons: tuple[str, ...]
    checks: tuple[Check, ...]
    numbers: tuple[tuple[str, str], ...]
    points: np.ndarray
    station_of: np.ndarray
    used: np.ndarray
    stems_xyz: np.ndarray  # K x 3: the shared stems at breast height (placed)
    stems_used: np.ndarray  # K bools


def _mm(v: float) -> str:
    return f"{v * 1000:.2f} mm" if np.isfinite(v) else "not measured"


def _share(v: float) -> str:
    return f"{v:.0%}" if np.isfinite(v) else "not measured"


def pair_checks(pair: SurveyPair, sv: SurveyParams) -> tuple[Check, ...]:
    """The checks of `register._judged`, each number beside the threshold it is judged against."""
    f = pair.fit
    out = [Check(what="stems used", value=f"{f.stems_used} of {len(f.stems)}",
                 threshold=f"at least {sv.min_stems} (survey.min_stems)", ok=f.stems_used >= sv.min_stems),
           Check(what="stem residual", value=_mm(f.residual_m),
                 threshold=f"at most {sv.max_residual_m * 1000:g} mm (survey.max_residual_m)",
                 ok=bool(f.residual_m <= sv.max_residual_m)),
           Check(what="pose uncertainty 20 m out", value=_mm(f.pose_sd_m),
                 threshold=f"at most {sv.max_pose_sd_m * 1000:g} mm (survey.max_pose_sd_m)",
                 ok=bool(f.pose_sd_m <= sv.max_pose_sd_m)),
           Check(what="stems' spread across their line", value=f"{f.spread_m:.2f} m" if np.isfinite(f.spread_m) else "not measured",
                 threshold=f"at least {_MIN_SPREAD_M:g} m", ok=bool(f.spread_m >= _MIN_SPREAD_M))]
    if np.isfinite(f.runner_up_agreement):
        out.append(Check(what=f"crowns agree, stem map shifted {f.runner_up_shift_m:.1f} m",
                         value=f"{_share(f.runner_up_agreement)} against {_share(f.agreement)}",
                         threshold=f"below {sv.ambiguity:g} × the best's (survey.ambiguity)",
                         ok=bool(f.runner_up_agreement < sv.ambiguity * f.agreement)))
    else:
        out.append(Check(what="shifted stem map", value="none fits as many stems",
                         threshold=f"crowns below {sv.ambiguity:g} × the best's (survey.ambiguity)", ok=True))
    return tuple(out)


def inspect_pair(survey: Survey, index: int, sv: SurveyParams) -> PairInspection:
    """Pair `index` of `survey` inspected (see `PairInspection`)."""
    p = survey.pairs[index]
    f = p.fit
    state, loop = link_state(survey, p)
    placed = placements(survey)
    # The pair is drawn where the placement put its reference (or its target, through the fit).
    if p.i in placed:
        T_i = placed[p.i]
    elif p.j in placed and f.T_ref_target is not None:
        T_i = placed[p.j] @ np.linalg.inv(f.T_ref_target)
    else:
        T_i = np.eye(4)
    T_j = T_i @ f.T_ref_target if f.T_ref_target is not None else placed.get(p.j, T_i)
    ref, tgt = survey.stations[p.i], survey.stations[p.j]
    pts, who, used, at, at_used = [], [], [], [], []
    for tie in f.stems:
        for k, st, c, T in ((p.i, ref, tie.ref_index, T_i), (p.j, tgt, tie.tgt_index, T_j)):
            if c >= len(st.columns):
                continue
            col = st.columns[c]
            pts.append(apply_transform(T, col.points))
            who.append(np.full(len(col.points), k, dtype=np.int32))
            used.append(np.full(len(col.points), tie.used))
        z = ref.ground_z(np.asarray([tie.xy]))[0] + BREAST_HEIGHT_M
        at.append(apply_transform(T_i, np.array([[tie.xy[0], tie.xy[1], z]]))[0])
        at_used.append(tie.used)
    numbers = (("shared stems (stem maps)", str(p.shared_stems)), ("stems used", f"{f.stems_used} of {len(f.stems)}"),
               ("stem residual", _mm(f.residual_m)), ("ground residual", _mm(f.ground_residual_m)),
               ("ground points", f"{f.ground_points:,}"), ("pose uncertainty 20 m out", _mm(f.pose_sd_m)),
               ("crowns agree", _share(f.agreement)),
               ("shifted stem map: crowns agree", _share(f.runner_up_agreement) if np.isfinite(f.runner_up_agreement)
                else "no rival stem map"),
               ("residual in the joint placement", _mm(loop)),
               ("in the placement", {"used": "used", "dropped": "verified, dropped by a loop that did not close"}
                .get(state, "not used (not verified)")))
    return PairInspection(index=index, i=int(p.i), j=int(p.j), verdict=p.verdict, state=state, reasons=p.reasons,
                          checks=pair_checks(p, sv), numbers=numbers,
                          points=np.concatenate(pts) if pts else np.zeros((0, 3)),
                          station_of=np.concatenate(who) if who else np.zeros(0, np.int32),
                          used=np.concatenate(used) if used else np.zeros(0, bool),
                          stems_xyz=np.asarray(at).reshape(-1, 3), stems_used=np.asarray(at_used, bool))


@dataclass(frozen=True, kw_only=True, eq=False)
class StemView:
    """One station's view of a plot stem, placed: its section points (`section`: each point's index into
    the sections), each section's circle (`circles`: S x 4, centre x, y, z and radius; NaN where the
    station fitted none) and height above the ground (`heights_m`), and the section nearest breast height."""

    station: int
    name: str
    points: np.ndarray
    section: np.ndarray
    circles: np.ndarray
    heights_m: np.ndarray
    breast: int  # index of the section nearest BREAST_HEIGHT_M (-1: none fitted)


@dataclass(frozen=True, kw_only=True, eq=False)
class StemInspection:
    index: int
    xyz: np.ndarray
    radius_m: float
    views: tuple[StemView, ...]

    @property
    def heights(self) -> tuple[float, float]:
        """The lowest and highest section centre any station placed (m, the reference frame's z);
        breast height alone when none was traced."""
        z = np.concatenate([v.circles[:, 2] for v in self.views]) if self.views else np.zeros(0)
        z = z[np.isfinite(z)]
        return (float(z.min()), float(z.max())) if len(z) else (float(self.xyz[2]), float(self.xyz[2]))


def inspect_stem(survey: Survey, stem: PlotStem) -> StemInspection:
    """A plot stem's sections from every station that sees it, placed (see `StemView`)."""
    placed = placements(survey)
    views = []
    for k, c in stem.views:
        st, T = survey.stations[k], placed[k]
        col = st.columns[c]
        S = len(col.radii)
        z = np.full(S, np.nan)
        for s in range(S):
            on = col.section == s
            if on.any() and np.isfinite(col.radii[s]):
                z[s] = float(np.median(col.points[on, 2]))
        good = np.isfinite(z)
        heights = np.full(S, np.nan)
        if good.any():
            heights[good] = z[good] - st.ground_z(col.centres[good])
        centres = np.column_stack([col.centres, z])
        placed_c = np.full((S, 3), np.nan)
        if good.any():
            placed_c[good] = apply_transform(T, centres[good])
        breast = int(np.nanargmin(np.abs(heights - BREAST_HEIGHT_M))) if good.any() else -1
        views.append(StemView(station=k, name=survey.scans[k].name, points=apply_transform(T, col.points),
                              section=col.section.copy(), circles=np.column_stack([placed_c, col.radii]),
                              heights_m=heights, breast=breast))
    return StemInspection(index=stem.index, xyz=stem.xyz, radius_m=stem.radius_m, views=tuple(views))
