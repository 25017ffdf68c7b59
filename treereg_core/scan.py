"""The `Scan`: one station's points in its own scanner frame, with its angular grid.

A scan is immutable: points (N x 3 float64, metres, scanner at the origin, z up), a name, the
file it came from, and the instrument's angular steps phi (horizontal) and varphi (vertical) in
degrees. Azimuth alpha and elevation beta are computed once, when the scan is made.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .prepare.angular_step import estimate_angular_step
from .errors import ScanError
from .params import ANGULAR_STEP_RANGE_DEG

#: Fewer points than this cannot be registered meaningfully (and cannot estimate a grid).
MIN_POINTS = 100


def spherical_angles_deg(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth alpha in (-180, 180] and elevation beta in [-90, 90], degrees (paper Fig. 2)."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    alpha = np.degrees(np.arctan2(y, x))
    beta = np.degrees(np.arctan2(z, np.hypot(x, y)))
    return alpha, beta


@dataclass(frozen=True, eq=False)
class Scan:
    """One TLS station. Build with `Scan.from_points` (validates, estimates the steps if needed)."""

    points: np.ndarray
    name: str
    angular_step_deg: tuple[float, float]
    source: Path | None = None
    step_estimated: bool = False
    azimuth_deg: np.ndarray = field(init=False, repr=False)
    elevation_deg: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        pts = np.ascontiguousarray(self.points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ScanError(self.label, f"points must be an N x 3 array, got shape {pts.shape}")
        if not np.isfinite(pts).all():
            raise ScanError(self.label, "points contain NaN or infinite values")
        pts.setflags(write=False)
        alpha, beta = spherical_angles_deg(pts)
        alpha.setflags(write=False)
        beta.setflags(write=False)
        object.__setattr__(self, "points", pts)
        object.__setattr__(self, "azimuth_deg", alpha)
        object.__setattr__(self, "elevation_deg", beta)
        h, v = (float(s) for s in self.angular_step_deg)
        lo, hi = ANGULAR_STEP_RANGE_DEG
        if not (lo <= h <= hi and lo <= v <= hi):
            raise ScanError(self.label, f"angular steps {h:g} x {v:g} deg are outside the allowed range "
                                        f"({lo:g} to {hi:g} deg)")
        object.__setattr__(self, "angular_step_deg", (h, v))

    @property
    def label(self) -> str:
        """What messages call this scan: its file when it has one, else its name."""
        return str(self.source) if self.source is not None else self.name

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])

    @classmethod
    def from_points(
        cls,
        points: np.ndarray,
        name: str,
        source: Path | str | None = None,
        angular_step_deg: tuple[float, float] | None = None,
        min_points: int = MIN_POINTS,
    ) -> "Scan":
        """Validate `points` and make a scan; estimate the angular steps when not given."""
        src = Path(source) if source is not None else None
        label = str(src) if src is not None else name
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ScanError(label, f"points must be an N x 3 array, got shape {pts.shape}")
        if pts.shape[0] < min_points:
            raise ScanError(
                label, f"only {pts.shape[0]} points; at least {min_points} are needed to register a scan"
            )
        estimated = angular_step_deg is None
        if estimated:
            alpha, beta = spherical_angles_deg(pts)
            try:
                angular_step_deg = estimate_angular_step(alpha, beta)
            except ValueError as e:
                raise ScanError(label, f"cannot estimate the angular step: {e}; give it with --angular-step "
                                       "(the instrument's steps in degrees)") from None
            lo, hi = ANGULAR_STEP_RANGE_DEG
            if not all(lo <= float(s) <= hi for s in angular_step_deg):
                # Points not on a scanner's grid (a cloud merged from several stations, a resampled or
                # georeferenced file) give absurd steps: say so rather than compute with them.
                h, v = (float(s) for s in angular_step_deg)
                raise ScanError(label, f"the angular step estimated from the points, {h:.2g} x {v:.2g} deg, is "
                                       f"outside {lo:g} to {hi:g} deg, so the points do not look like one "
                                       "station's scan in its own frame; give the instrument's steps with "
                                       "--angular-step")
        return cls(
            points=pts,
            name=name,
            angular_step_deg=tuple(angular_step_deg),  # type: ignore[arg-type]
            source=src,
            step_estimated=estimated,
        )

    def with_angular_step(self, angular_step_deg: tuple[float, float]) -> "Scan":
        """The same station with the instrument's steps given (not estimated)."""
        return Scan(points=self.points, name=self.name, angular_step_deg=tuple(angular_step_deg),  # type: ignore[arg-type]
                    source=self.source, step_estimated=False)

    def with_points(self, points: np.ndarray, name: str | None = None) -> "Scan":
        """The same station (steps, source) with other points, e.g. after cropping or ground removal."""
        return Scan(
            points=points,
            name=name or self.name,
            angular_step_deg=self.angular_step_deg,
            source=self.source,
            step_estimated=self.step_estimated,
        )
