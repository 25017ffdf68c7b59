"""The Projection stage: ImageSequence — every scan's binary image at one step of its rotation.

The panel shows all scans' images at the chosen step, one under the other in the scans' colours.
In 3-D, optionally, each prepared cloud rotated as it was for that image (a pose on its node:
`ImageSequence.rotation`).
"""

from __future__ import annotations

import numpy as np
import viser

from treereg_core.coarse.sequences import ImageSequence
from treereg_core.prepare.ground import PreparedScan

from ..controller import Snapshot
from ..draw.common import Drawing, Handles, display_subset, metrics_table, pose_kwargs, title
from ..draw.images import binary_to_rgb, fit_factor, fit_width, hstack, upscale, vstack
from ..palette import scan_color
from ..view_panel import PanelContent
from ..text import md
from ..view_state import ViewState
from .base import AppStage, ControlHost, StageControls, StageView, TourStep


def step_index(seq: ImageSequence, step: int) -> int:
    """The view's step, clamped to this sequence (sequences of different scans may differ in length)."""
    return int(np.clip(step, 0, len(seq.angles_deg) - 1))


def render(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> Drawing:
    out = snap.output("projection")
    assert out is not None  # the drawer draws a stage that has an output
    seqs = out.items
    tiles: list[np.ndarray] = []
    names: list[str] = []
    handles: Handles = []
    prepared = snap.output("prepare")
    for i in range(len(seqs)):
        # A scan that could not be prepared has a Skipped item (not ok), drawn as nothing.
        seq = snap.scan_item("projection", i, ImageSequence)
        if seq is None or not seq.ok or not len(seq.angles_deg):
            continue
        k = step_index(seq, view.projection_step)
        tiles.append(binary_to_rgb(seq.images[k], scan_color(i)))
        names.append(f"{md(seq.scan_name)} ({seq.angles_deg[k]:+.0f}°)")
        if view.projection_3d and prepared is not None:
            pts = prepared.item(i, PreparedScan).scan.points
            idx = display_subset(len(pts), view.max_points, seed=100 + i)
            r, g, b = scan_color(i)
            light = (int(0.5 * r + 127), int(0.5 * g + 127), int(0.5 * b + 127))
            pose = pose_kwargs(seq.rotation(k))
            handles.append(scene.add_point_cloud(
                f"{root}/rotated{i}", pts[idx], light, point_size=view.point_size,
                point_shape="circle", precision="float32", wxyz=pose["wxyz"], position=pose["position"],
            ))
            handles.append(scene.add_frame(
                f"{root}/axis{i}", axes_length=0.6, axes_radius=0.03,
                position=(seq.centre_xy[0], seq.centre_xy[1], 0.0),
            ))
    first = out.item(0, ImageSequence)  # the reference's: never skipped (the run stops without it)
    k0 = step_index(first, view.projection_step)
    images: list[tuple[np.ndarray, str]] = []
    if tiles:
        # Tree images are tall and narrow: side by side unless that makes a very wide strip.
        side = sum(t.shape[1] for t in tiles) <= 2 * max(t.shape[0] for t in tiles)
        width = sum(t.shape[1] + 12 for t in tiles) if side else max(t.shape[1] for t in tiles)
        k = fit_factor(width)
        tiles = [upscale(t, k) for t in tiles]
        lay = hstack(tiles, gap=12) if side else vstack(tiles, gap=12)
        images.append((fit_width(lay.image), ("Left to right: " if side else "Top to bottom: ") + ", ".join(names)))
    pp = snap.params.projection
    span = f"{first.angles_deg[0]:+.0f}° to {first.angles_deg[-1]:+.0f}°" if len(first.angles_deg) else "no span"
    text = (
        f"Step {k0 + 1} of {len(first.angles_deg)}: points rotated by {first.angles_deg[k0]:+.1f}° about the "
        f"vertical axis through each scan's centre (steps θ = {pp.theta_deg:g}°, projection.theta_deg; from {span}). "
        f"A pixel covers {pp.pixel_factor:g} angular steps each way (projection.pixel_factor). Black in the paper, "
        "here each scan's colour: pixels holding points; white: empty pixels. Shown upright, as seen from the scanner."
    )
    bad = [f"**{md(snap.scans[i].name)}:** {md(it.message)}" for i, it in enumerate(seqs) if not it.ok]
    if bad:
        text += "\n\n" + "\n\n".join(bad)
    # A scan that could not be prepared has a Skipped item here, named by its scan.
    table = metrics_table({scan.name: s.metrics for scan, s in zip(snap.scans, seqs)})
    return handles, PanelContent(title("projection"), text=text, images=tuple(images), table=table)


class StepControls(StageControls):
    """"Rotation step" (counted from 1, as the panel's "Step k of n" reads) and "Show rotated clouds in 3-D"."""

    def __init__(self, gui: viser.GuiApi, host: ControlHost, stage: str) -> None:
        self.host = host
        self.slider = gui.add_slider("Rotation step", 1, 2, 1, 1,
                                     hint="Walk the rotation sequence (the angle is shown in the panel).")
        self.slider.on_update(lambda _: host.set_view(projection_step=int(self.slider.value) - 1))
        self.in_3d = gui.add_checkbox("Show rotated clouds in 3-D", False)
        self.in_3d.on_update(lambda _: host.set_view(projection_3d=bool(self.in_3d.value)))

    def show_view(self, view: ViewState, snap: Snapshot) -> None:
        step = view.projection_step + 1
        if self.slider.value != step and step <= self.slider.max:
            # viser's slider and checkbox redeclare `value` with a getter only; the base class's setter applies.
            self.slider.value = step  # type: ignore[misc]
        self.in_3d.value = view.projection_3d  # type: ignore[misc]

    def show_snapshot(self, snap: Snapshot, view: ViewState) -> None:
        proj = snap.output("projection")
        if proj is None or not proj.items:
            return
        seqs = [snap.scan_item("projection", i, ImageSequence) for i in range(len(proj.items))]
        n = max(len(s.angles_deg) if s is not None else 0 for s in seqs)
        if n > 1 and self.slider.max != n:
            zero = next((k for k, a in enumerate(proj.item(0, ImageSequence).angles_deg) if abs(a) < 1e-9), 0)
            self.slider.max = n
            self.slider.value = min(zero, n - 1) + 1  # type: ignore[misc]  # viser: a getter only, as above
            # A new sequence starts at the unrotated view: the view follows, even while the panel is quiet.
            self.host.app.set_view(projection_step=min(zero, n - 1))


STAGE = AppStage(
    "projection",
    StageView(
        None,
        explanation="Each scan is projected onto a sphere around its scanner: a pixel covers k·φ × k·ϕ of azimuth α and "
            "elevation β (φ, ϕ: the instrument's angular steps; paper: k = 2) and is black when any point falls "
            "in it (eq. 2-3). Two stations see the tree from different sides, so their images differ; the paper "
            "therefore rotates each cloud about the vertical axis through its mean (x̄, ȳ) in steps θ (paper: 10°; "
            "the value in force is in the panel and under Parameters) from −360°/n to +360°/n (n scans) and projects again, giving a sequence of views (2.1.2). "
            "The slider walks the sequence.",
    ),
    draw=render,
    view_fields=("projection_step", "projection_3d", "point_size", "max_points"),
    controls=(StepControls,),
    tour=(
        TourStep(
            "projection", "Rotating projection",
            "Each scan is projected onto a sphere around its scanner into a binary image: a pixel is black when a point "
            "falls into it (paper 2.1.1). Two stations see the tree from different sides, so the paper turns each cloud "
            "about the vertical axis in steps of θ (paper: 10°) and projects it again (2.1.2).",
            "Move *Rotation step* (Stage tab) and watch each scan's image change as its tree turns.",
            view={"panel": "stage"}),
    ),
)
