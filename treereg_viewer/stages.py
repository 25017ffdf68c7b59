"""How the app shows each pipeline stage: the stages are exactly the core's (`treereg_core.stages`),
keyed by name; here is what the app adds to each: the pose the scans are drawn at, how the scans
are drawn, the few sentences that explain the stage (for teaching), and its view controls.

A stage the app has no entry for is still shown (its metrics as a table), with the defaults.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from treereg_core.stages import STAGES, Stage


@dataclass(frozen=True)
class StageView:
    """The app's side of one stage.

    Attributes
    ----------
    pose
        Which transform places the target scans on this stage: None (each in its own scanner frame,
        before registration), "coarse", "hypothesis", "fine", "icp" or "final" (the joint placement).
    scans
        How the scan layer is drawn: "full", "faded" (the stage's own drawing is the subject) or
        "hidden" (points would hide fitted surfaces).
    controls
        View controls the stage's folder gets ("target", "projection_step", "match_pair", "fits" (show
        rejected fits, frame a fit), "hypothesis" (pick a coarse hypothesis by hand), "result"
        (registration shown, colour by)).
    explanation
        What the stage does and why, in a few sentences (the paper's sections cited).
    """

    pose: str | None = "fine"
    scans: str = "full"
    controls: tuple[str, ...] = ("target",)
    explanation: str = ""


VIEWS: dict[str, StageView] = {
    "prepare": StageView(
        None, controls=("mixed",),
        explanation="Each station's points in its own scanner frame (scan 1 green, 2 red, 3 blue, as in the paper); "
        "the axes mark the scanners (before registration they all sit at the origin). Scan 1 is the "
        "reference: every other scan is registered onto it (2 → 1, 3 → 1). The paper's trees hold no ground; "
        "real scans do, and ground fills the projection images and pulls the rotation centre off the stem, "
        "so treereg removes it (grey) before projection, and a crop can keep the tree alone. Where a beam straddles "
        "a stem's edge, the range lands between the edge and what lies behind (a mixed pixel): every silhouette "
        "trails a comet tail. Those returns, just behind a range jump with no neighbour at their own range, are "
        "removed first (near-black).",
    ),
    "projection": StageView(
        None, controls=("projection_step",),
        explanation="Each scan is projected onto a sphere around its scanner: a pixel covers k·φ × k·ϕ of azimuth α and "
        "elevation β (φ, ϕ: the instrument's angular steps; paper: k = 2) and is black when any point falls "
        "in it (eq. 2-3). Two stations see the tree from different sides, so their images differ; the paper "
        "therefore rotates each cloud about the vertical axis through its mean (x̄, ȳ) in steps θ = 10° from "
        "−360°/n to +360°/n (n scans) and projects again, giving a sequence of views (2.1.2). "
        "The slider walks the sequence.",
    ),
    "matching": StageView(
        None, controls=("target", "match_pair"),
        explanation="The most similar image pairs of two sequences (marked on the similarity matrix) are matched with "
        "ORB, fast and suited to images with little texture (2.1.3; the paper: 3 pairs, the 5 best matches "
        "of each). Each kept match gives a tie point: the centroid of the scan's points in that pixel's "
        "(α, β) cell, rotation undone (2.1.4). The paper's β check (4.1) drops a match whose elevation "
        "difference |β₁ − β₂| lies outside the mean ± one standard deviation of all matches: a crown point "
        "must match a crown point; its rejected matches are drawn in grey. treereg's default leaves the β check "
        "off (matching.beta_check) and lets RANSAC at the coarse stage reject wrong matches instead, so grey "
        "matches appear here only with the check on (e.g. the paper preset, Files tab).",
    ),
    "coarse": StageView(
        "coarse",
        explanation="The rigid transform that best maps the target's tie points onto the reference's, by SVD over all "
        "of them in the paper (2.1.4). Wrong matches cannot be avoided on binary images (4.1), so treereg by "
        "default lets RANSAC keep the consistent ones (green lines; outliers grey), solving yaw and "
        "translation for levelled scanners. Projection loses detail, so trunks and branches are close but "
        "not yet aligned (paper Fig. 9). ⚠ marks a transform that cannot be right.",
    ),
    "hypotheses": StageView(
        "hypothesis", controls=("target", "hypothesis"),
        explanation="A nearly round crown looks alike from several headings: RANSAC's winner can be the wrong one. "
        "So every distinct RANSAC solution and the coarse transform turned about the stem by quarter, third and half turns are "
        "each aligned cheaply by the surfaces and judged by what the reference scanner saw: a target point lying "
        "where the reference's laser passed through empty space speaks against the pose (grey: the rivals). The "
        "most consistent pose goes on to the fine stage; the margin to the best distinct rival says how sure "
        "that is. You can pick another hypothesis here.",
    ),
    "slices": StageView(
        "hypothesis", scans="faded",
        explanation="Fine registration starts from the coarse pose. Both scans are cut into thin horizontal slices at "
        "quantiles of tree height (paper: the three quartiles, 10 cm thick, 2.2.1; treereg takes more): low "
        "slices hold the trunk, high ones branches, whose centres become the fine tie points.",
    ),
    "arcs": StageView(
        "hypothesis", scans="faded",
        explanation="Each slice holds several arcs (trunk and branch sections). Because the scanner samples a fixed "
        "angular grid, two points are neighbours when their angles differ by at most c·φ and c·ϕ "
        "(paper: c = 3, 2.2.2); connected components give the arcs, coloured one per component.",
    ),
    "sections": StageView(
        "hypothesis", scans="hidden", controls=("target", "fits"),
        explanation="The trunk in the lowest slice is fitted with a Taubin circle, the other sections with least-squares "
        "cylinders (2.2.3); the circle centre, and on each cylinder axis its start and the point one unit "
        "further up, are the tie points, joined here to their partners in the other scan (at the pose "
        "the hypotheses stage chose). Fits that fail a plausibility check, e.g. the paper's rule that a section is no wider "
        "than the one below it (4.2), are not used; tick *Show rejected fits* to see them in grey.",
    ),
    "fine": StageView(
        "fine", scans="hidden", controls=("target", "fits"),
        explanation="An SVD over the tie points gives the paper's fine transform; treereg's default (fine.method = "
        "joint) instead fits each pair of corresponding sections as one cylinder together with the pose, "
        "re-slices at the new pose and repeats. Directions the sections fix only weakly come from the "
        "scans' surfaces, and the update is kept only when it measurably improves the alignment. "
        "Shown: the sections at the final pose.",
    ),
    "verify": StageView(
        "fine",
        explanation="A registration must show its evidence before it is trusted: enough coarse tie points agree "
        "compared with what chance gives on the same ties; the target's points lie where the reference scanner "
        "saw a surface, not in space it saw through (where both stations could see); the surfaces fit within "
        "their own noise; no other heading explains the scans almost as well; the scanner stays level and at "
        "its height above the ground. A pair failing any of these is unverified, with the reason.",
    ),
    "graph": StageView(
        "final", controls=(),
        explanation="With three or more scans every verified pair is an edge of a graph of stations. Around a loop "
        "the transforms must compose to nothing; a pair that keeps a loop open is dropped. All poses are then "
        "solved together, so a station opposite the reference is placed through its neighbours. Each scan ends "
        "verified (with the evidence), unverified (the best guess and why) or failed.",
    ),
    "icp": StageView(
        "icp",
        explanation="The paper compares its fine stage with ICP (iterative closest point) started from the coarse "
        "result (3.3): every target point pairs with its nearest reference point and the pose that brings "
        "the pairs together is solved again and again. On trees two stations see different sides of a "
        "branch, so the nearest point is often the wrong one.",
    ),
    "evaluation": StageView(
        "final", controls=("target", "result"),
        explanation="The final overlay. The paper judges a registration by its branches: in three layers of each "
        "corresponding branch, cylinder axes are fitted in both scans and the distances between centre "
        "points at equal height averaged, d̄ (eq. 8, 3.3), here for each pair's own fine transform. The targets "
        "are drawn at their final (joint) placement unless you pick another. ICP from the coarse result is shown beside it, "
        "as the paper compares. When a truth.json comes with the scans (the demo, simulated cases), the "
        "errors against it are listed first; ⚠ marks a registration that failed. Colour the points by their "
        "distance to the other scans to see where the scans agree.",
    ),
}


def view_of(name: str) -> StageView:
    """The app's view of stage `name` (defaults for a stage without an entry)."""
    return VIEWS.get(name, StageView())


#: The stage whose output holds each pose's transforms.
POSE_STAGE = {"coarse": "coarse", "hypothesis": "hypotheses", "fine": "fine", "icp": "icp", "final": "graph"}


#: The app's stages: exactly the pipeline's, in run order.
APP_STAGES: tuple[Stage, ...] = STAGES
STAGE_NAMES: tuple[str, ...] = tuple(s.name for s in STAGES)


def label(name: str) -> str:
    """What a person reads for a stage, numbered from 1: '4 Coarse'."""
    i = STAGE_NAMES.index(name)
    return f"{i + 1} {APP_STAGES[i].title}"


def by_label(text: str) -> str:
    """The stage name behind a selector label."""
    for name in STAGE_NAMES:
        if label(name) == text:
            return name
    raise KeyError(text)


def registered(name: str) -> bool:
    """Whether the scans are drawn over the reference (a pose exists) rather than scattered in their frames."""
    return view_of(name).pose is not None


def section_available(snap: Any, name: str) -> bool:
    """Whether the cross-section inspector can be shown on stage `name`: the scans are registered
    there and a coarse registration exists to cut."""
    return registered(name) and snap.output("coarse") is not None and len(snap.scans) >= 2
