"""The app's eight stages: what each one shows, which pipeline stage makes its data, which
parameter sections it edits, and the few sentences that explain it (for teaching).

The pipeline has six stages; the app splits the fine stage into three views (slices, arcs, fits)
because the paper explains them as three steps (2.2.1-2.2.3).
"""

from __future__ import annotations

from dataclasses import dataclass

from treereg_core.pipeline import STAGES


@dataclass(frozen=True)
class AppStage:
    """One step of the app: a title, the pipeline stage behind it, its parameter sections."""

    index: int
    title: str
    pipeline_stage: str
    sections: tuple[str, ...]
    explanation: str

    @property
    def label(self) -> str:
        """What the stage selector shows, e.g. '3 Coarse'."""
        return f"{self.index} {self.title}"


APP_STAGES: tuple[AppStage, ...] = (
    AppStage(
        0, "Scans", "prepare", ("prepare",),
        "Each station's points in its own scanner frame (scan 1 green, 2 red, 3 blue, as in the paper); "
        "the axes mark the scanners (before registration they all sit at the origin). Scan 1 is the "
        "reference: every other scan is registered onto it (2 → 1, 3 → 1). The paper's trees hold no ground; "
        "real scans do, and ground fills the projection images and pulls the rotation centre off the stem, "
        "so treereg removes it (grey) before projection, and a crop can keep the tree alone.",
    ),
    AppStage(
        1, "Projection", "projection", ("projection",),
        "Each scan is projected onto a sphere around its scanner: a pixel covers k·φ × k·ϕ of azimuth α and "
        "elevation β (φ, ϕ: the instrument's angular steps; paper: k = 2) and is black when any point falls "
        "in it (eq. 2-3). Two stations see the tree from different sides, so their images differ; the paper "
        "therefore rotates each cloud about the vertical axis through its mean (x̄, ȳ) in steps θ = 10° from "
        "−360°/n to +360°/n (n scans) and projects again, giving a sequence of views (2.1.2). "
        "The slider walks the sequence.",
    ),
    AppStage(
        2, "Matching", "matching", ("matching",),
        "The most similar image pairs of two sequences (marked on the similarity matrix) are matched with "
        "ORB, fast and suited to images with little texture (2.1.3; the paper: 3 pairs, the 5 best matches "
        "of each). Each kept match gives a tie point: the centroid of the scan's points in that pixel's "
        "(α, β) cell, rotation undone (2.1.4). The paper's β check (4.1) drops a match whose elevation "
        "difference |β₁ − β₂| lies outside the mean ± one standard deviation of all matches: a crown point "
        "must match a crown point. Rejected matches are drawn in grey.",
    ),
    AppStage(
        3, "Coarse", "coarse", ("coarse",),
        "The rigid transform that best maps the target's tie points onto the reference's, by SVD over all "
        "of them in the paper (2.1.4). Wrong matches cannot be avoided on binary images (4.1), so treereg by "
        "default lets RANSAC keep the consistent ones (green lines; outliers grey), solving yaw and "
        "translation for levelled scanners. Projection loses detail, so trunks and branches are close but "
        "not yet aligned (paper Fig. 9). ⚠ marks a transform that cannot be right.",
    ),
    AppStage(
        4, "Slices", "fine", ("slicing",),
        "Fine registration starts from the coarse pose. Both scans are cut into thin horizontal slices at "
        "quantiles of tree height (paper: the three quartiles, 10 cm thick, 2.2.1; treereg takes more): low "
        "slices hold the trunk, high ones branches, whose centres become the fine tie points.",
    ),
    AppStage(
        5, "Arcs", "fine", ("arcs",),
        "Each slice holds several arcs (trunk and branch sections). Because the scanner samples a fixed "
        "angular grid, two points are neighbours when their angles differ by at most c·φ and c·ϕ "
        "(paper: c = 3, 2.2.2); connected components give the arcs, coloured one per component.",
    ),
    AppStage(
        6, "Fits", "fine", ("fitting", "fine"),
        "The trunk in the lowest slice is fitted with a Taubin circle, the other sections with least-squares "
        "cylinders (2.2.3); the circle centre, and on each cylinder axis its start and the point one unit "
        "further up, are the tie points, joined here to their partners in the other scan. An SVD over them "
        "gives the fine transform (treereg's default, fine.method = joint, instead fits each pair of "
        "sections as one cylinder together with the pose). Grey fits failed a plausibility check, e.g. the paper's rule that a "
        "section is no wider than the one below it (4.2). Fits on short arcs are unreliable, so treereg "
        "keeps the update only when it measurably improves the alignment.",
    ),
    AppStage(
        7, "Result", "evaluation", ("evaluation", "icp"),
        "The final overlay. The paper judges a registration by its branches: in three layers of each "
        "corresponding branch, cylinder axes are fitted in both scans and the distances between centre "
        "points at equal height averaged, d̄ (eq. 8, 3.3). ICP from the coarse result is shown beside it, "
        "as the paper compares. When a truth.json comes with the scans (the demo, simulated cases), the "
        "errors against it are listed first; ⚠ marks a registration that failed.",
    ),
)

assert all(s.pipeline_stage in STAGES for s in APP_STAGES)

#: The app stage that first shows each pipeline stage (for messages like 'failed at Coarse').
FIRST_APP_STAGE: dict[str, AppStage] = {}
for _s in APP_STAGES:
    FIRST_APP_STAGE.setdefault(_s.pipeline_stage, _s)


def stage_by_label(label: str) -> AppStage:
    """The stage whose selector label is `label`."""
    for s in APP_STAGES:
        if s.label == label:
            return s
    raise KeyError(label)
