"""Coarse registration of one target scan onto the reference (paper 2.1): images -> ties -> transform.

Three stages, each returning a frozen result the app can draw:

1. `match_sequences`: similarity matrix of the two image sequences, the most similar image pairs,
   ORB matches on each, the beta check (4.1), and 3-D tie points (2.1.4);
2. `estimate_coarse`: the rigid transform from the tie points, by plain SVD over all ties (the paper)
   or RANSAC with 4 DOF (yaw + translation, levelled scanners) and an optional 6-DOF refit;
3. `register_coarse`: both scans prepared, both sequences built, then 1 and 2.

ORB runs once per image, not once per pair: keypoints of a sequence's images are cached with the
sequence (weakly, they go when the sequence goes), so a reference matched against several targets
is described once.
"""

from __future__ import annotations

import threading
import time
import weakref
from dataclasses import dataclass, fields

import numpy as np

from . import features, robust, similarity
from .features import ImageFeatures
from .ground import prepare_scan
from .params import CoarseParams, MatchingParams, Params
from .results import Metric, Progress, no_progress
from .rigid import rotation_angle_deg
from .scan import Scan
from .sequences import ImageSequence, build_sequence
from .tiepoints import pixel_centroids

#: Fewest tie points for which a transform is attempted at all.
MIN_TIES_ANY = 3

_FEATURE_FIELDS = ("image_mode", "ramp_px", "orb_nfeatures", "orb_edge_threshold", "orb_patch_size",
                   "orb_fast_threshold", "snap_px")
_feature_cache: "weakref.WeakKeyDictionary[ImageSequence, dict]" = weakref.WeakKeyDictionary()
_feature_lock = threading.Lock()


def sequence_features(seq: ImageSequence, index: int, p: MatchingParams) -> ImageFeatures:
    """ORB features of image `index` of `seq`, computed once per (sequence, image, feature parameters)."""
    key = (index,) + tuple(getattr(p, f) for f in _FEATURE_FIELDS)
    with _feature_lock:
        found = _feature_cache.get(seq, {}).get(key)
    if found is None:
        # Detect outside the lock (it is the slow part); two threads may both compute it: harmless.
        found = features.detect(seq.images[index], p)
        with _feature_lock:
            _feature_cache.setdefault(seq, {})[key] = found
    return found


@dataclass(frozen=True, eq=False)
class PairMatches:
    """ORB matches of one image pair (image i of the reference sequence, image j of the target's).

    Attributes
    ----------
    i, j : image indices; angle_ref_deg, angle_tgt_deg their rotations.
    similarity : the pair's entry of the similarity matrix.
    xy_ref, xy_tgt : (K, 2) matched keypoint positions (x = column, y = row) as ORB found them.
    rc_ref, rc_tgt : (K, 2) occupied pixel (row, col) each keypoint was snapped to.
    hamming : (K,) descriptor distances, smallest first.
    kept : (K,) False where the beta check (4.1) rejected the match.
    n_keypoints_ref, n_keypoints_tgt : usable keypoints of each image.
    """

    i: int
    j: int
    angle_ref_deg: float
    angle_tgt_deg: float
    similarity: float
    xy_ref: np.ndarray
    xy_tgt: np.ndarray
    rc_ref: np.ndarray
    rc_tgt: np.ndarray
    hamming: np.ndarray
    kept: np.ndarray
    n_keypoints_ref: int
    n_keypoints_tgt: int


@dataclass(frozen=True, eq=False)
class MatchResult:
    """Tie points of a target scan against the reference, with everything the app draws.

    Attributes
    ----------
    ok, message, metrics : as every stage result.
    similarity : (n_ref, n_tgt) similarity of every image pair (larger = more similar).
    measure : the similarity measure used.
    pairs : the chosen image pairs, most similar first, with their matches.
    ref_xyz, tgt_xyz : (N, 3) tie points, each in its own scan's frame.
    tie_pair : (N,) index into `pairs` of the pair each tie came from.
    tie_match : (N,) index of the tie's match within its pair.
    seconds : wall time of the stage.
    """

    ok: bool
    message: str
    metrics: tuple[Metric, ...]
    similarity: np.ndarray
    measure: str
    pairs: tuple[PairMatches, ...]
    ref_xyz: np.ndarray
    tgt_xyz: np.ndarray
    tie_pair: np.ndarray
    tie_match: np.ndarray
    seconds: float

    @property
    def n_ties(self) -> int:
        return int(len(self.ref_xyz))


@dataclass(frozen=True, eq=False)
class CoarseResult:
    """The coarse transform of a target onto the reference.

    Attributes
    ----------
    ok, message, metrics : as every stage result.
    T_ref_target : 4x4 mapping target points into the reference frame (identity when not ok).
    inliers : (N,) bool per tie point: agrees with the transform within the inlier distance.
    residuals_m : (N,) |T tgt - ref| per tie point, metres (NaN when no transform).
    n_ties, n_inliers : counts.
    match : the MatchResult the transform came from (None when called without one).
    seconds : wall time of the estimate (register_coarse: of everything).
    """

    ok: bool
    message: str
    metrics: tuple[Metric, ...]
    T_ref_target: np.ndarray
    inliers: np.ndarray
    residuals_m: np.ndarray
    n_ties: int
    n_inliers: int
    match: MatchResult | None = None
    seconds: float = 0.0


def _fail_match(message: str, sim: np.ndarray, measure: str, pairs: tuple[PairMatches, ...],
                metrics: tuple[Metric, ...], t0: float) -> MatchResult:
    z3 = np.zeros((0, 3))
    zi = np.zeros(0, dtype=np.int64)
    return MatchResult(False, message, metrics, sim, measure, pairs, z3, z3, zi, zi, time.perf_counter() - t0)


def match_sequences(
    seq_ref: ImageSequence, seq_tgt: ImageSequence, ref: Scan, tgt: Scan, p: MatchingParams,
    progress: Progress | None = None,
) -> MatchResult:
    """Similar image pairs, ORB matches, beta check and tie points of a target against the reference.

    Parameters
    ----------
    seq_ref, seq_tgt : image sequences built from `ref` and `tgt` (the same prepared scans).
    ref, tgt : the prepared scans whose points the sequences' labels index.
    p : matching parameters.
    progress : optional callback.

    Returns
    -------
    MatchResult (ok False, with a message, when fewer than 3 tie points come out).
    """
    progress = progress or no_progress
    t0 = time.perf_counter()
    sim = similarity.similarity_matrix(seq_ref, seq_tgt, p.similarity)
    chosen = similarity.most_similar_pairs(sim, p.n_pairs)
    pairs: list[PairMatches] = []
    for n, (i, j) in enumerate(chosen):
        progress(n / max(len(chosen), 1), f"ORB on image pair {n + 1} of {len(chosen)}")
        fa = sequence_features(seq_ref, i, p)
        fb = sequence_features(seq_tgt, j, p)
        ia, ib, ham = features.match(fa, fb, p.matches_per_pair)
        pairs.append(PairMatches(
            i=i, j=j, angle_ref_deg=seq_ref.angles_deg[i], angle_tgt_deg=seq_tgt.angles_deg[j],
            similarity=float(sim[i, j]), xy_ref=fa.xy[ia], xy_tgt=fb.xy[ib], rc_ref=fa.pixel_rc[ia],
            rc_tgt=fb.pixel_rc[ib], hamming=ham, kept=np.ones(len(ia), dtype=bool),
            n_keypoints_ref=len(fa), n_keypoints_tgt=len(fb),
        ))
    n_matches = sum(len(pm.hamming) for pm in pairs)
    if p.beta_check and n_matches:
        # 4.1: |beta1 - beta2| over all matches of all pairs, kept within mean +- sd.
        b_ref = np.concatenate([seq_ref.projections[pm.i].geometry.beta_interval_deg(pm.rc_ref[:, 0])[0]
                                for pm in pairs])
        b_tgt = np.concatenate([seq_tgt.projections[pm.j].geometry.beta_interval_deg(pm.rc_tgt[:, 0])[0]
                                for pm in pairs])
        keep = features.beta_check(b_ref, b_tgt)
        splits = np.cumsum([len(pm.hamming) for pm in pairs])[:-1]
        pairs = [_with_kept(pm, k) for pm, k in zip(pairs, np.split(keep, splits))]
    refs, tgts, tie_pair, tie_match = [], [], [], []
    for n, pm in enumerate(pairs):
        k = np.flatnonzero(pm.kept)
        if k.size == 0:
            continue
        a, ca = pixel_centroids(seq_ref.projections[pm.i], ref.points, pm.rc_ref[k])
        b, cb = pixel_centroids(seq_tgt.projections[pm.j], tgt.points, pm.rc_tgt[k])
        good = (ca > 0) & (cb > 0)
        refs.append(a[good])
        tgts.append(b[good])
        tie_pair.append(np.full(int(good.sum()), n))
        tie_match.append(k[good])
    n_kept = sum(int(pm.kept.sum()) for pm in pairs)
    ref_xyz = np.concatenate(refs) if refs else np.zeros((0, 3))
    tgt_xyz = np.concatenate(tgts) if tgts else np.zeros((0, 3))
    metrics = (
        Metric("similarity measure", "", p.similarity),
        Metric("image pairs matched", "", len(pairs)),
        Metric("matches", "", n_matches),
        Metric("matches after beta check", "", n_kept),
        Metric("tie points", "", len(ref_xyz)),
        Metric("best image similarity", "", float(sim.max()) if sim.size else float("nan")),
    )
    progress(1.0, "tie points ready")
    if len(ref_xyz) < MIN_TIES_ANY:
        what = f"{n_matches} ORB matches" + (f", {n_kept} after the beta check" if p.beta_check else "")
        return _fail_match(f"only {len(ref_xyz)} tie points ({what}); try {match_hints(p)}", sim,
                           p.similarity, tuple(pairs), metrics, t0)
    return MatchResult(True, "", metrics, sim, p.similarity, tuple(pairs), ref_xyz, tgt_xyz,
                       np.concatenate(tie_pair), np.concatenate(tie_match), time.perf_counter() - t0)


def match_hints(p: MatchingParams) -> str:
    """What a user can change when there are too few tie points, given the current settings."""
    hints = []
    if p.n_pairs < 15:
        hints.append(f"more image pairs (n_pairs {p.n_pairs} -> 15)")
    if p.matches_per_pair < 60:
        hints.append(f"more matches per pair ({p.matches_per_pair} -> 60)")
    if p.image_mode == "binary":
        hints.append("image_mode = ramp")
    if p.beta_check:
        hints.append("beta_check off")
    hints.append("a smaller theta (e.g. 5 deg)")
    return ", ".join(hints)


def _with_kept(pm: PairMatches, kept: np.ndarray) -> PairMatches:
    values = {f.name: getattr(pm, f.name) for f in fields(pm)}
    values["kept"] = kept
    return PairMatches(**values)


def _coarse_fail(message: str, match: MatchResult, metrics: tuple[Metric, ...], t0: float) -> CoarseResult:
    n = match.n_ties
    return CoarseResult(False, message, metrics, np.eye(4), np.zeros(n, dtype=bool), np.full(n, np.nan),
                        n, 0, match, time.perf_counter() - t0)


def estimate_coarse(match: MatchResult, p: CoarseParams) -> CoarseResult:
    """The coarse rigid transform from a MatchResult's tie points.

    `estimator="svd"` (paper): one least-squares fit over all ties (6 DOF, or 4 with `dof=4`).
    `estimator="ransac"`: RANSAC with `dof` degrees of freedom and inlier distance `inlier_m`, then
    (with `refit_6dof`) a full rigid least-squares refit on the inliers, which absorbs a small scanner
    tilt that the 4-DOF model cannot.
    """
    t0 = time.perf_counter()
    src, dst = match.tgt_xyz, match.ref_xyz
    n = len(src)
    if not match.ok:
        return _coarse_fail(match.message, match, (Metric("tie points", "", n),), t0)
    if n < p.min_ties:
        return _coarse_fail(
            f"only {n} tie points, at least {p.min_ties} are needed; use more image pairs or matches "
            "per pair, or a smaller theta (e.g. 5 deg)", match, (Metric("tie points", "", n),), t0)
    if p.estimator == "svd":
        if robust.is_degenerate(src, p.dof):
            return _coarse_fail(f"the {n} tie points lie on one line: the transform is undetermined; "
                                "use more image pairs", match, (Metric("tie points", "", n),), t0)
        T = robust.fit(src, dst, p.dof)
        res = robust.residuals(T, src, dst)
        inl = res < p.inlier_m
        how = f"SVD over all ties ({p.dof} DOF)"
    else:
        fit = robust.ransac(src, dst, p.dof, p.inlier_m, p.iterations, p.seed,
                            final_inlier_m=p.final_inlier_m, min_inliers=p.min_ties)
        if fit is None:
            return _coarse_fail(f"no usable sample among {n} tie points (all too close together); "
                                "use more image pairs or matches per pair", match,
                                (Metric("tie points", "", n),), t0)
        T, inl = fit.T, fit.inliers
        how = f"RANSAC {p.dof} DOF"
        if fit.n_inliers < p.min_ties:
            return _coarse_fail(
                f"only {fit.n_inliers} of {n} tie points agree on one transform (within {p.inlier_m:g} m), "
                f"at least {p.min_ties} are needed; try more image pairs, more matches per pair, "
                "removing the ground, or a larger inlier distance", match,
                (Metric("tie points", "", n), Metric("inliers", "", fit.n_inliers)), t0)
        if p.refit_6dof and p.dof == 4 and not robust.is_degenerate(src[inl], 6):
            T = robust.fit(src[inl], dst[inl], 6)
            how += " + 6-DOF refit"
        res = robust.residuals(T, src, dst)
    R = T[:3, :3]
    tilt = float(np.degrees(np.arccos(np.clip(R[2, 2], -1.0, 1.0))))
    yaw = float(np.degrees(np.arctan2(R[1, 0], R[0, 0])))
    n_in = int(inl.sum())
    metrics = (
        Metric("estimator", "", how),
        Metric("tie points", "", n),
        Metric("inliers", "", n_in),
        Metric("inlier ratio", "", n_in / n),
        Metric("inlier RMS residual", "m", float(np.sqrt(np.mean(res[inl] ** 2))) if n_in else float("nan")),
        Metric("yaw", "deg", yaw),
        Metric("tilt", "deg", tilt),
        Metric("rotation angle", "deg", rotation_angle_deg(R)),
    )
    problem = _implausible(n_in, n, tilt, p)
    # A failed check keeps its transform, so the app can show how wrong it is.
    return CoarseResult(not problem, problem, metrics, T, inl, res, n, n_in, match, time.perf_counter() - t0)


def _implausible(n_inliers: int, n_ties: int, tilt_deg: float, p: CoarseParams) -> str:
    """Why a computed transform cannot be trusted ('' when it can).

    Plain SVD (the paper) always returns a transform, even when wrong matches dominate and the scan
    comes out upside down: a result is only kept when enough ties agree with it, and when it leaves
    the scanner nearly level (TLS instruments level themselves).
    """
    fix = ("plain SVD has no defence against wrong matches: use estimator = ransac"
           if p.estimator == "svd" else
           "try more image pairs or matches per pair, or removing the ground")
    if n_inliers < p.min_ties:
        return (f"only {n_inliers} of {n_ties} tie points agree with the transform within {p.inlier_m:g} m "
                f"(at least {p.min_ties} needed), so it is unreliable; {fix}")
    if p.max_tilt_deg is not None and tilt_deg > p.max_tilt_deg:
        return (f"the transform tilts the scan by {tilt_deg:.1f} deg, but scanners stand nearly level "
                f"(max_tilt_deg = {p.max_tilt_deg:g}), so its tie points are wrong; {fix}")
    return ""


def register_coarse(ref: Scan, tgt: Scan, params: Params, n_scans: int,
                    progress: Progress | None = None) -> CoarseResult:
    """Coarse transform of `tgt` onto `ref`: prepare both, build both sequences, match, estimate.

    Parameters
    ----------
    ref, tgt : the reference and the target scan, as read.
    params : the whole parameter tree (its prepare, projection, matching and coarse sections are used).
    n_scans : number of scans registered together (sets the sequence span 360 / n).
    progress : optional callback.
    """
    progress = progress or no_progress
    t0 = time.perf_counter()
    prepared = []
    for k, s in enumerate((ref, tgt)):
        progress(0.1 * k, f"preparing {s.name}")
        ps = prepare_scan(s, params.prepare)
        if not ps.ok:
            dummy = MatchResult(False, ps.message, ps.metrics, np.zeros((0, 0)), params.matching.similarity, (),
                                np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0, np.int64), 0.0)
            return _coarse_fail(ps.message, dummy, ps.metrics, t0)
        prepared.append(ps.scan)
    seqs = []
    for k, s in enumerate(prepared):
        progress(0.2 + 0.2 * k, f"projecting {s.name}")
        seqs.append(build_sequence(s, params.projection, n_scans))

    def sub(f: float, text: str) -> None:
        progress(0.6 + 0.35 * f, text)

    m = match_sequences(seqs[0], seqs[1], prepared[0], prepared[1], params.matching, sub)
    result = estimate_coarse(m, params.coarse)
    progress(1.0, "coarse done")
    values = {f.name: getattr(result, f.name) for f in fields(result)}
    values["seconds"] = time.perf_counter() - t0
    return CoarseResult(**values)
