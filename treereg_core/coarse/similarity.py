"""How similar two projection images are, for every image pair of two sequences (2.1.3).

The paper picks "three pairs of similar images" without saying how similarity is measured. Two
stations 8 and 15 m from a tree see it at different angular sizes, and every image has its own
alpha_min, so images are compared after normalising each to the bounding box of its occupied pixels
and resampling it to a small thumbnail (area averaging: each thumbnail cell holds the occupied
fraction of the image pixels it covers). Measures on thumbnails:

- ``iou``: intersection over union of the binary thumbnails (cell occupied when any pixel is);
- ``ncc``: normalised cross-correlation of the occupancy fractions, lightly blurred;
- ``chamfer``: minus the symmetric mean distance (in thumbnail cells) from occupied cells of one
  thumbnail to the nearest occupied cell of the other.

All are computed for whole sequences at once by matrix products, so the full matrix is cheap and
kept for the app to plot.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .projection import OCCUPIED, wrap_deg
from .sequences import ImageSequence

#: Thumbnail rows x cols used for comparing images.
THUMB_SHAPE: tuple[int, int] = (48, 48)

MEASURES: tuple[str, ...] = ("iou", "ncc", "chamfer")


def thumbnail(image: np.ndarray, shape: tuple[int, int] = THUMB_SHAPE) -> np.ndarray:
    """Occupied fraction per cell of `image`'s occupied bounding box resampled to `shape` (float32)."""
    occ = image == OCCUPIED
    rows = np.flatnonzero(occ.any(axis=1))
    cols = np.flatnonzero(occ.any(axis=0))
    if rows.size == 0:
        return np.zeros(shape, dtype=np.float32)
    crop = occ[rows[0]: rows[-1] + 1, cols[0]: cols[-1] + 1].astype(np.float32)
    h, w = crop.shape
    th, tw = shape
    # Upsample tiny crops by repetition so every thumbnail cell gets at least one pixel.
    if h < th:
        crop = np.repeat(crop, -(-th // h), axis=0)
    if w < tw:
        crop = np.repeat(crop, -(-tw // w), axis=1)
    h, w = crop.shape
    re = np.linspace(0, h, th + 1).astype(np.int64)[:-1]
    ce = np.linspace(0, w, tw + 1).astype(np.int64)[:-1]
    sums = np.add.reduceat(np.add.reduceat(crop, re, axis=0), ce, axis=1)
    areas = np.outer(np.diff(np.r_[re, h]), np.diff(np.r_[ce, w]))
    return (sums / areas).astype(np.float32)


def thumbnails(seq: ImageSequence, shape: tuple[int, int] = THUMB_SHAPE) -> np.ndarray:
    """(n_images, rows * cols) thumbnails of a sequence."""
    return np.stack([thumbnail(im, shape).ravel() for im in seq.images])


def similarity_matrix(seq_ref: ImageSequence, seq_tgt: ImageSequence, measure: str = "iou") -> np.ndarray:
    """(n_ref, n_tgt) similarity of every image pair; larger is more similar.

    Parameters
    ----------
    seq_ref, seq_tgt : the two sequences.
    measure : "iou", "ncc" or "chamfer" (see the module doc).
    """
    a = thumbnails(seq_ref)
    b = thumbnails(seq_tgt)
    if measure == "iou":
        ab, bb = (a > 0).astype(np.float32), (b > 0).astype(np.float32)
        inter = ab @ bb.T
        union = ab.sum(1)[:, None] + bb.sum(1)[None, :] - inter
        return inter / np.maximum(union, 1.0)
    if measure == "ncc":
        def norm(t: np.ndarray) -> np.ndarray:
            t = ndimage.gaussian_filter1d(ndimage.gaussian_filter1d(
                t.reshape(-1, *THUMB_SHAPE), 1.0, axis=1), 1.0, axis=2).reshape(len(t), -1)
            t = t - t.mean(axis=1, keepdims=True)
            return t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-9)
        return norm(a) @ norm(b).T
    if measure == "chamfer":
        def dist(t: np.ndarray) -> np.ndarray:
            return np.stack([ndimage.distance_transform_edt(~r.reshape(THUMB_SHAPE)).ravel() for r in t])
        ao, bo = a > 0, b > 0
        da, db = dist(ao).astype(np.float32), dist(bo).astype(np.float32)
        af, bf = ao.astype(np.float32), bo.astype(np.float32)
        a_to_b = (af @ db.T) / np.maximum(af.sum(1), 1.0)[:, None]
        b_to_a = (da @ bf.T) / np.maximum(bf.sum(1), 1.0)[None, :]
        return -(a_to_b + b_to_a) / 2.0
    raise ValueError(f"unknown similarity measure {measure!r}; choose one of {MEASURES}")


def most_similar_pairs(sim: np.ndarray, n_pairs: int) -> list[tuple[int, int]]:
    """The `n_pairs` (i, j) with the largest similarity, best first."""
    flat = np.argsort(-sim, axis=None, kind="stable")[: max(int(n_pairs), 0)]
    return [(int(i), int(j)) for i, j in zip(*np.unravel_index(flat, sim.shape))]


def implied_yaw_deg(seq_ref: ImageSequence, seq_tgt: ImageSequence, i: int, j: int) -> float:
    """Yaw of the target onto the reference implied when image i of ref and image j of tgt show the same view.

    Both virtual viewpoints look at the tree from the same direction when
    yaw = az_ref(ref) - az_ref(tgt) + angle_j - angle_i, with az_ref the azimuth of each scan's centre
    (wrapped into [-180, 180)). Used to check pair selection against the truth and to diagnose.
    """
    az_r = np.degrees(np.arctan2(seq_ref.centre_xy[1], seq_ref.centre_xy[0]))
    az_t = np.degrees(np.arctan2(seq_tgt.centre_xy[1], seq_tgt.centre_xy[0]))
    return float(wrap_deg(az_r - az_t + seq_tgt.angles_deg[j] - seq_ref.angles_deg[i]))


def scan_similarity(seqs: list[ImageSequence], measure: str) -> np.ndarray:
    """(n, n) how alike every two scans look: the best similarity of any image pair of their sequences."""
    n = len(seqs)
    out = np.full((n, n), -np.inf)
    for i in range(n):
        for j in range(i + 1, n):
            out[i, j] = out[j, i] = float(similarity_matrix(seqs[i], seqs[j], measure).max())
    return out
