"""Image sequences: the scan rotated about its vertical centre axis, one projection per rotation (2.1.2).

The points are rotated by theta steps about the vertical axis through (x_mean, y_mean, 0), which is
the same as walking the scanner around the tree; each rotated copy is projected (projection.py).
The paper's sequence spans [-360/n, +360/n] for n scans, theta = 10 deg.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..limits import check_raster
from ..params import ProjectionParams
from .projection import Projection, gap_fill_px, limit_pixel_size, pixel_size_deg, project
from ..prepare.image_check import fill_rate, image_warning, stripe_fraction
from ..geometry.rigid import make_transform, rotation_z
from ..results import Metric
from ..scan import Scan

#: Points used to size the images of a sequence (the extent of a few thousand points is enough).
_SIZING_SAMPLE = 4000


@dataclass(frozen=True, eq=False, kw_only=True)
class ImageSequence:
    """The projection images of one scan rotated about its centre.

    Attributes
    ----------
    angles_deg : rotation of the points (about +z through `centre_xy`) for each image.
    projections : one Projection per angle: image, per-point flat pixel labels, geometry. Labels
        index the points of the scan the sequence was built from (`points_of_pixel` gives them back);
        a pixel's alpha interval is an azimuth of the points *as rotated* for that image.
    centre_xy : (x_mean, y_mean) of the scan's points, metres: the rotation axis.
    azimuth_ref_deg : azimuth that alpha is measured from (the centre's azimuth; 0 = absolute alpha).
    pixel_deg : (d_alpha, d_beta) pixel size of every image, degrees.
    scan_name : the scan the sequence was made from.
    """

    angles_deg: tuple[float, ...]
    projections: tuple[Projection, ...]
    centre_xy: tuple[float, float]
    azimuth_ref_deg: float
    pixel_deg: tuple[float, float]
    scan_name: str

    @property
    def images(self) -> tuple[np.ndarray, ...]:
        """The binary images (uint8, 0 = occupied, 255 = empty), one per angle."""
        return tuple(p.image for p in self.projections)

    def __len__(self) -> int:
        return len(self.angles_deg)

    def rotation(self, k: int) -> np.ndarray:
        """The 4x4 rigid motion of image k's points: about +z through (x_mean, y_mean, 0) by
        `angles_deg[k]` (what the app poses the rotated cloud by)."""
        R = rotation_z(self.angles_deg[k])
        c = np.array([self.centre_xy[0], self.centre_xy[1], 0.0])
        return make_transform(R, c - R @ c)

    @property
    def ok(self) -> bool:
        """A sequence always exists once built (an empty scan is refused by `build_sequence`)."""
        return True

    @property
    def message(self) -> str:
        """A warning when the image of the scan as taken is striped or mostly empty, else ""."""
        return image_warning(self.projections[len(self) // 2].image == 0)

    @property
    def metrics(self) -> tuple[Metric, ...]:
        shapes = np.array([p.shape for p in self.projections])
        occ = self.projections[len(self) // 2].image == 0  # the scan as taken (rotation 0)
        gx, gy = stripe_fraction(occ)
        rows = [
            Metric("images", "", len(self)),
            Metric("rotation step", "deg", float(np.diff(self.angles_deg).mean()) if len(self) > 1 else 0.0),
            Metric("pixel size", "deg", f"{self.pixel_deg[0]:.3g} x {self.pixel_deg[1]:.3g}"),
            Metric("largest image", "px", f"{shapes[:, 1].max()} x {shapes[:, 0].max()}"),
            Metric("fill rate", "", round(fill_rate(occ), 3)),
            Metric("single-pixel gaps (x, y)", "", f"{gx:.0%}, {gy:.0%}"),
        ]
        if self.message:
            rows.append(Metric("warning", "", self.message))
        return tuple(rows)


def sequence_angles_deg(theta_deg: float, span_deg: float) -> np.ndarray:
    """Rotations -span .. +span in steps of theta, always including 0 (the scan as it was taken)."""
    k = int(np.floor(span_deg / theta_deg + 1e-9))
    return np.arange(-k, k + 1) * float(theta_deg)


def rotated_angles_deg(
    points: np.ndarray, centre_xy: np.ndarray, angle_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """(alpha, beta) in degrees of `points` rotated by `angle_deg` about the vertical axis through the centre.

    float32 arithmetic: the angles only need to be good to a small fraction of a pixel (~0.01 deg).
    """
    c, s = np.float32(np.cos(np.radians(angle_deg))), np.float32(np.sin(np.radians(angle_deg)))
    cx, cy = np.float32(centre_xy[0]), np.float32(centre_xy[1])
    dx = points[:, 0] - cx
    dy = points[:, 1] - cy
    x = c * dx - s * dy + cx
    y = s * dx + c * dy + cy
    alpha = np.arctan2(y, x)
    alpha *= np.float32(180.0 / np.pi)
    beta = np.arctan2(points[:, 2], np.hypot(x, y))
    beta *= np.float32(180.0 / np.pi)
    return alpha, beta


def build_sequence(scan: Scan, *, projection: ProjectionParams, n_scans: int) -> ImageSequence:
    """Rotate `scan` about its centre axis and project each rotation (paper 2.1.2).

    Parameters
    ----------
    scan : the (prepared) scan.
    projection : projection parameters (pixel factor k, borders, theta, span, relative azimuth, size cap).
    n_scans : number of scans registered together; the span is 360 / n_scans unless `p.span_deg`,
        and at least `p.min_span_deg`.

    Returns
    -------
    ImageSequence; the pixel size is the same for every image of the sequence.
    """
    p = projection
    if scan.n_points == 0:
        raise ValueError(f"{scan.label}: no points left to project")
    centre = scan.points[:, :2].mean(axis=0)
    span = p.span_deg if p.span_deg is not None else 360.0 / max(int(n_scans), 1)
    span = max(span, p.min_span_deg)
    angles = sequence_angles_deg(p.theta_deg, span)
    # The centre's azimuth does not change under rotation about the centre: one reference for all
    # images. Turning the whole scan by -az_ref about the scanner first puts the centre on +x, so
    # arctan2 gives the relative azimuth directly, already in (-180, 180]: no wrapping per image.
    az_ref = float(np.degrees(np.arctan2(centre[1], centre[0]))) if p.relative_azimuth else 0.0
    pts = scan.points.astype(np.float32)
    if az_ref != 0.0:
        R = rotation_z(-az_ref)[:2, :2].astype(np.float32)
        pts = np.column_stack([pts[:, :2] @ R.T, pts[:, 2]])
    centre_rel = (rotation_z(-az_ref)[:2, :2] @ centre).astype(np.float32)
    pixel = pixel_size_deg(scan.angular_step_deg, p.pixel_factor, p.square_pixels)
    sample = pts[:: max(1, scan.n_points // _SIZING_SAMPLE)]
    spans = np.zeros(2)
    for a in angles:  # a few thousand points per angle: cheap
        al, be = rotated_angles_deg(sample, centre_rel, a)
        spans = np.maximum(spans, [np.ptp(al), np.ptp(be)])
    spans *= 1.05  # 5% margin: the sample can miss the extreme points.
    if p.max_image_px is not None:
        pixel = limit_pixel_size(spans[0], spans[1], pixel, p.max_image_px)
    # The sequence keeps every image: refuse sizes that cannot fit before allocating any.
    check_raster(f"{scan.label}: the projection images",
                 spans[1] / pixel[1] + 1 + 2 * p.border_px[1], spans[0] / pixel[0] + 1 + 2 * p.border_px[0], 1.0,
                 "cap the image size (projection.max_image_px, e.g. 700), or use a larger pixel factor "
                 "(projection.pixel_factor), fewer rotations (a larger projection.theta_deg) or a coarser angular step", count=len(angles))
    fill = gap_fill_px(scan.angular_step_deg, pixel)
    projections = []
    for a in angles:
        al, be = rotated_angles_deg(pts, centre_rel, a)
        projections.append(project(al, be, pixel, p.border_px, None, fill))
    # Record the reference azimuth in each image's geometry (project() saw relative angles).
    projections = [replace(pr, geometry=replace(pr.geometry, azimuth_ref_deg=az_ref)) for pr in projections]
    return ImageSequence(
        angles_deg=tuple(float(a) for a in angles),
        projections=tuple(projections),
        centre_xy=(float(centre[0]), float(centre[1])),
        azimuth_ref_deg=az_ref,
        pixel_deg=pixel,
        scan_name=scan.name,
    )
