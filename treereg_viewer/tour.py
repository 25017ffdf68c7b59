"""The guided tour: the stages in order, each with the paper's reasoning in two sentences and one
thing to try, the camera, the panel and a highlight set for it.

For teaching: a class follows the steps on its own screens, or follows the teacher's tab ("others
follow me", Teach tab). The steps read only the results (the stage, its panel, a height on the
trunk), so the tour works on any scans, the demo or uploaded ones, offline.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import viser


@dataclass(frozen=True)
class TourStep:
    """One step of the tour.

    Attributes
    ----------
    stage
        The pipeline stage shown.
    title
        A short heading.
    why
        The paper's reasoning, two sentences.
    try_this
        One thing to try (controls named as they read in the app).
    view
        View choices set for the step (e.g. the cross-section panel).
    camera
        "frame" (what the stage draws) or "trunk" (a close view of the trunk slice).
    highlight
        What labels in 3-D point at: "trees" (each scan's tree), "trunk" (the cross-section's
        slice) or "" (none).
    """

    stage: str
    title: str
    why: str
    try_this: str
    view: dict[str, Any] = field(default_factory=dict)
    camera: str = "frame"
    highlight: str = ""


STEPS: tuple[TourStep, ...] = (
    TourStep(
        "prepare", "One tree, several stations",
        "A terrestrial scanner sees one side of a tree, so the tree is scanned from several stations, each scan in "
        "its own frame with the scanner at the origin. Registration finds the rigid transforms that bring scans 2, "
        "3, … onto scan 1, here from the tree itself instead of targets placed in the forest.",
        "Rotate the view with the mouse: the stations' trees stand apart. In the *Scans* tab, untick a scan to see "
        "what one station saw.",
        view={"panel": "stage"}, highlight="trees"),
    TourStep(
        "projection", "Rotating projection",
        "Each scan is projected onto a sphere around its scanner into a binary image: a pixel is black when a point "
        "falls into it (paper 2.1.1). Two stations see the tree from different sides, so the paper turns each cloud "
        "about the vertical axis in 10° steps and projects it again (2.1.2).",
        "Move *Rotation step* (Stage tab) and watch each scan's image change as its tree turns.",
        view={"panel": "stage"}),
    TourStep(
        "matching", "Matching the most similar views",
        "The most similar image pairs of two sequences are matched with ORB, and each match becomes a 3-D tie point: "
        "the centroid of the points behind that pixel (2.1.3–2.1.4). Binary images carry little texture, so some "
        "matches are wrong (4.1).",
        "Move *Image pair* and compare the lines between the two images with the tie lines in 3-D.",
        view={"panel": "stage"}),
    TourStep(
        "coarse", "The coarse transform",
        "One rigid transform maps the target's tie points onto the reference's; treereg lets RANSAC keep the "
        "consistent ties (green) and drop the wrong ones (grey). The trees now overlap, but projection loses "
        "detail: stems are close, not yet aligned (paper Fig. 9).",
        "Zoom onto the trunk: each scan's skin of the stem lies a little apart from the others.",
        view={"panel": "stage"}),
    TourStep(
        "hypotheses", "Could it be another heading?",
        "A nearly round crown looks alike from several sides, so the best coarse match can be a wrong heading. "
        "treereg keeps every distinct RANSAC solution and the coarse pose turned about the stem (quarter, third and half turns), aligns each "
        "cheaply and asks the reference scanner: a target point where its laser passed through empty space "
        "speaks against the pose.",
        "Read the table: the margin between the chosen pose and its best rival. Pick another under *Use "
        "hypothesis* and watch the later stages run again.",
        view={"panel": "stage"}),
    TourStep(
        "slices", "Slices at the coarse pose",
        "Fine registration cuts both scans into thin horizontal slices (2.2.1). Seen from above, a slice of the trunk "
        "holds one arc per scan; at the coarse pose the arcs do not yet close into one circle.",
        "Drag *Height* in the cross-section (left panel), or click the stem in 3-D.",
        view={"panel": "section", "section_poses": "Coarse", "branch": None, "section_height": None},
        camera="trunk", highlight="trunk"),
    TourStep(
        "arcs", "Arcs by angular connectivity",
        "Within a slice, two points belong to one arc when they are neighbours in the scanner's own angular grid "
        "(2.2.2, Fig. 6): the connected cells of the raster below the top view. A slice through the crown holds "
        "many arcs, one per branch.",
        "Raise *Height* into the crown and watch the raster split into arcs of different colours.",
        view={"panel": "section", "section_poses": "Coarse", "branch": None}, camera="trunk", highlight="trunk"),
    TourStep(
        "sections", "Circles, cylinders and their centres",
        "The trunk's arcs get Taubin circles, the branches' least-squares cylinders (2.2.3); their centres pair up "
        "between the scans and become the fine tie points. A section wider than the part below it is a "
        "mis-separated arc and is dropped (4.2).",
        "Tick *Show rejected fits*, then pick a row under *Frame a fit*.",
        view={"panel": "stage", "show_rejected": False}),
    TourStep(
        "fine", "From separate arcs to one ring",
        "The corresponding sections give the fine transform; treereg fits each pair as one cylinder together with "
        "the pose and keeps the update only when the surfaces agree better. In the cross-section the separate arcs "
        "of the coarse pose close into one ring (paper Figs. 11 and 19).",
        "Compare the coarse and the fine panel side by side, then choose *All three* under *Registration*.",
        view={"panel": "section", "section_poses": "Coarse and fine", "branch": None, "section_height": None},
        camera="trunk", highlight="trunk"),
    TourStep(
        "fine", "Wind: what moved and what did not",
        "Stations are scanned minutes apart; in wind the crown is never where it was, while the stem base and the "
        "ground stay put, and the instrument's pose is in them. treereg fits the stem's bend (a cantilever) with the "
        "pose, so the crown's motion is not taken for a tilt of the scanner; the plot shows the target's stem offset "
        "by height: at zero where the stem holds, bending off above where the crown moved.",
        "Read the plot below the text; in still air it stands at zero all the way up. In *13 Result*, colour by "
        "distance: pink points moved with the wind.",
        view={"panel": "stage"}),
    TourStep(
        "verify", "Evidence before trust",
        "A registration is trusted only with its evidence. Enough tie points must agree compared with chance, the "
        "target's points lie where the reference saw a surface and not where it saw through, the surfaces fit "
        "within their noise, no rival heading is nearly as good, the scanner stays level.",
        "Read each check's value against its threshold; a failed check says what to try.",
        view={"panel": "stage"}),
    TourStep(
        "graph", "Every station placed",
        "With three or more scans each verified pair is an edge between stations; around a loop the transforms must "
        "compose to nothing, and all poses are solved together. Each scan ends verified, unverified (best guess and "
        "why) or failed: the marks in the header.",
        "Look at the station graph: which pairs carry each scan to scan 1?",
        view={"panel": "stage"}),
    TourStep(
        "icp", "The ICP baseline",
        "The paper compares its fine stage with ICP started from the coarse result (3.3). On a tree two stations see "
        "different sides of a branch, so the nearest point is often the wrong partner.",
        "Choose *9 Fine*, then *12 ICP* under *Stage*, and watch the scans move.",
        view={"panel": "stage"}),
    TourStep(
        "evaluation", "Judging the result",
        "The paper judges a registration by its branches: three layers per branch, the distance between the scans' "
        "fitted centres, averaged (eq. 8, Table 2). Here each point is also coloured by its distance to the other "
        "scans' surface: blue where they agree, red where they do not, pink where they moved with the wind (they fit "
        "once the crown's measured motion is taken out).",
        "Switch *Targets at* between Final, Coarse and ICP and watch the colours change.",
        view={"panel": "stage", "result_colour": "residual", "result_pose": "final"}),
)


class TourPanel:
    """The tour's card at the top of the control panel: step text and Back / Next / End."""

    def __init__(self, gui: viser.GuiApi, go_to: Any) -> None:
        self._go_to = go_to  # go_to(step index or None)
        self.card = gui.add_markdown("", visible=False)
        self.nav = gui.add_button_group("Tour", ("◀ Back", "Next ▶", "End tour"), visible=False)
        self.nav.on_click(lambda e: self._nav(e.target.value))
        self.step: int | None = None

    def _nav(self, which: str) -> None:
        if self.step is None:
            return
        if which == "End tour":
            self._go_to(None)
        else:
            self._go_to(max(0, min(len(STEPS) - 1, self.step + (1 if which.startswith("Next") else -1))))

    def show(self, step: int | None) -> None:
        """Show step `step` (None hides the card)."""
        self.step = step
        if step is None:
            self.card.visible = False
            self.nav.visible = False
            return
        s = STEPS[step]
        self.card.content = (f"#### Tour · step {step + 1} of {len(STEPS)}: {s.title}\n\n{s.why}\n\n"
                             f"**Try:** {s.try_this}")
        self.card.visible = True
        self.nav.visible = True
