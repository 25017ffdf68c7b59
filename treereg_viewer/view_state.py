"""What the user chose to look at (not what the pipeline computed): stage, display options.

Frozen, replaced as a whole: the drawing thread reads one consistent value without a lock.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class ViewState:
    """Display choices shared by every browser tab."""

    stage: str = "prepare"  # a pipeline stage name
    point_size: float = 0.04
    max_points: int = 40_000  # per scan, for display only
    hidden_scans: frozenset[str] = field(default_factory=frozenset)
    show_stations: bool = True
    projection_step: int = 0  # index into the rotation sequence
    projection_3d: bool = False  # also show the rotated cloud in 3-D
    target: int = 0  # which target scan (0 = the second scan) the matching/coarse/fine views detail
    match_pair: int = 0  # which chosen image pair of that target's matching
    show_icp: bool = False  # Result stage: show the ICP pose instead of the fine one
