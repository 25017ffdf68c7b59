"""Spherical projection of a scan into a binary image (paper 2.1.1, eq. 2-3).

Every point has an azimuth alpha and an elevation beta seen from the scanner at the origin. A pixel
covers k*phi x k*varphi degrees (k = 2 in the paper); the image is the bounding box of all (alpha,
beta) plus a border of r1, r2 pixels. Pixels holding points are 0, empty pixels 255, as in the paper.

Image layout follows eq. 3 literally: column x grows with alpha, row y grows with beta, so row 0 is
the *lowest* elevation and the tree appears upside down and mirrored in a plain image viewer
(display with `origin="lower"` and a flipped x axis, or `image[::-1, ::-1]`).

Azimuth wrap: alpha lives in (-180, 180]. A tree straddling the -x axis would otherwise become an
image 360 degrees wide. With `azimuth_ref_deg` set (the azimuth of the scan's centroid), alpha is
measured relative to it and wrapped into [-180, 180), so the tree sits in the middle.

Each point keeps its flat pixel index (`labels`), which gives any pixel's points back.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Value of a pixel with points / without points (paper 2.1.1).
OCCUPIED: int = 0
EMPTY: int = 255


def wrap_deg(angle_deg: np.ndarray | float) -> np.ndarray | float:
    """Wrap degrees into [-180, 180)."""
    return (np.asarray(angle_deg) + 180.0) % 360.0 - 180.0


def spherical_deg(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth alpha and elevation beta (degrees) of points seen from the origin (paper Fig. 2)."""
    alpha = np.degrees(np.arctan2(y, x))
    beta = np.degrees(np.arctan2(z, np.hypot(x, y)))
    return alpha, beta


@dataclass(frozen=True, kw_only=True)
class ProjectionGeometry:
    """Where the pixels of one image lie in (alpha, beta).

    Pixel (row, col) covers alpha in [alpha_min + (col - r1) * d_alpha, ... + d_alpha) and
    beta in [beta_min + (row - r2) * d_beta, ... + d_beta), alpha relative to `azimuth_ref_deg`.
    """

    alpha_min_deg: float
    beta_min_deg: float
    pixel_deg: tuple[float, float]
    border_px: tuple[int, int]
    shape: tuple[int, int]
    azimuth_ref_deg: float

    def alpha_interval_deg(self, col: np.ndarray | int) -> tuple[np.ndarray, np.ndarray]:
        """[alpha_l, alpha_h) of columns `col`, in the scan's absolute azimuth, wrapped."""
        lo = self.alpha_min_deg + (np.asarray(col) - self.border_px[0]) * self.pixel_deg[0]
        lo = wrap_deg(lo + self.azimuth_ref_deg)
        return lo, lo + self.pixel_deg[0]

    def beta_interval_deg(self, row: np.ndarray | int) -> tuple[np.ndarray, np.ndarray]:
        """[beta_l, beta_h) of rows `row`."""
        lo = self.beta_min_deg + (np.asarray(row) - self.border_px[1]) * self.pixel_deg[1]
        return lo, lo + self.pixel_deg[1]


@dataclass(frozen=True, eq=False, kw_only=True)
class Projection:
    """One binary image with its pixel -> points index.

    Attributes
    ----------
    image : uint8 (rows, cols); 0 where the pixel holds points, 255 where it is empty.
    labels : int32 (N,); flat pixel index (row * cols + col) of every point.
    geometry : ProjectionGeometry
    """

    image: np.ndarray
    labels: np.ndarray
    geometry: ProjectionGeometry

    @property
    def shape(self) -> tuple[int, int]:
        return self.geometry.shape

    def counts(self) -> np.ndarray:
        """Points per pixel, int64 (rows, cols) (computed on demand: sequences keep many images)."""
        return np.bincount(self.labels, minlength=self.image.size).reshape(self.shape)

    def points_of_pixel(self, row: int, col: int) -> np.ndarray:
        """Indices of the points that fall into pixel (row, col); empty for an empty pixel."""
        rows, cols = self.shape
        if not (0 <= row < rows and 0 <= col < cols):
            return np.zeros(0, dtype=np.int64)
        return np.flatnonzero(self.labels == row * cols + col)

    def pixel_index(self) -> tuple[np.ndarray, np.ndarray]:
        """CSR index of all pixels: points of flat pixel f are `order[offsets[f]:offsets[f + 1]]`."""
        order = np.argsort(self.labels, kind="stable")
        offsets = np.zeros(self.image.size + 1, dtype=np.int64)
        np.cumsum(self.counts().ravel(), out=offsets[1:])
        return order, offsets


def image_geometry(
    alpha_rel_deg: np.ndarray,
    beta_deg: np.ndarray,
    pixel_deg: tuple[float, float],
    border_px: tuple[int, int],
    azimuth_ref_deg: float,
) -> ProjectionGeometry:
    """Image extent of eq. 2: m = (alpha_max - alpha_min) / d_alpha + 2 r1 (likewise n), rounded up."""
    a0, a1 = float(alpha_rel_deg.min()), float(alpha_rel_deg.max())
    b0, b1 = float(beta_deg.min()), float(beta_deg.max())
    r1, r2 = int(border_px[0]), int(border_px[1])
    cols = int(np.floor((a1 - a0) / pixel_deg[0])) + 1 + 2 * r1
    rows = int(np.floor((b1 - b0) / pixel_deg[1])) + 1 + 2 * r2
    return ProjectionGeometry(alpha_min_deg=a0, beta_min_deg=b0, pixel_deg=(float(pixel_deg[0]), float(pixel_deg[1])),
                              border_px=(r1, r2), shape=(rows, cols), azimuth_ref_deg=float(azimuth_ref_deg))


#: Steps differing by more than this factor get square pixels (with `square`).
ANISOTROPY = 1.5


def pixel_size_deg(angular_step_deg: tuple[float, float], pixel_factor: int, square: bool = False) -> tuple[float, float]:
    """k*phi x k*varphi (paper: k = 2).

    With `square`, steps that differ a lot (a RIEGL scan of 0.622 x 0.048 deg) give square pixels of
    k times the finer step instead: k*phi x k*varphi would squash the scene 13:1 into vertical
    stripes. The gaps this leaves between scan lines along the coarser direction are closed by
    `project(fill_px=...)` (`gap_fill_px`).
    """
    phi, vphi = float(angular_step_deg[0]), float(angular_step_deg[1])
    if square and max(phi, vphi) > ANISOTROPY * min(phi, vphi):
        return (pixel_factor * min(phi, vphi),) * 2
    return (pixel_factor * phi, pixel_factor * vphi)


def gap_fill_px(angular_step_deg: tuple[float, float], pixel_deg: tuple[float, float]) -> tuple[int, int]:
    """Empty pixels that can lie between two scan lines along x and y (pixels finer than the step)."""
    return tuple(max(int(np.ceil(s / p - 1e-9)) - 1, 0) for s, p in zip(angular_step_deg, pixel_deg))  # type: ignore[return-value]


def limit_pixel_size(
    alpha_span_deg: float, beta_span_deg: float, pixel_deg: tuple[float, float], max_image_px: int
) -> tuple[float, float]:
    """Enlarge both pixel sides by one factor so the image is at most `max_image_px` on its long side.

    ORB cost grows with the image area; a fine instrument step (0.02 deg) on a tall tree would give
    images of many thousand pixels that carry no more structure than a 1000 px one.
    """
    longest = max(alpha_span_deg / pixel_deg[0], beta_span_deg / pixel_deg[1])
    if longest <= max_image_px:
        return pixel_deg
    f = longest / max_image_px
    return (pixel_deg[0] * f, pixel_deg[1] * f)


def project(
    alpha_deg: np.ndarray,
    beta_deg: np.ndarray,
    pixel_deg: tuple[float, float],
    border_px: tuple[int, int] = (10, 10),
    azimuth_ref_deg: float | None = None,
    fill_px: tuple[int, int] = (0, 0),
) -> Projection:
    """Project points given by their angles into one binary image (eq. 2-3).

    Parameters
    ----------
    alpha_deg, beta_deg : (N,) azimuth and elevation of the points, degrees.
    pixel_deg : (d_alpha, d_beta) pixel size, degrees (k*phi, k*varphi).
    border_px : (r1, r2) border in pixels.
    azimuth_ref_deg : measure alpha relative to this azimuth, wrapped into [-180, 180) (None: use
        alpha as it is, like the paper; a tree straddling +-180 deg then gives a very wide image).
    fill_px : close empty runs of up to this many pixels between occupied ones along x and y (the
        gaps between scan lines when pixels are finer than the step); filled pixels hold no points.

    Returns
    -------
    Projection with the image and the per-point flat pixel labels.
    """
    alpha = np.asarray(alpha_deg)
    beta = np.asarray(beta_deg)
    if alpha.size == 0:
        raise ValueError("cannot project an empty set of points")
    ref = 0.0 if azimuth_ref_deg is None else float(azimuth_ref_deg)
    rel = alpha if azimuth_ref_deg is None else wrap_deg(alpha - ref)
    geo = image_geometry(rel, beta, pixel_deg, border_px, ref)
    rows, cols = geo.shape
    # eq. 3, floored: the pixel whose [l, h) interval holds the angle.
    x = ((rel - geo.alpha_min_deg) / geo.pixel_deg[0]).astype(np.int32) + geo.border_px[0]
    y = ((beta - geo.beta_min_deg) / geo.pixel_deg[1]).astype(np.int32) + geo.border_px[1]
    np.clip(x, 0, cols - 1, out=x)  # rounding at alpha_max can land one past the edge
    np.clip(y, 0, rows - 1, out=y)
    labels = (y * cols + x).astype(np.int32)
    image = np.full(rows * cols, EMPTY, dtype=np.uint8)
    image[labels] = OCCUPIED
    image = image.reshape(rows, cols)
    if any(fill_px):
        from scipy import ndimage

        occ = ndimage.binary_closing(image == OCCUPIED, structure=np.ones((2 * fill_px[1] + 1, 2 * fill_px[0] + 1)))
        image[occ] = OCCUPIED
    return Projection(image=image, labels=labels, geometry=geo)
