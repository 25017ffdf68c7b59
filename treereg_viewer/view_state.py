"""What one viewer (a browser tab) chose to look at — not what the pipeline computed.

Every tab has its own `ViewState`: its stage, pair, sliders, display options and cross-section;
the computation and its results are shared. Frozen, replaced as a whole: the drawing thread reads
one consistent value without a lock.
"""

from __future__ import annotations

from dataclasses import dataclass, field

#: What the cross-section shows: one registration, or several side by side.
SECTION_POSES = {
    "Coarse and fine": ("coarse", "fine"),
    "Coarse": ("coarse",),
    "Fine": ("fine",),
    "ICP": ("icp",),
    "All three": ("coarse", "fine", "icp"),
}


#: `ViewState.slice_shown` for every slice at once.
ALL_SLICES = -1


@dataclass(frozen=True)
class ViewState:
    """One viewer's display choices."""

    stage: str = "prepare"  # a pipeline stage name
    point_size: float = 0.02
    max_points: int = 40_000  # per scan, for display only
    hidden_scans: frozenset[str] = field(default_factory=frozenset)
    show_stations: bool = True
    projection_step: int = 0  # index into the rotation sequence (shown 1-based)
    projection_3d: bool = False  # also show the rotated cloud in 3-D
    target: int = 0  # which target scan (0 = the second scan) the stage details
    match_pair: int = 0  # which chosen image pair of that target's matching (shown 1-based)
    result_pose: str = "final"  # Result stage: the targets at their "final" (joint), "fine", "coarse" or "icp" pose
    result_colour: str = "scan"  # Result stage: "scan" colours or "residual" (distance to the other scans)
    residual_max_m: float = 0.02  # the residual colour map's top
    show_rejected: bool = False  # Fits and Fine: also draw the fits judged implausible
    show_mixed: bool = True  # Scans: draw the mixed pixels the preparation removed (near-black)
    focus_section: int | None = None  # Fits and Fine: the table row (0-based) picked to look at
    panel: str = "stage"  # the docked panel shows "stage" details or the "section" inspector
    section_height: float | None = None  # cross-section height (m, reference frame); None = the trunk slice
    section_thickness: float | None = None  # slab thickness (m); None = the slices stage's thickness in force
    section_poses: str = "Coarse and fine"  # a key of SECTION_POSES
    branch: int | None = None  # cross-section of an evaluated branch (its index) instead of the stem
    tour_step: int | None = None  # the guided tour's step, when the tour is on
    slice_shown: int | None = None  # Arcs, Fits, Fine: one slice (0-based), ALL_SLICES, or None = the busiest
    align_scan: str | None = None  # Align: the scan this tab aligns by hand (its layers hidden meanwhile)
    show_before: bool = False  # draw the stage's run before (a parameter changed since) instead of the latest
    scale: float = 1.0  # sizes on screen (labels, lines, points): PROJECTOR_SCALE in projector mode
    rival: str | None = None  # Hypotheses: the rival drawn beside the chosen pose (None = the best distinct one)
