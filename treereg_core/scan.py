"""The `Scan`: one station's points in its own scanner frame, with its angular grid.

A scan is immutable: points (N x 3 float64, metres, scanner at the origin, z up), a name, the
file it came from, and the instrument's angular steps phi (horizontal) and varphi (vertical) in
degrees. Azimuth alpha and elevation beta are computed once, when first asked for: a station of
10 M points as read is only reduced to the working resolution, and never needs its own (160 MB).

`pose` (T_user_scan) is where the user's file puts the scan: the pose an E57 or PTX file carries,
or the shift from a scanner position the user gave for a georeferenced file. Registration works
in the scanner frame (where the angular grid is regular and coordinates are small enough for
float32); `io.transforms.registration_file` maps the transforms back through the poses.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from .prepare.angular_step import StepEstimate, estimate_steps, grid_steps
from .errors import ScanError
from .params import ANGULAR_STEP_RANGE_DEG
from .text import shown

#: Fewer points than this cannot be registered meaningfully (and cannot estimate a grid).
MIN_POINTS = 100


def spherical_angles_deg(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth alpha in (-180, 180] and elevation beta in [-90, 90], degrees (paper Fig. 2)."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    alpha = np.arctan2(y, x)
    np.degrees(alpha, out=alpha)
    rho = x * x  # sqrt(x^2 + y^2) in place: np.hypot is several times slower on millions of points
    rho += y * y
    np.sqrt(rho, out=rho)
    beta = np.arctan2(z, rho, out=rho)
    np.degrees(beta, out=beta)
    return alpha, beta


@dataclass(frozen=True, eq=False)
class Scan:
    """One TLS station. Build with `Scan.from_points` (validates, estimates the steps if needed)."""

    points: np.ndarray
    name: str
    angular_step_deg: tuple[float, float]
    source: Path | None = None
    step_estimated: bool = False
    #: T_user_scan: maps the scan's points into the frame its file (or the user) gave them in.
    pose: np.ndarray | None = field(default=None, repr=False)
    #: How the steps were obtained and how far to trust them (`StepEstimate`); None = given.
    step: StepEstimate | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        # A name comes from a file name or a file's header: kept as it is shown (one line, controls as
        # escapes), so every output keyed or labelled by it - the CLI's lines, transforms.json, the app -
        # says the same and none can forge a line or drive a terminal.
        object.__setattr__(self, "name", shown(self.name))
        pts = np.ascontiguousarray(self.points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ScanError(self.label, f"points must be an N x 3 array, got shape {pts.shape}")
        if not np.isfinite(pts).all():
            raise ScanError(self.label, "points contain NaN or infinite values")
        pts.setflags(write=False)
        object.__setattr__(self, "points", pts)
        h, v = (float(s) for s in self.angular_step_deg)
        lo, hi = ANGULAR_STEP_RANGE_DEG
        if not (lo <= h <= hi and lo <= v <= hi):
            raise ScanError(self.label, f"angular steps {h:g} x {v:g} deg are outside the allowed range "
                                        f"({lo:g} to {hi:g} deg)")
        object.__setattr__(self, "angular_step_deg", (h, v))
        pose = np.eye(4) if self.pose is None else np.array(self.pose, dtype=np.float64)
        if pose.shape != (4, 4) or not np.isfinite(pose).all():
            raise ScanError(self.label, f"the scan's pose must be a finite 4 x 4 matrix, got shape {pose.shape}")
        pose.setflags(write=False)
        object.__setattr__(self, "pose", pose)
        if self.step is None:
            object.__setattr__(self, "step", StepEstimate(h, v, 1.0, "estimated" if self.step_estimated else "given"))

    @cached_property
    def _angles(self) -> tuple[np.ndarray, np.ndarray]:
        alpha, beta = spherical_angles_deg(self.points)
        alpha.setflags(write=False)
        beta.setflags(write=False)
        return alpha, beta

    def forget_angles(self) -> None:
        """Drop the cached angles (a full-resolution scan needs them once, to be reduced; they are
        recomputed if asked for again)."""
        self.__dict__.pop("_angles", None)

    @property
    def azimuth_deg(self) -> np.ndarray:
        """Azimuth alpha of every point, degrees in (-180, 180] (computed on first use)."""
        return self._angles[0]

    @property
    def elevation_deg(self) -> np.ndarray:
        """Elevation beta of every point, degrees in [-90, 90] (computed on first use)."""
        return self._angles[1]

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
        pose: np.ndarray | None = None,
        grid: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> "Scan":
        """Validate `points` and make a scan; when the steps are not given, read them off the
        file's row/column `grid` (row, col per point) if there is one, else estimate them."""
        src = Path(source) if source is not None else None
        label = str(src) if src is not None else name
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ScanError(label, f"points must be an N x 3 array, got shape {pts.shape}")
        if pts.shape[0] < min_points:
            raise ScanError(
                label, f"only {pts.shape[0]} points; at least {min_points} are needed to register a scan"
            )
        step: StepEstimate | None = None
        computed = angular_step_deg is None
        if computed:
            alpha, beta = spherical_angles_deg(pts)
            try:
                step = grid_steps(alpha, beta, *grid) if grid is not None else None
            except ValueError:
                step = None  # a grid too sparse to read: estimate from the angles instead
            try:
                step = step or estimate_steps(alpha, beta)
            except ValueError as e:
                raise ScanError(label, f"cannot estimate the angular step: {e}; give it with --angular-step "
                                       "(the instrument's steps in degrees)") from None
            angular_step_deg = step.steps
            lo, hi = ANGULAR_STEP_RANGE_DEG
            if not all(lo <= float(s) <= hi for s in angular_step_deg):
                # Points not on a scanner's grid (a cloud merged from several stations, a resampled
                # file) give absurd steps: say so rather than compute with them.
                h, v = (float(s) for s in angular_step_deg)
                raise ScanError(label, f"the angular step estimated from the points, {h:.2g} x {v:.2g} deg, is "
                                       f"outside {lo:g} to {hi:g} deg, so the points do not look like one "
                                       "station's scan in its own frame; give the instrument's steps with "
                                       "--angular-step")
        scan = cls(
            points=pts,
            name=name,
            angular_step_deg=tuple(angular_step_deg),  # type: ignore[arg-type]
            source=src,
            step_estimated=step is not None and step.source == "estimated",
            pose=pose,
            step=step,
        )
        if computed and scan.points is pts:
            # Computed for the estimate: kept for the working resolution (the points were not copied).
            alpha.setflags(write=False)
            beta.setflags(write=False)
            scan.__dict__["_angles"] = (alpha, beta)
        return scan

    def with_angular_step(self, angular_step_deg: tuple[float, float]) -> "Scan":
        """The same station with the instrument's steps given (not estimated)."""
        h, v = (float(s) for s in angular_step_deg)
        return Scan(points=self.points, name=self.name, angular_step_deg=(h, v), source=self.source,
                    step_estimated=False, pose=self.pose, step=StepEstimate(h, v, 1.0, "given"))

    def header(self) -> "ScanHeader":
        """The scan without its points: what outputs keyed by scans need once its points are reduced."""
        return ScanHeader(name=self.name, source=self.source, angular_step_deg=self.angular_step_deg,
                          step=self.step, pose=self.pose if self.pose is not None else np.eye(4),
                          n_points=self.n_points)

    def with_points(self, points: np.ndarray, name: str | None = None) -> "Scan":
        """The same station (steps, source) with other points, e.g. after cropping or ground removal."""
        return Scan(
            points=points,
            name=name or self.name,
            angular_step_deg=self.angular_step_deg,
            source=self.source,
            step_estimated=self.step_estimated,
            pose=self.pose,
            step=self.step,
        )


@dataclass(frozen=True, kw_only=True, eq=False)
class ScanHeader:
    """A scan's name, file, steps and pose without its points (`Scan.header`): a survey reads each
    station, keeps its summary and this, and lets the points go (60 stations: 1 GB not held)."""

    name: str
    source: Path | None
    angular_step_deg: tuple[float, float]
    step: StepEstimate | None
    pose: np.ndarray
    n_points: int

    @property
    def label(self) -> str:
        return str(self.source) if self.source is not None else self.name
