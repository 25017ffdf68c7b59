"""The Projection stage: ImageSequence — every scan's binary image at one step of its rotation.

The panel shows all scans' images at the chosen step, one under the other in the scans' colours.
In 3-D, optionally, each prepared cloud rotated as it was for that image (a pose on its node:
`ImageSequence.rotation`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import viser

from ..controller import Snapshot
from ..drawing import binary_to_rgb, fit_factor, fit_width, hstack, upscale, vstack
from ..palette import scan_color
from ..view_panel import PanelContent
from ..view_state import ViewState
from .common import Drawing, display_subset, metrics_table, pose_kwargs, title


def step_index(seq: Any, step: int) -> int:
    """The view's step, clamped to this sequence (sequences of different scans may differ in length)."""
    return int(np.clip(step, 0, len(seq.angles_deg) - 1))


def render(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> Drawing:
    seqs = snap.output("projection").items
    tiles, names = [], []
    handles: list[Any] = []
    prepared = snap.output("prepare")
    for i, seq in enumerate(seqs):
        if not getattr(seq, "ok", True) or not len(seq.angles_deg):
            continue
        k = step_index(seq, view.projection_step)
        tiles.append(binary_to_rgb(seq.images[k], scan_color(i)))
        names.append(f"{seq.scan_name} ({seq.angles_deg[k]:+.0f}°)")
        if view.projection_3d and prepared is not None:
            pts = prepared.items[i].scan.points
            idx = display_subset(len(pts), view.max_points, seed=100 + i)
            light = tuple(int(0.5 * c + 127) for c in scan_color(i))
            handles.append(scene.add_point_cloud(
                f"{root}/rotated{i}", pts[idx], light, point_size=view.point_size,
                point_shape="circle", precision="float32", **pose_kwargs(seq.rotation(k)),
            ))
            handles.append(scene.add_frame(
                f"{root}/axis{i}", axes_length=0.6, axes_radius=0.03,
                position=(seq.centre_xy[0], seq.centre_xy[1], 0.0),
            ))
    first = seqs[0]
    k0 = step_index(first, view.projection_step)
    images = []
    if tiles:
        # Tree images are tall and narrow: side by side unless that makes a very wide strip.
        side = sum(t.shape[1] for t in tiles) <= 2 * max(t.shape[0] for t in tiles)
        width = sum(t.shape[1] + 12 for t in tiles) if side else max(t.shape[1] for t in tiles)
        k = fit_factor(width)
        tiles = [upscale(t, k) for t in tiles]
        lay = hstack(tiles, gap=12) if side else vstack(tiles, gap=12)
        images.append((fit_width(lay.image), ("Left to right: " if side else "Top to bottom: ") + ", ".join(names)))
    text = (
        f"Step {k0 + 1} of {len(first.angles_deg)}: points rotated by θ = {first.angles_deg[k0]:+.1f}° about the "
        f"vertical axis through each scan's centre. Black in the paper, here each scan's colour: pixels holding "
        f"points; white: empty pixels. Shown upright, as seen from the scanner."
    )
    bad = [f"**{snap.scans[i].name}:** {it.message}" for i, it in enumerate(seqs) if not getattr(it, "ok", True)]
    if bad:
        text += "\n\n" + "\n\n".join(bad)
    table = metrics_table({s.scan_name: s.metrics for s in seqs})
    return handles, PanelContent(title("projection"), text=text, images=tuple(images), table=table)


#: The view choices this drawing depends on (it is redrawn when one of them changes).
VIEW_FIELDS = ("projection_step", "projection_3d", "point_size", "max_points")
