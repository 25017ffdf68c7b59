"""Warnings the app reads off finished results: a stage can succeed and still be wrong.

Coarse registration by SVD over all tie points (the paper's setting) always returns a transform,
even when wrong matches dominate and the scan comes out upside down; the stage is then "done" but
the registration has failed. These checks only read results (transforms, counts, errors against
truth); they compute no geometry. The app marks the stage with ⚠ and says why.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .controller import Snapshot

#: A coarse transform tilting a scan more than this is wrong: TLS instruments stand roughly level
#: (a few degrees off at most; the simulator's worst case is 10 degrees per instrument).
MAX_PLAUSIBLE_TILT_DEG = 30.0
#: Errors against truth beyond these mean the registration failed (the fine stage aims at
#: well under 0.5 deg and 3 cm).
TRUTH_ROT_DEG = 1.0
TRUTH_DISP_M = 0.05


def tilt_deg(T: np.ndarray) -> float:
    """How far a rigid transform tips the vertical axis, in degrees."""
    return float(np.degrees(np.arccos(np.clip(np.asarray(T, dtype=float)[2, 2], -1.0, 1.0))))


def _pair(snap: Snapshot, k: int) -> str:
    return f"{snap.scans[k + 1].name} → {snap.scans[0].name}" if k + 1 < len(snap.scans) else f"target {k + 1}"


def coarse_warnings(snap: Snapshot) -> list[str]:
    """One sentence per successful coarse transform that is implausible, saying what to change."""
    out = snap.output("coarse")
    if out is None:
        return []
    p = snap.params.coarse
    advice = ("SVD over all tie points has no defence against wrong matches: set coarse.estimator to ransac"
              if p.estimator == "svd" else
              "try more image pairs or matches per pair (matching), or removing the ground (prepare)")
    notes = []
    for k, c in enumerate(out.items):
        if not c.ok:
            continue
        why = []
        tilt = tilt_deg(c.T_ref_target)
        if tilt > MAX_PLAUSIBLE_TILT_DEG:
            why.append(f"it tilts the scan by {tilt:.0f}° (scanners stand nearly level)")
        if c.n_ties and c.n_inliers < p.min_ties:
            why.append(f"only {c.n_inliers} of {c.n_ties} tie points agree with it within {p.inlier_m:g} m")
        if why:
            notes.append(f"{_pair(snap, k)}: the coarse transform is probably wrong — {'; '.join(why)}. {advice}.")
    return notes


def truth_rows(snap: Snapshot, names_only: bool = False) -> list[tuple[str, str, float, float, bool]]:
    """(pair, registration, rotation error deg, mean displacement m, within tolerance) per known truth.

    With `names_only` the first column is the target's name alone (a narrow table column).
    """
    out = snap.output("evaluation")
    if out is None or not snap.truth:
        return []
    rows = []
    for k, rep in enumerate(out.items):
        for label, ev in (("coarse", rep.coarse), ("fine", rep.fine), ("ICP", getattr(rep, "icp_eval", None))):
            if ev is None or ev.rotation_error_deg is None or ev.mean_displacement_m is None:
                continue
            rot, disp = float(ev.rotation_error_deg), float(ev.mean_displacement_m)
            rows.append((snap.scans[k + 1].name if names_only else _pair(snap, k), label, rot, disp, rot <= TRUTH_ROT_DEG and disp <= TRUTH_DISP_M))
    return rows


def truth_warnings(snap: Snapshot) -> list[str]:
    """One sentence per target whose final (fine) transform is far from the known truth."""
    return [
        f"{pair}: the final transform is {rot:.3g}° and {disp:.3g} m from the truth — the registration failed."
        for pair, label, rot, disp, good in truth_rows(snap) if label == "fine" and not good
    ]


def stage_warnings(snap: Snapshot) -> dict[str, list[str]]:
    """Warnings by pipeline stage ('coarse', 'evaluation'), only for stages that are done."""
    found = {}
    if snap.status("coarse") == "done" and (w := coarse_warnings(snap)):
        found["coarse"] = w
    if snap.status("evaluation") == "done" and (w := truth_warnings(snap)):
        found["evaluation"] = w
    return found
