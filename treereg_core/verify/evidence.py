"""The verdict of one registered pair: verified, unverified (with the reasons) or failed.

Independent kinds of evidence, each measured and reported, because no single number separates a
right registration from a wrong one (a correct pair with neighbouring trees can have as few coarse
inliers as two different look-alike trees):

* support — the coarse stage's inliers against what RANSAC reaches on randomly re-paired ties;
* agreement — the free-space test at the final pose (`visibility`): of the target's points that
  both stations could see, the share lying where the reference saw a surface (not in space it saw
  through), and enough of them to judge;
* residual — the trimmed point-to-plane residual of the surfaces against their own noise floor;
* ambiguity — the margin to the best distinct competing hypothesis (`hypotheses`);
* plausibility — the scanner stays nearly level; both scanners stand at the heights above the
  ground their own scans show.

With three or more scans the pose graph adds loop closure (`graph`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..fine.surface import Surface, noise_floor, trimmed_residuals
from ..geometry.rigid import apply_transform
from ..params import AcceptanceParams, CoarseParams, HypothesesParams, VerifyParams
from ..results import Metric
from .hypotheses import SCORE_POINTS, HypothesesResult
from .visibility import RangeImage, Visibility, visibility

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

    def as_dict(self) -> dict[str, float | int | str | None]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class PairVerification:
    """The verify stage's result for one pair.

    `ok` is True when a transform exists (verified or not); `verdict` says whether it can be
    trusted, `reasons` why not (sentences a user can act on), `hint` what to try.
    """

    ok: bool
    message: str
    metrics: tuple[Metric, ...]
    T_ref_target: np.ndarray
    verdict: str
    reasons: tuple[str, ...]
    hint: str
    evidence: Evidence


def scanner_height_m(plane: tuple[float, float, float, float] | None) -> float | None:
    """Height of the scanner (the frame's origin) above a scan's ground plane, or None without ground."""
    return None if plane is None else float(plane[3])


def gather_evidence(ref_image: RangeImage, ref_surf: Surface, tgt_surf: Surface, tgt_points: np.ndarray,
                    T: np.ndarray, coarse: object, hyp: HypothesesResult | None,
                    ref_plane: tuple[float, float, float, float] | None,
                    tgt_plane: tuple[float, float, float, float] | None, *, hypotheses: HypothesesParams,
                    acceptance: AcceptanceParams) -> Evidence:
    """Measure every kind of evidence for the pose `T` of the target (prepared points, own frame)."""
    rng = np.random.default_rng(0)
    pts = tgt_points if len(tgt_points) <= SCORE_POINTS else tgt_points[rng.choice(len(tgt_points), SCORE_POINTS, replace=False)]
    vis: Visibility = visibility(ref_image, pts, T, hypotheses.tolerance_m)
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
    return Evidence(
        inliers=int(getattr(coarse, "n_inliers", 0)), ties=int(getattr(coarse, "n_ties", 0)),
        chance_inliers=int(getattr(coarse, "chance_inliers", -1)), consistency=float(vis.consistency),
        seen_by_both=vis.seen_by_both, violations=vis.violations, residual_m=residual, noise_m=noise,
        chosen=hyp.chosen if hyp is not None else "coarse", rival=hyp.runner_up if hyp is not None else "",
        margin=float(hyp.margin) if hyp is not None else float("nan"), tilt_deg=tilt, height_difference_m=dh,
        chosen_by_hand=bool(hyp is not None and hyp.chosen_by_hand),
    )


def judge(e: Evidence, *, verify: VerifyParams, coarse: CoarseParams) -> tuple[str, tuple[str, ...], str]:
    """The verdict from the evidence: (verdict, reasons it is not verified, what to try)."""
    p = verify
    reasons: list[str] = []
    hints: list[str] = []
    if e.chance_inliers >= 0 and e.inliers < max(coarse.min_ties, p.chance_factor * e.chance_inliers):
        reasons.append(f"only {e.inliers} of {e.ties} tie points agree with the coarse transform, against "
                       f"{e.chance_inliers} when the ties are re-paired at random (verify.chance_factor = {p.chance_factor:g})")
        hints.append("check that both scans show the same tree")
    if not e.seen_by_both >= p.min_seen:
        reasons.append(f"only {e.seen_by_both} of the target's points lie where both stations could see them "
                       f"(verify.min_seen = {p.min_seen}): too little overlap to judge")
        hints.append("add a station between these two")
    elif not e.consistency >= p.min_consistency:
        reasons.append(f"{1 - e.consistency:.1%} of the points both stations see lie in space the reference saw "
                       f"through (consistency {e.consistency:.3f} < verify.min_consistency = {p.min_consistency:g})")
        hints.append("check that both scans show the same tree, or pick another hypothesis in the app")
    # A hypothesis picked by hand settles the ambiguity: the person looked at both.
    if np.isfinite(e.margin) and e.margin < p.min_margin and not e.chosen_by_hand:
        reasons.append(f"another hypothesis ({e.rival}) explains the scans almost as well (consistency margin "
                       f"{e.margin:.3f} < verify.min_margin = {p.min_margin:g}): the heading is ambiguous")
        hints.append("compare the competing poses in the app (treereg view) and pick one, or add a station")
    if np.isfinite(e.noise_m) and e.noise_m > 0 and not e.residual_m <= p.max_residual_factor * e.noise_m:
        what = "do not pair up" if not np.isfinite(e.residual_m) else f"lie {e.residual_m * 1000:.1f} mm apart"
        reasons.append(f"the two surfaces {what}, more than {p.max_residual_factor:g} times the scans' own noise "
                       f"({e.noise_m * 1000:.1f} mm)")
    if e.tilt_deg > p.max_tilt_deg:
        reasons.append(f"the transform tilts the scanner by {e.tilt_deg:.1f}° (verify.max_tilt_deg = {p.max_tilt_deg:g}); "
                       "scanners stand nearly level")
    if e.height_difference_m is not None and abs(e.height_difference_m) > p.max_height_difference_m:
        reasons.append(f"the target's scanner would stand {abs(e.height_difference_m):.2f} m "
                       f"{'higher' if e.height_difference_m > 0 else 'lower'} above the ground than its own scan shows")
    verdict = VERIFIED if not reasons else UNVERIFIED
    hint = "; ".join(dict.fromkeys(hints)) or ("try --keep-unverified to use the best guess anyway" if reasons else "")
    return verdict, tuple(reasons), hint


def verification(T: np.ndarray, e: Evidence, verdict: str, reasons: tuple[str, ...], hint: str) -> PairVerification:
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
    )
    return PairVerification(True, "; ".join(reasons), metrics, np.asarray(T, dtype=float), verdict, reasons, hint, e)
