"""ORB keypoints and Hamming matching on projection images (2.1.3), and the beta check (4.1).

The only module of treereg_core that imports OpenCV.

A bare binary image has hardly any texture: FAST corners sit on the staircase edges of the pixel
grid and BRIEF descriptors of two such patches look alike. Option ``image_mode="ramp"`` gives ORB a
grey image instead: the distance of each pixel to the nearest occupied pixel, capped at `ramp_px`
and scaled to 0..255 (occupied pixels stay 0). The ramp keeps the shape and gives the descriptor
gradients to sample.

A keypoint is often placed on an empty pixel next to a branch; such a pixel has no points and can
not give a tie point. With `snap_px` > 0 it is moved to the nearest occupied pixel within that
radius; with 0 (the default: on sparse scans snapping moved keypoints onto the wrong branch and
made results worse) only keypoints on occupied pixels are kept. Unusable keypoints are dropped
before matching.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..params import MatchingParams
from .projection import EMPTY, OCCUPIED


@dataclass(frozen=True, eq=False)
class ImageFeatures:
    """ORB keypoints of one image that lie on (or were snapped to) an occupied pixel.

    Attributes
    ----------
    xy : (K, 2) float32 keypoint position (x = column, y = row) where ORB found it, pixels.
    pixel_rc : (K, 2) int32 (row, col) of the occupied pixel the keypoint stands for.
    descriptors : (K, 32) uint8 ORB descriptors.
    n_detected : keypoints ORB found before snapping.
    """

    xy: np.ndarray
    pixel_rc: np.ndarray
    descriptors: np.ndarray
    n_detected: int

    def __len__(self) -> int:
        return int(self.xy.shape[0])


def orb_input(image: np.ndarray, mode: str, ramp_px: float) -> np.ndarray:
    """The grey image ORB sees: the binary image itself, or the capped distance ramp."""
    if mode == "binary":
        return image
    if mode == "ramp":
        # distanceTransform measures, for every non-zero (empty) pixel, the distance to the nearest
        # zero (occupied) pixel: exactly the ramp we want.
        dist = cv2.distanceTransform(image, cv2.DIST_L2, cv2.DIST_MASK_5)
        return (np.minimum(dist, ramp_px) * (255.0 / ramp_px)).astype(np.uint8)
    raise ValueError(f"unknown image mode {mode!r}; choose 'binary' or 'ramp'")


def _snap_offsets(radius: int) -> np.ndarray:
    """(O, 2) integer (drow, dcol) offsets within `radius`, nearest first."""
    r = np.arange(-radius, radius + 1)
    dr, dc = np.meshgrid(r, r, indexing="ij")
    off = np.stack([dr.ravel(), dc.ravel()], axis=1)
    d2 = (off ** 2).sum(axis=1)
    keep = d2 <= radius * radius
    order = np.argsort(d2[keep], kind="stable")
    return off[keep][order]


def snap_to_occupied(image: np.ndarray, xy: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Nearest occupied pixel (row, col) within `radius` of each keypoint, and which keypoints have one."""
    rows, cols = image.shape
    base = np.stack([np.rint(xy[:, 1]), np.rint(xy[:, 0])], axis=1).astype(np.int64)
    off = _snap_offsets(max(int(radius), 0))
    cand = base[:, None, :] + off[None, :, :]                          # (K, O, 2)
    inside = (cand[..., 0] >= 0) & (cand[..., 0] < rows) & (cand[..., 1] >= 0) & (cand[..., 1] < cols)
    rr = np.clip(cand[..., 0], 0, rows - 1)
    cc = np.clip(cand[..., 1], 0, cols - 1)
    occ = inside & (image[rr, cc] == OCCUPIED)
    found = occ.any(axis=1)
    first = occ.argmax(axis=1)                                          # nearest, offsets are sorted
    k = np.arange(len(base))
    rc = np.stack([rr[k, first], cc[k, first]], axis=1).astype(np.int32)
    return rc, found


def _orb(p: MatchingParams) -> cv2.ORB:
    return cv2.ORB_create(
        nfeatures=int(p.orb_nfeatures),
        edgeThreshold=int(p.orb_edge_threshold),
        patchSize=int(p.orb_patch_size),
        fastThreshold=int(p.orb_fast_threshold),
    )


def detect(image: np.ndarray, p: MatchingParams) -> ImageFeatures:
    """ORB keypoints and descriptors of one binary projection image (0 occupied, 255 empty).

    The image is padded with empty pixels before detection so that ORB's edge threshold does not
    blind it to branches near the image border; positions are reported in the unpadded image.
    """
    pad = int(max(p.orb_edge_threshold, p.orb_patch_size // 2 + 1))
    padded = cv2.copyMakeBorder(image, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=EMPTY)
    grey = orb_input(padded, p.image_mode, p.ramp_px)
    kps, desc = _orb(p).detectAndCompute(grey, None)
    n = len(kps)
    if n == 0 or desc is None:
        return ImageFeatures(np.zeros((0, 2), np.float32), np.zeros((0, 2), np.int32),
                             np.zeros((0, 32), np.uint8), n)
    xy = np.array([k.pt for k in kps], dtype=np.float32) - pad
    rc, found = snap_to_occupied(image, xy, p.snap_px)
    return ImageFeatures(xy[found], rc[found], desc[found], n)


def match(fa: ImageFeatures, fb: ImageFeatures, n_best: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cross-checked Hamming matches between two feature sets, the `n_best` smallest distances first.

    Returns
    -------
    (ia, ib, hamming): indices into `fa` and `fb`, and the Hamming distance of each match.
    """
    if len(fa) == 0 or len(fb) == 0:
        z = np.zeros(0, dtype=np.int64)
        return z, z, z.astype(np.float32)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
    ms = bf.match(fa.descriptors, fb.descriptors)
    if not ms:
        z = np.zeros(0, dtype=np.int64)
        return z, z, z.astype(np.float32)
    arr = np.array([(m.queryIdx, m.trainIdx, m.distance) for m in ms], dtype=np.float64)
    order = np.argsort(arr[:, 2], kind="stable")[: max(int(n_best), 0)]
    arr = arr[order]
    return arr[:, 0].astype(np.int64), arr[:, 1].astype(np.int64), arr[:, 2].astype(np.float32)


def beta_check(beta_ref_deg: np.ndarray, beta_tgt_deg: np.ndarray) -> np.ndarray:
    """Paper 4.1: keep matches whose d = |beta1 - beta2| lies within (mean(d) - sd(d), mean(d) + sd(d)).

    With all d equal (sd = 0) every match is kept: there is nothing to tell good from bad.
    """
    d = np.abs(np.asarray(beta_ref_deg, dtype=float) - np.asarray(beta_tgt_deg, dtype=float))
    if d.size == 0:
        return np.zeros(0, dtype=bool)
    m, s = d.mean(), d.std()
    if s == 0:
        return np.ones(d.size, dtype=bool)
    return (d > m - s) & (d < m + s)
