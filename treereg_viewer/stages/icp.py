"""The ICP stage: IcpResult, the baseline the paper compares its fine stage with (3.3).

The scan layer shows every target at its ICP pose; the panel says how ICP ended for each pair and
how far its pose lies from the fine one (`rigid.rotation_error_deg`, `rigid.mean_displacement`: this only
compares two results).
"""

from __future__ import annotations

import viser

from treereg_core.evaluate.icp import IcpResult
from treereg_core.geometry.rigid import mean_displacement, rotation_error_deg

from ..controller import Snapshot
from ..draw.common import Drawing, md_table, metrics_table, pair_label, target_index, target_pose, title
from ..view_panel import PanelContent
from ..text import md, md_sentence
from ..view_state import ViewState
from .base import AppStage, StageView, TargetControl, TourStep


def render(scene: viser.SceneApi, root: str, snap: Snapshot, view: ViewState) -> Drawing:
    out = snap.output("icp")
    t = target_index(snap, "icp", view)
    item = snap.pair(t).item("icp", IcpResult)
    assert out is not None and item is not None, t  # the drawer draws a pair that was not skipped
    if not item.ran:
        return [], PanelContent(title("icp", snap, t), text=md_sentence(item.message))
    text = (f"{md(pair_label(snap, t))}: ICP ({snap.params.icp.method.replace('_', '-')}) "
            + (f"converged after {item.iterations} iterations" if item.converged else
               f"did not converge: stopped at icp.max_iterations = {snap.params.icp.max_iterations}")
            + f"{'' if item.ok else f' — {md(item.message)}'}. Every target is shown at its ICP pose.")
    rows = []
    for k in range(len(out.items)):
        pair, fine = snap.pair(k), target_pose(snap, "fine", k)
        it, scans = pair.item("icp", IcpResult), pair.prepared()
        if it is None or not (it.ok and it.ran) or fine is None or scans is None:
            continue
        if pair.ref != 0:  # the ICP-vs-fine table is about the reference's pairs
            continue
        pts = scans[1].points
        gap = mean_displacement(it.T_ref_target, fine, pts)
        rows.append((md(pair_label(snap, k)), f"{rotation_error_deg(it.T_ref_target, fine):.3f}", f"{gap * 1000:.1f}"))
    table = md_table(("pair", "ICP vs fine: rotation (°)", "mean point distance (mm)"), rows)
    table += "\n\n" + metrics_table({pair_label(snap, k): it.metrics for k, it in enumerate(out.items)})
    return [], PanelContent(title("icp", snap, t), text=text, table=table)


STAGE = AppStage(
    "icp",
    StageView(
        "icp",
        explanation="The paper compares its fine stage with ICP (iterative closest point) started from the coarse "
            "result (3.3): every target point pairs with its nearest reference point and the pose that brings "
            "the pairs together is solved again and again. On trees two stations see different sides of a "
            "branch, so the nearest point is often the wrong one.",
    ),
    draw=render,
    view_fields=("target",),
    controls=(TargetControl,),
    tour=(
        TourStep(
            "icp", "The ICP baseline",
            "The paper compares its fine stage with ICP started from the coarse result (3.3). On a tree two stations see "
            "different sides of a branch, so the nearest point is often the wrong partner.",
            "Choose *9 Fine*, then *12 ICP* under *Stage*, and watch the scans move.",
            view={"panel": "stage"}),
    ),
)
