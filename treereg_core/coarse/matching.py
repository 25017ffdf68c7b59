"""Matching a target's image sequence against the reference's (paper 2.1.3-2.1.4 and 4.1).

The similarity matrix of the two sequences, the most similar image pairs, ORB matches on each, the
beta check (4.1), and 3-D tie points (the centroid of each matched pixel's points, 2.1.4).

ORB runs once per image, not once per pair: keypoints of a sequence's images are cached with the
sequence (weakly, they go when the sequence goes), so a reference matched against several targets
is described once.
"""

from __future__ import annotations

import threading
import time
import weakref
from dataclasses import dataclass, replace

import numpy as np

from .. import parallel
from ..params import MatchingParams, set_flag
from ..results import Metric, Progress, no_progress
from ..scan import Scan
from . import features, similarity
from .features import ImageFeatures
from .sequences import ImageSequence
from .tiepoints import pixel_centroids

#: Fewest tie points for which a transform is attempted at all.
MIN_TIES_ANY = 3

_FEATURE_FIELDS = ("image_mode", "ramp_px", "orb_nfeatures", "orb_edge_threshold", "orb_patch_size",
                   "orb_fast_threshold", "snap_px")
_feature_cache: "weakref.WeakKeyDictionary[ImageSequence, dict]" = weakref.WeakKeyDictionary()
_feature_lock = threading.Lock()


class _Pending:
    """An image's features while one thread computes them (the others wait for them)."""

    def __init__(self) -> None:
        self.done = threading.Event()
        self.value: ImageFeatures | None = None


def sequence_features(seq: ImageSequence, index: int, p: MatchingParams) -> ImageFeatures:
    """ORB features of image `index` of `seq`, computed once per (sequence, image, feature parameters):
    pairs matched side by side that need the same image wait for the thread computing it."""
    key = (index,) + tuple(getattr(p, f) for f in _FEATURE_FIELDS)
    with _feature_lock:
        per = _feature_cache.setdefault(seq, {})
        found = per.get(key)
        if found is None:
            per[key] = mine = _Pending()
    if isinstance(found, _Pending):
        found.done.wait()
        if found.value is not None:
            return found.value
        return sequence_features(seq, index, p)  # its thread failed: try here
    if found is not None:
        return found
    try:
        mine.value = features.detect(seq.images[index], p)  # outside the lock: the slow part
    finally:
        with _feature_lock:
            if mine.value is None:
                per.pop(key, None)
            else:
                per[key] = mine.value
        mine.done.set()
    return mine.value


@dataclass(frozen=True, eq=False, kw_only=True)
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


@dataclass(frozen=True, eq=False, kw_only=True)
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


def _fail_match(message: str, sim: np.ndarray, measure: str, pairs: tuple[PairMatches, ...],
                metrics: tuple[Metric, ...], t0: float) -> MatchResult:
    z3 = np.zeros((0, 3))
    zi = np.zeros(0, dtype=np.int64)
    return MatchResult(ok=False, message=message, metrics=metrics, similarity=sim, measure=measure, pairs=pairs,
                       ref_xyz=z3, tgt_xyz=z3, tie_pair=zi, tie_match=zi, seconds=time.perf_counter() - t0)


def match_sequences(
    seq_ref: ImageSequence, seq_tgt: ImageSequence, ref: Scan, tgt: Scan, *, matching: MatchingParams,
    progress: Progress | None = None,
) -> MatchResult:
    """Similar image pairs, ORB matches, beta check and tie points of a target against the reference.

    Parameters
    ----------
    seq_ref, seq_tgt : image sequences built from `ref` and `tgt` (the same prepared scans).
    ref, tgt : the prepared scans whose points the sequences' labels index.
    matching : matching parameters.
    progress : optional callback.

    Returns
    -------
    MatchResult (ok False, with a message, when fewer than 3 tie points come out).
    """
    p = matching
    progress = progress or no_progress
    t0 = time.perf_counter()
    sim = similarity.similarity_matrix(seq_ref, seq_tgt, p.similarity)
    chosen = similarity.most_similar_pairs(sim, p.n_pairs)
    progress(0.0, f"ORB on {len(chosen)} image pairs")
    # ORB releases the GIL: the images' features side by side on the run's free threads.
    found = parallel.map(lambda ij: (sequence_features(seq_ref, ij[0], p), sequence_features(seq_tgt, ij[1], p)),
                         list(chosen))
    pairs: list[PairMatches] = []
    for (i, j), (fa, fb) in zip(chosen, found):
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
    return MatchResult(ok=True, message="", metrics=metrics, similarity=sim, measure=p.similarity, pairs=tuple(pairs),
                       ref_xyz=ref_xyz, tgt_xyz=tgt_xyz, tie_pair=np.concatenate(tie_pair),
                       tie_match=np.concatenate(tie_match), seconds=time.perf_counter() - t0)


def match_hints(p: MatchingParams) -> str:
    """What a user can change when there are too few tie points, given the current settings: each
    names its parameter and the `--set` that changes it."""
    hints = []
    if p.n_pairs < 15:
        hints.append(f"more image pairs (matching.n_pairs {p.n_pairs} -> 15: {set_flag('matching.n_pairs', 15)})")
    if p.matches_per_pair < 60:
        hints.append(f"more matches per pair (matching.matches_per_pair {p.matches_per_pair} -> 60: "
                     f"{set_flag('matching.matches_per_pair', 60)})")
    if p.image_mode == "binary":
        hints.append(f"ramp images ({set_flag('matching.image_mode', 'ramp')})")
    if p.beta_check:
        hints.append(f"the beta check off ({set_flag('matching.beta_check', False)})")
    hints.append(f"a smaller projection.theta_deg (e.g. {set_flag('projection.theta_deg', 5.0)})")
    return ", ".join(hints)


def _with_kept(pm: PairMatches, kept: np.ndarray) -> PairMatches:
    return replace(pm, kept=kept)
