"""The verdict of one registered pair: verified, unverified (with the reasons) or failed.

Independent kinds of evidence, each measured and reported, because no single number separates a
right registration from a wrong one (a correct pair with neighbouring trees can have as few coarse
inliers as two different look-alike trees):

* support — the coarse tie points that agree with the coarse transform or with the final pose,
  against what RANSAC reaches on randomly re-paired ties;
* agreement — the free-space test at the final pose (`visibility`): of the target's points that
  both stations could see, the share lying where the reference saw a surface (not in space it saw
  through), and enough of them to judge;
* residual — the trimmed point-to-plane residual of the surfaces against their own noise floor;
* ambiguity — the margin to the best distinct competing hypothesis (`hypotheses`);
* plausibility — the scanner stays nearly level; both scanners stand at the heights above the
  ground their own scans show.

Wind: when the fine stage fitted a bend of the target's stem (its crown moved between the
stations), the crown's motion is a nuisance, not evidence against the pose — but only as far as a
motion model fitted from the stems explains it. The target is then judged unbent (as the
reference's tree stood); its points the reference saw through count as moved, not as
contradictions, only within the branches' flutter the bend explains (`flutter_allowance`:
wind.flutter_share of the top's sway, in proportion to a point's height above the stem base,
never more than verify.max_motion_m), never within whatever the consistency check would need; the
consistency is shown with and without that allowance. A bend that moves the stem's base is no
wind's (a cantilever's base does not move: `_base_offset`), a heading the free-space evidence
prefers elsewhere is the pose's, one it cannot fix within verify.max_heading_deg (a broad top of
fluttering leaves) is not verified, and the wind is named as a reason only for a pose that passes
its own checks (stem lean, shift and base, heading, tilt, height): otherwise the pose is refused
for itself. The support is counted at the final pose, unbent, and the competing hypotheses are judged
the same way.

Plausibility checks are judged only with their evidence: the scanner height only when each scan
shows ground on its plane near its scanner (verify.ground_radius_m, min_ground_points,
ground_fit_m); "not the same tree" only with support at chance, the overlap to judge and a pose
that stands the scanner level; otherwise "not judged", the reason in the check's rule.

With three or more scans the pose graph adds loop closure (`graph`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np

from ..fine.bend import Bend
from ..fine.stem import StemProfile
from ..fine.surface import Surface, noise_floor, trimmed_residuals
from ..geometry.rigid import apply_transform, make_transform, rotation_z
from ..coarse.estimate import CoarseResult
from ..params import AcceptanceParams, CoarseParams, HypothesesParams, VerifyParams, WindParams
from ..results import Metric
from .hypotheses import SCORE_POINTS, HypothesesResult, distinct
from .visibility import RangeImage, Visibility, placed, violation_distances, visibility



VERIFIED, UNVERIFIED, FAILED = "verified", "unverified", "failed"


@dataclass(frozen=True)
class Evidence:
    """Every number the verdict of a pair rests on (NaN / None where not measured)."""

    inliers: int
    ties: int
    chance_inliers: int
    consistency: float
    seen_by_both: int
    violations: int
    residual_m: float
    noise_m: float
    chosen: str
    rival: str
    margin: float
    tilt_deg: float
    height_difference_m: float | None
    chosen_by_hand: bool = False
    #: Wind: how far the target's stem top had moved from the reference's (0 in still air), towards
    #: which azimuth (reference frame), its noise, and the height up to which the stems agree.
    sway_m: float = 0.0
    sway_direction_deg: float = float("nan")
    sway_std_m: float = float("nan")
    stable_height_m: float = float("nan")
    #: Whether the reference's tree holds a crown (`fine.stem.StemProfile.crown`; True when no stem
    #: was traced to tell). Without one the sway is a bend fitted to a bare stem, which cannot tell
    #: wind from a pose that is off: it is not called a crown's motion.
    crown: bool = True
    #: Wind: how far the points that still disagree once the stem is unbent must be allowed to lie
    #: from a surface the reference saw for the views to agree (the branches' own motion), the
    #: allowance used (capped at verify.max_motion_m), and the points counted as moved.
    motion_needed_m: float = 0.0
    motion_m: float = 0.0
    moved: int = 0
    #: The stem profile at the final pose: how far the target's stem leans against the reference's
    #: and how far apart they stand (at the profile's mid height), each with its noise std.
    stem_tilt_deg: float = float("nan")
    stem_tilt_std_deg: float = float("nan")
    stem_shift_m: float = float("nan")
    stem_shift_std_m: float = float("nan")
    #: Wind, the sections leaving the turn about the stem open: how far from the pose the free-space
    #: evidence puts the heading (deg, a turn about the stem; when the evidence is flat, its reach or
    #: the farthest turn that fits as well as the best; NaN when not measured).
    heading_offset_deg: float = float("nan")
    #: The fine stage kept its update; False: the pose is the coarse one, millimetres less certain
    #: (what the joint placement weighs the pair by, not part of the verdict).
    fine_kept: bool = True
    #: Wind: the free-space consistency of the target unbent with no motion granted (the
    #: `consistency` grants the branches' flutter the motion model explains: `motion_m` at the top).
    consistency_still: float = float("nan")
    #: Wind: how far the two stems stand apart below `base_height_m` (wind.base_share of the tree's
    #: height) once the fitted bend is taken out (the most of any slab there), and its noise: a
    #: cantilever's base does not move. NaN when not measured.
    base_offset_m: float = float("nan")
    base_offset_std_m: float = float("nan")
    base_height_m: float = float("nan")
    #: The heading scan found the free-space evidence flat (it cannot fix the heading), rather than
    #: preferring a heading at or beyond `heading_offset_deg`.
    heading_flat: bool = False
    #: Points of each scan on its own ground plane (within verify.ground_fit_m) within
    #: verify.ground_radius_m of its scanner: the evidence the scanner-height check rests on (-1: not
    #: counted).
    ground_ref_points: int = -1
    ground_tgt_points: int = -1
    #: How far each scan's ground plane tilts from its z, when that ground is seen near its scanner
    #: (NaN otherwise): a ground tilted beyond verify.max_tilt_deg is a tilted scanner or a slope, which
    #: the scan cannot tell apart, and the scanner-tilt check lacks its premise.
    ground_ref_tilt_deg: float = float("nan")
    ground_tgt_tilt_deg: float = float("nan")

    def as_dict(self) -> dict[str, float | int | str | None]:
        return dict(self.__dict__)


@dataclass(frozen=True, kw_only=True)
class PairVerification:
    """The verify stage's result for one pair.

    `ok` is True when a transform exists (verified, unverified, or failed because the scans show two
    different trees: the transform is kept for inspection); `verdict` says whether it can be
    trusted, `reasons` why not (sentences a user can act on), `hint` what to try, `checks` every
    check with its value, threshold and outcome.
    """

    ok: bool
    message: str
    metrics: tuple[Metric, ...]
    T_ref_target: np.ndarray
    verdict: str
    reasons: tuple[str, ...]
    hint: str
    evidence: Evidence
    #: Every check beside its threshold (`Check`), in the order of the reasons; the reasons are the
    #: failed checks' own.
    checks: tuple["Check", ...] = ()

    @property
    def other_tree(self) -> bool:
        """The two scans show different trees (the "same tree" check failed, the only way a verified
        pair fails): no scan is placed from this pair."""
        return self.verdict == FAILED


def scanner_height_m(plane: tuple[float, float, float, float] | None) -> float | None:
    """Height of the scanner (the frame's origin) above a scan's ground plane, or None without ground."""
    return None if plane is None else float(plane[3])


@dataclass(frozen=True, kw_only=True)
class PairScene:
    """The two scans of a pair as the verdict compares them.

    Attributes
    ----------
    ref_image : the reference's range image (what its laser saw and passed through).
    ref_surface, tgt_surface : both scans' surfaces; under wind the target's unbent.
    tgt_points : the target's prepared points, own frame.
    ref_plane, tgt_plane : each scan's ground plane (None without ground).
    ref_stem_xy : the reference's stem (reference frame), about which the heading is turned.
    """

    ref_image: RangeImage
    ref_surface: Surface
    tgt_surface: Surface
    tgt_points: np.ndarray
    ref_plane: tuple[float, float, float, float] | None
    tgt_plane: tuple[float, float, float, float] | None
    ref_stem_xy: np.ndarray | None = None
    #: Each scan's whole station (its own frame, ground included): where its ground near the scanner
    #: is counted (None: not counted, the height check judged on the planes alone).
    ref_station: np.ndarray | None = None
    tgt_station: np.ndarray | None = None


@dataclass(frozen=True, kw_only=True)
class PairResults:
    """What the earlier stages found for the pair: its coarse transform and competing hypotheses,
    and the fine stage's pose with what it found about the wind.

    Attributes
    ----------
    coarse, hypotheses : the coarse and hypotheses stages' results (hypotheses None when not run).
    T_ref_target : the final pose.
    bend : the target's stem bent against the reference's (None in still air).
    profile : the stem profile at the pose.
    turn_held : the fine stage could not fix the turn about the stem.
    fine_kept : the fine stage kept its update (False: the pose is the coarse one).
    """

    coarse: CoarseResult
    hypotheses: HypothesesResult | None
    T_ref_target: np.ndarray
    bend: Bend | None = None
    profile: StemProfile | None = None
    turn_held: bool = False
    fine_kept: bool = True


def gather_evidence(scene: PairScene, results: PairResults, *, verify: VerifyParams, hypotheses: HypothesesParams,
                    acceptance: AcceptanceParams, wind: WindParams, support_inlier_m: float) -> Evidence:
    """Measure every kind of evidence for the pose `results.T_ref_target` of the target.

    With a `bend` (the crown moved between the stations; `tgt_surface` is then the target's surface
    unbent), the target is judged unbent: points the reference saw through count as moved within the
    branches' flutter the bend explains (`flutter_allowance`, wind.flutter_share), and the
    consistency is also measured with none granted; the motion the check would need is measured
    (up to twice `verify.max_motion_m`) and shown, never granted. Its support also counts the
    ties that agree with the pose (within `support_inlier_m`), and its rivals are judged alike;
    below wind.base_share of the height the stems must agree once the bend is taken out.
    `scene.ref_station`/`tgt_station`: the ground near each scanner is counted for the height check.
    `profile`: the stem profile at the pose (the height the stems agree up to, within
    `wind.stable_tolerance_m`, and whether they lean or stand apart). With `turn_held` (the fine
    stage could not fix the turn about the stem, at `ref_stem_xy`), the heading the free-space
    evidence prefers is measured against the pose's.
    """
    ref_image, ref_surf, tgt_surf, tgt_points = scene.ref_image, scene.ref_surface, scene.tgt_surface, scene.tgt_points
    ref_plane, tgt_plane, axis_xy = scene.ref_plane, scene.tgt_plane, scene.ref_stem_xy
    coarse, hyp, T = results.coarse, results.hypotheses, results.T_ref_target
    bend, profile, turn_held = results.bend, results.profile, results.turn_held
    max_motion_m, min_consistency = verify.max_motion_m, verify.min_consistency
    rng = np.random.default_rng(0)
    pts = tgt_points if len(tgt_points) <= SCORE_POINTS else tgt_points[rng.choice(len(tgt_points), SCORE_POINTS, replace=False)]
    unbend = bend.unbend if bend is not None else None
    needed = motion = 0.0
    allowance = None
    still = float("nan")
    if bend is not None:
        # What the check would need (shown, never granted) and what the motion model grants.
        needed = _motion_needed(*violation_distances(ref_image, pts, T, hypotheses.tolerance_m, unbend,
                                                     ref_surf.cloud_tree, 2.0 * max_motion_m), min_consistency)
        allowance = flutter_allowance(bend, wind.flutter_share, hypotheses.tolerance_m, max_motion_m)
        motion = float(allowance(np.array([[0.0, 0.0, bend.base_z_m + bend.height_m]]))[0])
        still = float(visibility(ref_image, pts, T, hypotheses.tolerance_m, unbend=unbend).consistency)

    def judged(T_: np.ndarray) -> Visibility:
        return visibility(ref_image, pts, T_, hypotheses.tolerance_m, unbend=unbend, surface_tree=ref_surf.cloud_tree,
                          motion_m=allowance if allowance is not None else 0.0)

    vis: Visibility = judged(T)
    residual = float(trimmed_residuals(ref_surf, tgt_surf, [T], acceptance.gate_m, acceptance.select_trim)[0])
    noise = float(np.nanmax([noise_floor(ref_surf), noise_floor(tgt_surf)]))
    tilt = float(np.degrees(np.arccos(np.clip(T[2, 2], -1.0, 1.0))))
    dh = None
    h_ref, h_tgt = scanner_height_m(ref_plane), scanner_height_m(tgt_plane)
    if h_ref is not None and h_tgt is not None:
        # The target's scanner, mapped into the reference frame, above the reference's ground.
        station = apply_transform(T, np.zeros((1, 3)))[0]
        n, d = np.asarray(ref_plane[:3]), float(ref_plane[3])
        dh = float(station @ n + d - h_tgt)
    inliers = coarse.n_inliers
    rival = hyp.runner_up if hyp is not None else ""
    margin = float(hyp.margin) if hyp is not None else float("nan")
    match = coarse.match
    if match is not None and match.n_ties:
        # The ties that agree with the final pose count too (the coarse transform is RANSAC's best on
        # them alone, fitted rigidly even to a crown that moved): the target unbent under wind.
        q = placed(match.tgt_xyz, T, unbend)
        inliers = max(inliers, int(np.count_nonzero(np.linalg.norm(q - match.ref_xyz, axis=1) < support_inlier_m)))
    if bend is not None:
        if hyp is not None and hyp.candidates and not hyp.chosen_by_hand:
            rival, margin = _rival_under_wind(hyp, T, pts, judged, vis, hypotheses)
    model = profile.model if profile is not None else None
    stem = dict(stem_tilt_deg=float(np.degrees(np.hypot(*model.tilt))), stem_tilt_std_deg=float(np.degrees(np.hypot(*model.std[2:4]))),
                stem_shift_m=float(np.hypot(*model.shift_m)), stem_shift_std_m=float(np.hypot(*model.std[0:2]))) if model else {}
    heading, flat = float("nan"), False
    if bend is not None and turn_held and axis_xy is not None:
        heading, flat = _heading_offset(ref_image, pts, T, axis_xy, unbend, hypotheses.tolerance_m,
                                        4.0 * verify.max_heading_deg, verify.max_heading_deg)
    base = _base_offset(profile, bend, wind.base_share) if bend is not None and profile is not None else {}
    ground = {}
    if scene.ref_station is not None and scene.tgt_station is not None:
        ground = dict(ground_ref_points=ground_near_scanner(scene.ref_station, ref_plane, verify),
                      ground_tgt_points=ground_near_scanner(scene.tgt_station, tgt_plane, verify))
        for which, plane in (("ref", ref_plane), ("tgt", tgt_plane)):
            if plane is not None and ground[f"ground_{which}_points"] >= verify.min_ground_points:
                ground[f"ground_{which}_tilt_deg"] = float(np.degrees(np.arccos(np.clip(abs(plane[2]), 0.0, 1.0))))
    return Evidence(
        inliers=inliers, ties=coarse.n_ties,
        chance_inliers=coarse.chance_inliers, consistency=float(vis.consistency),
        seen_by_both=vis.seen_by_both, violations=vis.violations, residual_m=residual, noise_m=noise,
        chosen=hyp.chosen if hyp is not None else "coarse", rival=rival,
        margin=margin, tilt_deg=tilt, height_difference_m=dh,
        chosen_by_hand=bool(hyp is not None and hyp.chosen_by_hand),
        sway_m=bend.sway_m if bend is not None else 0.0,
        sway_direction_deg=bend.sway_direction_deg if bend is not None else float("nan"),
        sway_std_m=bend.sway_std_m if bend is not None else float("nan"),
        stable_height_m=profile.stable_height_m(wind.stable_tolerance_m) if profile is not None else float("nan"),
        crown=profile.crown if profile is not None else True,
        motion_needed_m=needed, motion_m=motion, moved=vis.moved, heading_offset_deg=heading, heading_flat=flat,
        fine_kept=results.fine_kept, consistency_still=still, **stem, **base, **ground,
    )


def flutter_allowance(bend: Bend, flutter_share: float, tolerance_m: float,
                      max_motion_m: float) -> Callable[[np.ndarray], np.ndarray]:
    """The motion the stems' fitted bend explains beyond itself, point by point: the branches' own
    flutter, at most `flutter_share` times the stem top's sway, in proportion to a point's height
    above the stem base (nothing at the base, all of it at the top), never more than
    `max_motion_m` (points placed and unbent, reference frame)."""
    def allow(p: np.ndarray) -> np.ndarray:
        s = np.clip((np.asarray(p, dtype=float)[:, 2] - bend.base_z_m) / bend.height_m, 0.0, 1.0)
        return np.minimum(tolerance_m + flutter_share * bend.sway_m * s, max_motion_m)
    return allow


def _base_offset(profile: StemProfile, bend: Bend, base_share: float) -> dict[str, float]:
    """How far the target's stem stands from the reference's below `base_share` of the tree's
    height once the fitted bend is taken out (the most of any slab there), and that slab's noise;
    {} with fewer than 3 slabs there."""
    rel = (profile.heights_m - profile.base_z_m) / profile.height_m
    low = rel < base_share
    if np.count_nonzero(low) < 3:
        return {}
    off = profile.offsets_m[low] + bend.shape(profile.heights_m[low])[:, None] * np.asarray(bend.top_m)[None, :]
    dist = np.hypot(off[:, 0], off[:, 1])
    i = int(np.argmax(dist))
    return dict(base_offset_m=float(dist[i]), base_offset_std_m=float(profile.std_m[low][i]),
                base_height_m=float(base_share * profile.height_m))


def ground_near_scanner(station: np.ndarray, plane: tuple[float, float, float, float] | None, verify: VerifyParams) -> int:
    """Points of a station (its own frame) on its ground plane (within verify.ground_fit_m) within
    verify.ground_radius_m of its scanner, horizontally: the ground the scanner's height is read
    from (0 without a plane)."""
    if plane is None:
        return 0
    p = np.asarray(station, dtype=float)
    near = p[np.hypot(p[:, 0], p[:, 1]) <= verify.ground_radius_m]
    if not len(near):
        return 0
    return int(np.count_nonzero(np.abs(near @ np.asarray(plane[:3]) + float(plane[3])) <= verify.ground_fit_m))


def sway_text(e: Evidence) -> str:
    """The fitted bend in words that are true: "the crown moved 0.21 m between the stations (the stem
    top)", or, on a stem without crown, how far its top stands off and what that cannot tell apart."""
    if e.crown:
        return f"the crown moved {e.sway_m:.2f} m between the stations (the stem top)"
    return (f"the stem top stands {e.sway_m:.2f} m off the reference's (a bend fitted to a stem without crown: wind, "
            "or a pose that is off, which a bare stem cannot tell apart)")


#: Steps of the heading scan each side of the pose.
_HEADING_STEPS = 8
#: The heading scan's consistency must fall by at least this from its best to either end, else the
#: evidence is flat: it cannot fix the heading.
_HEADING_DROP = 0.005


def _heading_offset(ref_image: RangeImage, pts: np.ndarray, T: np.ndarray, axis_xy: np.ndarray, unbend,
                    tolerance_m: float, reach_deg: float, within_deg: float | None = None) -> tuple[float, bool]:
    """The heading the free-space evidence prefers, relative to the pose: the pose turned about the
    stem (at `axis_xy`, reference frame) in steps up to `reach_deg` each way, the consistency of the
    unbent target at each turn, and the vertex of a parabola through the best turn and its
    neighbours (deg). `reach_deg` when the best lies at either end or the evidence is flat; and
    whether it is flat (the best no better than the pose's own by `_HEADING_DROP`, or not above
    either end by as much): it cannot fix the heading, rather than preferring another. Also flat, with
    the farthest such turn returned, when every turn that fits within `_HEADING_DROP` of the best lies
    on one side of the pose and one more than `within_deg` from it: a broad top (fluttering leaves)
    that the pose sits at the edge of bounds its heading no closer than its far end, however near the
    pose the parabola's vertex lies."""
    offsets = np.linspace(-reach_deg, reach_deg, 2 * _HEADING_STEPS + 1)
    c = np.array([axis_xy[0], axis_xy[1], 0.0])
    cons = []
    for d in offsets:
        R = rotation_z(float(d))
        v = visibility(ref_image, pts, make_transform(R, c - R @ c) @ T, tolerance_m, unbend=unbend)
        cons.append(v.consistency if np.isfinite(v.consistency) else 0.0)
    cons = np.array(cons)
    best = int(np.argmax(cons))
    if best in (0, len(offsets) - 1):
        return float(reach_deg), bool(cons[best] - cons[_HEADING_STEPS] < _HEADING_DROP)
    if min(cons[best] - cons[0], cons[best] - cons[-1]) < _HEADING_DROP:
        return float(reach_deg), True
    alike = offsets[np.asarray(cons) >= cons[best] - _HEADING_DROP]
    one_side = alike.max() <= 1e-9 or alike.min() >= -1e-9
    if within_deg is not None and one_side and np.abs(alike).max() > within_deg + 1e-9:
        return float(np.abs(alike).max()), True
    near = slice(max(best - 2, 0), best + 3)
    a, b, _ = np.polyfit(offsets[near], cons[near], 2)
    vertex = -b / (2.0 * a) if a < 0 else offsets[best]
    return float(np.clip(vertex, -reach_deg, reach_deg)), False


def _motion_needed(distances_m: np.ndarray, seen: int, min_consistency: float) -> float:
    """The smallest distance within which the points the reference saw through must lie of a surface
    it saw, for `min_consistency` of the `seen` points to agree (0 when they agree already)."""
    d = np.sort(distances_m)
    consistent = seen - len(d)
    allowed = int(np.floor(consistent * (1.0 - min_consistency) / max(min_consistency, 1e-9)))
    if len(d) <= allowed:
        return 0.0
    return float(d[len(d) - allowed - 1])


def _rival_under_wind(hyp: HypothesesResult, T: np.ndarray, pts: np.ndarray, judged, best: Visibility,
                      p: HypothesesParams) -> tuple[str, float]:
    """The best distinct competing hypothesis judged as the final pose is (unbent, motion allowed),
    and the margin of the final pose's consistency over it (negative: the rival explains the scans
    better)."""
    centre = pts.mean(axis=0)
    rivals = [c for c in hyp.candidates if distinct(c.T_ref_target, T, centre, p.distinct_deg, p.distinct_m)]
    if not rivals:
        return "", 1.0
    scored = [(judged(c.T_ref_target).consistency, c.label) for c in rivals]
    scored = [(c if np.isfinite(c) else 0.0, lab) for c, lab in scored]
    cons, label = max(scored)
    base = best.consistency if np.isfinite(best.consistency) else 0.0
    return label, float(base - cons)


@dataclass(frozen=True)
class Check:
    """One check of a pair's verdict beside its threshold, as the app shows it in a table.

    Attributes
    ----------
    what : what is checked, in a person's words ("tie support", "free-space consistency").
    value : what was measured (None: not measured; NaN reads as not measured too).
    unit : "", "m", "deg", "points" or "ties".
    relation, limit : the check passes when `value <relation> limit` (">=" or "<="); `limit` is the
        effective threshold compared with (e.g. max(coarse.min_ties, chance_factor x chance)).
    parameter : the Params key that sets the limit ("verify.chance_factor").
    rule : how the limit is made, in words, and why a check was not judged.
    passed : True, False, or None when not judged (not measured, or not applicable).
    reason, hint : the sentence among the pair's reasons and what to try, when it failed ("" otherwise).
    """

    what: str
    value: float | int | None
    unit: str
    relation: str
    limit: float | int | None
    parameter: str
    rule: str
    passed: bool | None
    reason: str = ""
    hint: str = ""

    def value_text(self) -> str:
        """"0.912", "1.2 mm", "4.1°", "412"; "not measured" for None or NaN."""
        return quantity_text(self.value, self.unit)

    def limit_text(self) -> str:
        """"≥ 0.95", "≤ 3.6 mm"; "" when there is no limit."""
        if self.limit is None or not _measured(self.limit):
            return ""
        sign = "≥" if self.relation == ">=" else "≤"
        return f"{sign} {quantity_text(self.limit, self.unit) if self.unit else f'{float(self.limit):.3g}'}"


def _measured(v: float | int | None) -> bool:
    return v is not None and bool(np.isfinite(float(v)))


def _unbounded(v: float | int | None) -> bool:
    """Measured, but beyond what the measurement reaches (a distance searched up to a limit)."""
    return v is not None and bool(np.isposinf(float(v)))


def _mm(v_m: float) -> str:
    """Metres as millimetres with one decimal, two significant digits below 0.1 mm ("0" only for
    zero: never "0.0" for a small nonzero length)."""
    mm = 1000.0 * v_m
    return "0" if mm == 0 else f"{mm:.1f}" if abs(mm) >= 0.1 else f"{mm:.2g}"


def quantity_text(value: float | int | None, unit: str) -> str:
    """A measured value as a person reads it: "0.912", "1.2 mm", "0.35 m", "4.1°", "412"; "not
    measured" for None or NaN (never "nan")."""
    if _unbounded(value):
        return "beyond reach"
    if not _measured(value):
        return "not measured"
    v = float(value)  # type: ignore[arg-type]
    if unit == "m":
        return f"{v:.2f} m" if abs(v) >= 0.1 else f"{_mm(v)} mm"
    if unit == "deg":
        return f"{v:.2f}°" if abs(v) < 1.0 else f"{v:.1f}°"
    if unit in ("points", "ties"):
        return f"{v:.0f}" if v == round(v) else f"{v:.1f}"
    return f"{v:.3f}"


def _check(what: str, value: float | int | None, unit: str, relation: str, limit: float | int | None, parameter: str,
           rule: str, *, judged: bool = True, reason: Callable[[], str] = lambda: "", hint: str = "") -> Check:
    """A Check compared here and only here: passed when judged and `value <relation> limit` (a NaN
    value fails a judged check); its reason is written only when it failed."""
    passed = (bool(value >= limit) if relation == ">=" else bool(value <= limit)) if judged else None  # type: ignore[operator]
    return Check(what, value, unit, relation, limit, parameter, rule, passed,
                 reason() if passed is False else "", hint if passed is False else "")


_CALM_HINT = "rescan these stations in calmer air, or add a station scanned soon after the reference"
_SAME_TREE_HINT = "check that both scans show the same tree"
#: The reason of a pair whose scans show two different trees (the graph stage recognises it).
OTHER_TREE = "it does not show the same tree as"


def _support(e: Evidence, p: VerifyParams, coarse: CoarseParams, wind: bool = True) -> Check:
    limit = max(coarse.min_ties, p.chance_factor * e.chance_inliers)
    judged = e.chance_inliers >= 0
    rule = (f"{p.chance_factor:g} × the {e.chance_inliers} inliers reached by chance (at least coarse.min_ties = "
            f"{coarse.min_ties})" if judged else "not judged: the ties were not re-paired at random")
    moving = (f"; the crown moved {e.sway_m:.2f} m between the stations, and ties on a moving crown agree less"
              if e.sway_m > 0 and e.crown and wind else "")
    return _check("tie support", e.inliers, "ties", ">=", limit if judged else None, "verify.chance_factor", rule,
                  judged=judged, hint=_SAME_TREE_HINT, reason=lambda: (
                      f"only {e.inliers} of {e.ties} tie points agree with the coarse transform or the final pose, against "
                      f"{e.chance_inliers} when the ties are re-paired at random (verify.chance_factor = {p.chance_factor:g})"
                      + moving))


def _overlap(e: Evidence, p: VerifyParams) -> Check:
    return _check("points seen by both stations", e.seen_by_both, "points", ">=", p.min_seen, "verify.min_seen",
                  f"verify.min_seen = {p.min_seen}: enough overlap to judge the free space",
                  hint="add a station between these two", reason=lambda: (
                      f"only {e.seen_by_both} of the target's points lie where both stations could see them "
                      f"(verify.min_seen = {p.min_seen}): too little overlap to judge"))


def _motion(e: Evidence, p: VerifyParams) -> Check:
    """What the consistency check would need granted as motion, beside what the motion model grants
    (shown, not judged: the consistency is judged with the model's allowance, never with this)."""
    return _check("branches' own motion (wind)", e.motion_needed_m, "m", "<=", e.motion_m, "wind.flutter_share",
                  f"shown, not judged: the motion the free-space consistency would need granted, beside the "
                  f"{100 * e.motion_m:.0f} cm at the top the stems' bend explains (wind.flutter_share of the sway, in "
                  f"proportion to the height; at most verify.max_motion_m = {p.max_motion_m:g} m), which the "
                  "consistency is judged with", judged=False)


def _consistency(e: Evidence, p: VerifyParams, why_not: str, wind: bool) -> Check:
    """The free-space consistency; under a fitted bend judged with the motion its model grants (the
    rule shows it with none granted too). `wind`: the pose passed its own checks, so the wind may be
    named as what the scans disagree by; otherwise the pose is."""
    granted = e.sway_m > 0 and _measured(e.consistency_still)
    still = (f"; {e.consistency_still:.3f} with no motion granted, {e.consistency:.3f} with the branches' flutter the "
             f"stems' bend explains (up to {100 * e.motion_m:.0f} cm at the top)") if granted else ""

    def reason() -> str:
        share = f"{1 - e.consistency:.1%} of the points both stations see lie in space the reference saw through"
        if not granted:
            return f"{share} (consistency {e.consistency:.3f} < verify.min_consistency = {p.min_consistency:g})"
        if wind:
            return (f"{sway_text(e)}, and with the stem's bend and the branches' flutter it explains taken out "
                    f"({e.moved} points within up to {100 * e.motion_m:.0f} cm of a surface the reference saw counted as "
                    f"moved) {share} (consistency {e.consistency:.3f} < verify.min_consistency = {p.min_consistency:g}): "
                    "more motion than the stem's bend explains, or a wrong pose")
        return (f"{share}, even with a bend of the stem and its branches' flutter taken out (consistency "
                f"{e.consistency:.3f} < verify.min_consistency = {p.min_consistency:g}; {e.consistency_still:.3f} with no "
                "motion granted): the pose does not fit the scans")
    hint = f"{_CALM_HINT}, or pick another hypothesis in the app" if granted and wind else \
        f"{_SAME_TREE_HINT}, or pick another hypothesis in the app"
    return _check("free-space consistency", e.consistency, "", ">=", p.min_consistency, "verify.min_consistency",
                  f"verify.min_consistency = {p.min_consistency:g} of the points both stations see lie where the "
                  "reference saw a surface" + still + (f" (not judged: {why_not})" if why_not else ""),
                  judged=not why_not, hint=hint, reason=reason)


def _same_tree(e: Evidence, p: VerifyParams, why_not: str, target: str, reference: str) -> Check:
    """Support at chance level and much of the target in the reference's free space (right poses leave
    6% or less there, two different trees 7% to 93%): the scans show two different trees, and the
    pair fails rather than stays a best guess."""
    return _check("same tree", e.consistency, "", ">=", p.other_tree_consistency, "verify.other_tree_consistency",
                  f"verify.other_tree_consistency = {p.other_tree_consistency:g}, judged when the tie support is at chance "
                  "level and the pose stands the scanner level (verify.max_tilt_deg): below it more of the target lies "
                  "in the reference's free space than a right pose leaves"
                  + (f" (not judged: {why_not})" if why_not else ""),
                  judged=not why_not, hint=f"check the files: {target} and {reference} may be scans of different trees",
                  reason=lambda: f"{OTHER_TREE} {reference}")


def _margin(e: Evidence, p: VerifyParams) -> Check:
    # A hypothesis picked by hand settles the ambiguity: the person looked at both.
    why_not = ("the hypothesis was chosen by hand" if e.chosen_by_hand else
               "no competing hypothesis was scored" if not _measured(e.margin) else "")
    rival = f" (best rival: {e.rival})" if e.rival else ""

    def reason() -> str:
        if e.margin < 0:
            return (f"another hypothesis ({e.rival}) explains the scans better (its consistency is "
                    f"{-e.margin:.3f} higher): the heading is wrong or ambiguous")
        return (f"another hypothesis ({e.rival}) explains the scans almost as well (consistency margin "
                f"{e.margin:.3f} < verify.min_margin = {p.min_margin:g}): the heading is ambiguous")
    return _check("ambiguity margin", e.margin, "", ">=", p.min_margin, "verify.min_margin",
                  f"verify.min_margin = {p.min_margin:g}: the chosen pose's consistency over the best distinct rival's"
                  + rival + (f" (not judged: {why_not})" if why_not else ""), judged=not why_not, reason=reason,
                  hint="compare the competing poses in the app (treereg view) and pick one, or add a station")


def _residual(e: Evidence, p: VerifyParams) -> Check:
    judged = _measured(e.noise_m) and e.noise_m > 0
    limit = p.max_residual_factor * e.noise_m if judged else None
    rule = (f"{p.max_residual_factor:g} × the scans' own noise ({_mm(e.noise_m)} mm)" if judged else
            f"verify.max_residual_factor = {p.max_residual_factor:g} × the scans' own noise (not judged: the noise was "
            "not measured)")

    def reason() -> str:
        what = "do not pair up" if not _measured(e.residual_m) else f"lie {_mm(e.residual_m)} mm apart"
        return (f"the two surfaces {what}, more than {p.max_residual_factor:g} times the scans' own noise "
                f"({_mm(e.noise_m)} mm)")
    return _check("surface residual", e.residual_m, "m", "<=", limit, "verify.max_residual_factor", rule,
                  judged=judged, reason=reason)


def _stem_lean(e: Evidence, ap: AcceptanceParams) -> Check:
    limit = max(ap.stem_tilt_deg, 3.0 * e.stem_tilt_std_deg)
    noise = f"; noise {e.stem_tilt_std_deg:.2f}°" if _measured(e.stem_tilt_std_deg) else ""
    return _check("stem lean", e.stem_tilt_deg, "deg", "<=", limit, "acceptance.stem_tilt_deg",
                  f"acceptance.stem_tilt_deg = {ap.stem_tilt_deg:g}°, or 3 × the lean's noise if larger"
                  + ("" if _measured(e.stem_tilt_deg) else " (not judged: no stem profile)"),
                  judged=_measured(e.stem_tilt_deg), reason=lambda: (
                      f"the target's stem leans {e.stem_tilt_deg:.2f}° against the reference's (acceptance.stem_tilt_deg "
                      f"= {ap.stem_tilt_deg:g}{noise}): the pose tilts the scan against the tree both stations saw"))


def _stem_shift(e: Evidence, ap: AcceptanceParams) -> Check:
    limit = max(ap.stem_shift_m, 3.0 * e.stem_shift_std_m)
    noise = f"; noise {_mm(e.stem_shift_std_m)} mm" if _measured(e.stem_shift_std_m) else ""
    return _check("stem shift", e.stem_shift_m, "m", "<=", limit, "acceptance.stem_shift_m",
                  f"acceptance.stem_shift_m = {_mm(ap.stem_shift_m)} mm, or 3 × the shift's noise if larger"
                  + ("" if _measured(e.stem_shift_m) else " (not judged: no stem profile)"),
                  judged=_measured(e.stem_shift_m), reason=lambda: (
                      f"the two stems stand {_mm(e.stem_shift_m)} mm apart (acceptance.stem_shift_m = "
                      f"{ap.stem_shift_m * 1000:g} mm{noise})"))


def _heading(e: Evidence, p: VerifyParams) -> Check:
    """The heading the free-space evidence prefers. Preferring another one is the pose's fault (it is
    turned); evidence too flat to fix it is the wind's (the bend left the turn about the stem open)."""
    judged = _measured(e.heading_offset_deg)
    # Wind is what to try against only when the scans agree with no motion granted: then only the
    # heading is loose, and a bend left it so.
    calm = e.heading_flat and _measured(e.consistency_still) and e.consistency_still >= p.min_consistency
    hint = f"{_CALM_HINT}, or pick another hypothesis in the app" if calm else "pick another hypothesis in the app, or add a station"

    def reason() -> str:
        if e.heading_flat:
            return (f"the sections leave the turn about the stem open, and the free-space evidence cannot fix the "
                    f"heading within {abs(e.heading_offset_deg):.1f}° of the pose (verify.max_heading_deg = "
                    f"{p.max_heading_deg:g})")
        return (f"the free-space evidence prefers a heading {abs(e.heading_offset_deg):.1f}° "
                f"{'or more ' if abs(e.heading_offset_deg) >= 4.0 * p.max_heading_deg else ''}from the pose's "
                f"(verify.max_heading_deg = {p.max_heading_deg:g}): the pose is turned about the stem")
    return _check("heading", abs(e.heading_offset_deg), "deg", "<=", p.max_heading_deg, "verify.max_heading_deg",
                  f"verify.max_heading_deg = {p.max_heading_deg:g}°: the heading the free-space evidence prefers, from "
                  "the pose's" + ("" if judged else " (not judged: measured only when the sections leave the turn about "
                                                    "the stem open)"),
                  judged=judged, hint=hint, reason=reason)


def _stem_base(e: Evidence, w: WindParams) -> Check:
    """Under a fitted bend: the stems agree low down, the bend taken out (a cantilever's base does
    not move); a bend whose base moved is no wind's, and the pose is refused for itself."""
    judged = _measured(e.base_offset_m)
    limit = max(w.stable_tolerance_m, 3.0 * e.base_offset_std_m) if judged and _measured(e.base_offset_std_m) else \
        w.stable_tolerance_m
    below = f"{e.base_height_m:.1f} m" if _measured(e.base_height_m) else "a third of the tree's height"
    return _check("stem base (wind)", e.base_offset_m, "m", "<=", limit, "wind.stable_tolerance_m",
                  f"wind.stable_tolerance_m = {_mm(w.stable_tolerance_m)} mm, or 3 × the profile's noise if larger: below "
                  f"wind.base_share = {w.base_share:.2g} of the tree's height the two stems agree once the fitted bend is "
                  "taken out (a cantilever's base does not move)"
                  + ("" if judged else " (not judged: too few stem slabs traced low down)"),
                  judged=judged, hint="pick another hypothesis in the app", reason=lambda: (
                      f"below {below} the two stems stand {_mm(e.base_offset_m)} mm apart once the fitted bend is taken "
                      f"out (wind.stable_tolerance_m = {_mm(w.stable_tolerance_m)} mm): a bend that moves the stem's base "
                      "is no wind's, the pose is off"))


def _tilt(e: Evidence, p: VerifyParams) -> Check:
    """Scanners stand nearly level: judged unless a scan's own ground near its scanner tilts beyond
    the limit (a tilted scanner or a slope, which the scan cannot tell apart: the premise fails)."""
    tipped = [f"{w} ground near its scanner tilts {t:.1f}° from its z (a tilted scanner or a slope, which the scan "
              "cannot tell apart)" for w, t in (("the reference's", e.ground_ref_tilt_deg), ("the target's", e.ground_tgt_tilt_deg))
              if _measured(t) and t > p.max_tilt_deg]
    why_not = "not measured" if not _measured(e.tilt_deg) else "; ".join(tipped)
    return _check("scanner tilt", e.tilt_deg, "deg", "<=", p.max_tilt_deg, "verify.max_tilt_deg",
                  f"verify.max_tilt_deg = {p.max_tilt_deg:g}°: scanners stand nearly level"
                  + (f" (not judged: {why_not})" if why_not else ""), judged=not why_not,
                  reason=lambda: (f"the transform tilts the scanner by {e.tilt_deg:.1f}° (verify.max_tilt_deg = "
                                  f"{p.max_tilt_deg:g}); scanners stand nearly level"))


def _height(e: Evidence, p: VerifyParams) -> Check:
    """Both scanners at the heights above the ground their own scans show: judged only when each
    scan shows its ground near its scanner (verify.min_ground_points on its plane within
    verify.ground_radius_m), else a plane fitted to distant ground, a slope or another surface would
    refuse right poses."""
    dh = e.height_difference_m
    counted = e.ground_ref_points >= 0 and e.ground_tgt_points >= 0
    few = [w for w, n in (("the reference's", e.ground_ref_points), ("the target's", e.ground_tgt_points))
           if counted and n < p.min_ground_points]
    why_not = ("not both scans show ground" if dh is None else
               f"{' and '.join(few)} scan shows fewer than verify.min_ground_points = {p.min_ground_points} points on its "
               f"ground plane within verify.ground_radius_m = {p.ground_radius_m:g} m of its scanner" if few else "")
    return _check("scanner height difference", abs(dh) if dh is not None else None, "m", "<=", p.max_height_difference_m,
                  "verify.max_height_difference_m",
                  f"verify.max_height_difference_m = {p.max_height_difference_m:g} m: each scanner at the height above the "
                  "ground its own scan shows near it" + (f" (not judged: {why_not})" if why_not else ""),
                  judged=not why_not, reason=lambda: (
                      f"the target's scanner would stand {abs(dh):.2f} m "  # type: ignore[arg-type]
                      f"{'higher' if dh > 0 else 'lower'} above the ground than its own scan shows"))  # type: ignore[operator]


def checks(e: Evidence, *, verify: VerifyParams, coarse: CoarseParams, acceptance: AcceptanceParams | None = None,
           target: str = "the target", reference: str = "the reference", wind: WindParams | None = None) -> tuple[Check, ...]:
    """Every check of the pair's verdict, in the order its reasons are given: "same tree" first (judged
    only when the support is at chance level), then support, overlap, the wind's motion (only when the
    crown moved), consistency (judged only with enough overlap and a motion the wind explains),
    ambiguity, residual, the stems, the heading (wind only), the scanner's tilt and height."""
    p, ap, w = verify, acceptance or AcceptanceParams(), wind or WindParams()
    overlap = _overlap(e, p)
    heading = (_heading(e, p),) if e.sway_m > 0 or _measured(e.heading_offset_deg) else ()
    base = (_stem_base(e, w),) if e.sway_m > 0 else ()
    pose = (_stem_lean(e, ap), _stem_shift(e, ap), *base, *heading, _tilt(e, p), _height(e, p))
    # The wind is named as a reason only for a pose that passes its own checks (its heading fixed
    # among them): a pose that fails one is refused for itself, however much bend was fitted to it.
    wind_story = not any(c.passed is False for c in pose)
    support = _support(e, p, coarse, wind_story)
    motion = (_motion(e, p),) if e.sway_m > 0 else ()
    why_not = ("too little overlap" if not overlap.passed else
               "not measured" if not _measured(e.consistency) else "")
    # "Another tree" needs its evidence: support at chance, the overlap to judge, and the scanner standing
    # level at the pose (scans compared upright; a pose that tips one over is wrong, whatever the trees).
    upright = _measured(e.tilt_deg) and e.tilt_deg <= p.max_tilt_deg
    # Why "another tree" is not judged, in the words of the first missing piece of its evidence.
    unjudged = ("the tie support is above chance level (these scans share tie points: no evidence of another tree)"
                if support.passed is not False else
                "too little overlap to compare the scans" if not overlap.passed else
                "the consistency was not measured" if not _measured(e.consistency) else
                "the pose tilts the scanner beyond verify.max_tilt_deg (scans compared only upright)" if not upright else "")
    same = _same_tree(e, p, unjudged, target, reference)
    still = (_check("free-space consistency, no motion granted", e.consistency_still, "", ">=", p.min_consistency,
                    "verify.min_consistency", "shown, not judged: the target unbent, none of its points counted as moved",
                    judged=False),) if e.sway_m > 0 and _measured(e.consistency_still) else ()
    return (same, support, overlap, *motion, _consistency(e, p, why_not, wind_story), *still, _margin(e, p),
            _residual(e, p), *pose)


def joined_hints(hints: Iterable[str]) -> str:
    """Hints joined by "; " with no clause twice: a hint whose clauses (split at ", or ") another hint
    holds too is left out, and a clause that repeats (or is contained in) an earlier or longer one is
    dropped ("check that both scans show the same tree" and "check that both scans show the same tree,
    or pick another hypothesis in the app" give the second once)."""
    groups = [h.split(", or ") for h in dict.fromkeys(h for h in hints if h)]
    groups = [g for k, g in enumerate(groups)
              if not any(set(g) < set(o) or (set(g) == set(o) and j < k) for j, o in enumerate(groups) if j != k)]
    clauses = [c for g in groups for c in g]
    seen: set[str] = set()
    out = []
    for g in groups:
        kept = [c for c in g if c not in seen and not any(c != o and c in o for o in clauses)]
        seen.update(kept)
        if kept:
            out.append(", or ".join(kept))
    return "; ".join(out)


@dataclass(frozen=True)
class Judgement:
    """The verdict of a pair from its checks: the reasons are the failed checks' (in their order),
    the hint theirs joined (a pair of two different trees: only the hint to check the files)."""

    verdict: str
    reasons: tuple[str, ...]
    hint: str
    checks: tuple[Check, ...]


def assess(e: Evidence, *, verify: VerifyParams, coarse: CoarseParams, acceptance: AcceptanceParams | None = None,
           target: str = "the target", reference: str = "the reference", wind: WindParams | None = None) -> Judgement:
    """The pair's checks and its verdict: failed when it shows another tree than the reference,
    unverified when any other check failed, else verified."""
    cs = checks(e, verify=verify, coarse=coarse, acceptance=acceptance, target=target, reference=reference, wind=wind)
    failed = [c for c in cs if c.passed is False]
    reasons = tuple(c.reason for c in failed)
    if cs[0].passed is False:  # "same tree": the files are what to check, nothing generic
        return Judgement(FAILED, reasons, cs[0].hint, cs)
    hint = joined_hints(c.hint for c in failed) or ("try --keep-unverified to use the best guess anyway" if failed else "")
    return Judgement(UNVERIFIED if failed else VERIFIED, reasons, hint, cs)


def judge(e: Evidence, *, verify: VerifyParams, coarse: CoarseParams, acceptance: AcceptanceParams | None = None,
          wind: WindParams | None = None) -> tuple[str, tuple[str, ...], str]:
    """The verdict from the evidence: (verdict, reasons it is not verified, what to try)."""
    j = assess(e, verify=verify, coarse=coarse, acceptance=acceptance, wind=wind)
    return j.verdict, j.reasons, j.hint


def verification(T: np.ndarray, e: Evidence, j: Judgement) -> PairVerification:
    """The verify stage's result for a pair: its transform, evidence, checks and verdict."""
    verdict, reasons = j.verdict, j.reasons
    metrics = (
        Metric("verdict", "", verdict),
        Metric("coarse inliers", "", e.inliers),
        Metric("inliers by chance", "", e.chance_inliers),
        Metric("free-space consistency", "", e.consistency),
        Metric("points seen by both stations", "", e.seen_by_both),
        Metric("points in the reference's free space", "", e.violations),
        Metric("surface residual (trimmed)", "m", e.residual_m),
        Metric("noise floor of the scans", "m", e.noise_m),
        Metric("ambiguity margin", "", e.margin),
        Metric("best rival hypothesis", "", e.rival or "none"),
        Metric("scanner tilt", "deg", e.tilt_deg),
        Metric("scanner height difference", "m", e.height_difference_m if e.height_difference_m is not None else float("nan")),
        Metric("stems lean against each other", "deg", e.stem_tilt_deg),
        Metric("stems stand apart", "m", e.stem_shift_m),
        Metric("crown moved between the stations (stem top)" if e.crown else
               "stem top off the reference's (a bend of a stem without crown)", "m", e.sway_m),
        Metric("stems agree up to (above the base)", "m", e.stable_height_m),
    ) + ((Metric("free-space consistency with no motion granted", "", e.consistency_still),
          Metric("branches moved on their own by (allowed at the top, by the stems' bend)", "m", e.motion_m),
          Metric("motion the consistency would need (not granted)", "m", e.motion_needed_m),
          Metric("points counted as moved", "", e.moved),
          Metric("stems apart low down, the bend taken out", "m", e.base_offset_m)) if e.sway_m > 0 else ()) + (
        (Metric("heading the evidence prefers (turn about the stem, from the pose)", "deg", e.heading_offset_deg),)
        if np.isfinite(e.heading_offset_deg) else ())
    return PairVerification(ok=True, message="; ".join(reasons), metrics=metrics, T_ref_target=np.asarray(T, dtype=float),
                            verdict=verdict, reasons=reasons, hint=j.hint, evidence=e, checks=j.checks)
