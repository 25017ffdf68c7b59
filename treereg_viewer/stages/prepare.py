"""The Scans stage (`prepare`): Scan and PreparedScan — a table of the scans, what preparation kept
and which tree it took; in 3-D each scan's target stem (the scan layer draws the points).
"""

from __future__ import annotations

import numpy as np
import viser

from treereg_core.prepare.ground import PreparedScan

from ..controller import Snapshot
from ..draw.common import Drawing, Handles, md_table, not_ready_text, title
from ..palette import GREY, scan_color
from ..view_panel import PanelContent
from ..text import md
from ..view_state import ViewState
from .base import AppStage, ControlHost, StageControls, StageView, TourStep


#: Where the stem markers start without a ground plane: the scanner's foot, 1.5 m below it.
SCANNER_FOOT_Z = -1.5


def _stem_markers(scene: viser.SceneApi, root: str, snap: Snapshot) -> Handles:
    """The target tree of each scan (a tall line at its stem, in the scan's colour, labelled) and the
    other stems found at breast height (short grey lines), in each scan's own frame."""
    prepared = snap.output("prepare")
    handles: Handles = []
    if prepared is None:
        return handles
    for i in range(len(prepared.items)):
        prep = snap.scan_item("prepare", i, PreparedScan)
        if prep is None:
            continue
        stems = prep.stems
        if len(stems):
            base = prep.ground_z(stems[:, :2], SCANNER_FOOT_Z)
            segs = np.stack([np.column_stack([stems[:, :2], base]), np.column_stack([stems[:, :2], base + 2.0])], axis=1)
            handles.append(scene.add_line_segments(f"{root}/s{i}/stems", segs, GREY, thickness=2.0, thickness_units="screen"))
        xy = prep.stem_xy
        if xy is not None and prep.target:
            z = float(prep.ground_z(np.asarray([xy]), SCANNER_FOOT_Z)[0])
            seg = np.array([[[xy[0], xy[1], z], [xy[0], xy[1], z + 12.0]]])
            handles.append(scene.add_line_segments(f"{root}/s{i}/target", seg, scan_color(i), thickness=5.0,
                                                   thickness_units="screen"))
            handles.append(scene.add_label(f"{root}/s{i}/target/name", f"target ({snap.scans[i].name})",
                                           position=(xy[0], xy[1], z + 12.5 + 0.5 * i)))
    return handles


def render(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> Drawing:
    """The Scans stage's panel: a table of the scans, what preparation kept and which tree it took."""
    prepared = snap.output("prepare")
    rows = []
    stood_down: list[str] = []
    for i, scan in enumerate(snap.scans):
        prep = snap.scan_item("prepare", i, PreparedScan)
        # The instrument's steps in force: the parameter's when one is set (it replaces the
        # estimate in the prepare stage), else the scan's own (read off its grid, or estimated).
        given = snap.params.prepare.angular_step_deg
        phi, vphi = given or scan.angular_step_deg
        kept = ground = target = mixed = ""
        if prep is not None:
            mixed = f"{len(prep.mixed_points):,}" if snap.params.prepare.mixed_pixels else "off"
            # The filter stood down on this scan (no regular grid, a surface rougher than it): say why.
            why = prep.mixed_not_filtered
            if why:
                mixed = "not filtered"
                stood_down.append(f"{md(scan.name)}: mixed pixels {md(why)}.")
            kept = f"{prep.scan.n_points:,}"
            ground = f"{int(np.count_nonzero(prep.ground_mask)):,}"
            xy = prep.stem_xy
            target = (f"stem at {xy[0]:.2f}, {xy[1]:.2f}" if xy is not None and prep.target
                      else "every point (no stem picked)")
        step = scan.step
        how = "" if given or step is None or step.source == "given" else (" (grid)" if step.source == "grid" else f" (est., {step.confidence:.2f})")
        # Few columns, the counts stacked in one cell: the table fits a 330 px panel (1280 x 720).
        counts = "<br>".join(f"{v}&nbsp;{what}" for v, what in ((f"{scan.n_points:,}", "read"), (kept, "kept"),
                                                             (ground, "ground")) if v)
        if mixed:
            counts += "<br>" + (f"mixed pixels {mixed}" if mixed in ("off", "not filtered") else f"{mixed}&nbsp;mixed")
        rows.append((
            f"{i + 1}: {md(scan.name)}{' (reference)' if i == 0 else ''}", counts, f"{phi:.3g} / {vphi:.3g}{how}", target,
        ))
    table = md_table(("scan", "points", "φ / ϕ (deg)", "tree taken (x, y in m)"), rows)
    text = not_ready_text(snap, "prepare")
    if prepared is not None:
        bad = [f"**{md(snap.scans[i].name)}:** {md(it.message)}" for i, it in enumerate(prepared.items) if not it.ok]
        notes = [f"{md(snap.scans[i].name)}: {md(it.message)}" for i, it in enumerate(prepared.items) if it.ok and it.message]
        notes += stood_down
        text = "\n\n".join(bad + notes) or "Grey points were removed as ground; light grey were cropped."
        if snap.params.prepare.mixed_pixels:
            text += (" Near-black: mixed pixels, returns strung out behind a stem's or branch's edge (the beam "
                     "straddled it), removed before anything else; the free-space test is blind where they were.")
        reference = snap.scan_item("prepare", 0, PreparedScan)
        chosen = reference.target if reference is not None else ""
        if chosen and reference is not None and reference.stem_xy is not None:
            text += (f"\n\n**Target tree:** {md(chosen)}. The tall line marks it in every scan, grey lines the other stems; "
                     "to take another tree, type its stem's x, y (reference scan's frame) into *tree at* below.")
    if snap.truth:
        text += "\n\nTruth is known for this case (`truth.json`): the Result stage reports errors against it."
    return _stem_markers(scene, root, snap), PanelContent(title("prepare"), text=text, table=table)


class MixedControl(StageControls):
    """"Show removed mixed pixels"."""

    def __init__(self, gui: viser.GuiApi, host: ControlHost, stage: str) -> None:
        self.checkbox = gui.add_checkbox("Show removed mixed pixels", True,
                                         hint="Draw (near-black) the returns behind the stems' and branches' edges "
                                         "that the preparation removed as mixed pixels (prepare.mixed_pixels).")
        self.checkbox.on_update(lambda _: host.set_view(show_mixed=bool(self.checkbox.value)))

    def show_view(self, view: ViewState, snap: Snapshot) -> None:
        # viser's checkbox redeclares `value` with a getter only; the base class's setter applies.
        self.checkbox.value = view.show_mixed  # type: ignore[misc]


STAGE = AppStage(
    "prepare",
    StageView(
        None,
        explanation="Each station's points in its own scanner frame (scan 1 green, 2 red, 3 blue, as in the paper); "
            "the axes mark the scanners (before registration they all sit at the origin). Scan 1 is the "
            "reference: every other scan is registered onto it (2 → 1, 3 → 1). The paper's trees hold no ground; "
            "real scans do, and ground fills the projection images and pulls the rotation centre off the stem, "
            "so treereg removes it (grey) before projection, and a crop can keep the tree alone. Where a beam straddles "
            "a stem's edge, the range lands between the edge and what lies behind (a mixed pixel): every silhouette "
            "trails a comet tail. Those returns, just behind a range jump with no neighbour at their own range, are "
            "removed first (near-black).",
    ),
    draw=render,
    view_fields=(),
    needs_output=False,
    controls=(MixedControl,),
    tour=(
        TourStep(
            "prepare", "One tree, several stations",
            "A terrestrial scanner sees one side of a tree, so the tree is scanned from several stations, each scan in "
            "its own frame with the scanner at the origin. Registration finds the rigid transforms that bring scans 2, "
            "3, … onto scan 1, here from the tree itself instead of targets placed in the forest.",
            "Rotate the view with the mouse: the stations' trees stand apart. In the *Scans* tab, untick a scan to see "
            "what one station saw.",
            view={"panel": "stage"}, highlight="trees"),
    ),
)
