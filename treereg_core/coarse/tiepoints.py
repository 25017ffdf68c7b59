"""Matched pixels -> 3-D tie points (paper 2.1.4).

A pixel (row, col) of image k covers an interval of alpha and of beta of the *rotated* scan; the
tie point is the centroid of the scan's points in that cell, with the rotation undone. Rotation is
linear, so the centroid of the original points with that pixel label is already in the scan's own
frame: no point is rotated back.
"""

from __future__ import annotations

import numpy as np

from .projection import Projection


def pixel_centroids(proj: Projection, points: np.ndarray, rc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid of the points of each pixel (row, col) in `rc`, in the frame of `points`.

    Parameters
    ----------
    proj : the projection whose `labels` index `points`.
    points : (N, 3) the scan's points (unrotated, own frame).
    rc : (K, 2) integer pixel (row, col) per tie.

    Returns
    -------
    (xyz, count): (K, 3) centroids (NaN for an empty pixel) and (K,) number of points per pixel.
    """
    rc = np.asarray(rc, dtype=np.int64).reshape(-1, 2)
    k = rc.shape[0]
    if k == 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    cols = proj.shape[1]
    wanted = rc[:, 0] * cols + rc[:, 1]
    uniq, inv = np.unique(wanted, return_inverse=True)
    # Only the points of wanted pixels are summed: a lookup table over the image finds them without
    # a full-size bincount per coordinate.
    lut = np.full(proj.image.size, -1, dtype=np.int64)
    lut[uniq] = np.arange(uniq.size)
    pos = lut[proj.labels]
    hit = pos >= 0
    p = pos[hit]
    sel = points[hit]
    cnt = np.bincount(p, minlength=uniq.size)
    sums = np.stack([np.bincount(p, weights=sel[:, i], minlength=uniq.size) for i in range(3)], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cen = sums / cnt[:, None]
    cen[cnt == 0] = np.nan
    return cen[inv], cnt[inv]
