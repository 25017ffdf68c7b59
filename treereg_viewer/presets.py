"""What each parameter preset is, what it changes against the default, and where it breaks.

Shown under the preset selector (Files tab) and in the message when a preset is applied, so a
user who loads the paper's settings and sees a scan come out upside down knows why.
"""

from __future__ import annotations

from typing import Any

from treereg_core import params as P

from .renderers.common import md_table

#: One paragraph per preset. The paper preset's weaknesses are those seen on the bundled demo.
ABOUT: dict[str, str] = {
    "robust": (
        "treereg's defaults: the ground is removed, azimuth is measured from the tree's direction (no wrap "
        "at ±180°), ORB sees a grey distance ramp, 15 image pairs with up to 60 matches each, RANSAC (yaw and "
        "translation, then a full refit) for the coarse transform, 19 slices, and a fine update that is "
        "kept only when it improves the alignment."
    ),
    "paper": (
        "The paper's settings taken literally (2.1-2.2, 4.1): ground kept, 3 image pairs with the 5 best "
        "ORB matches each, checked by β, one SVD over all 15 or so tie points (6 DOF), slices at the "
        "quartiles, one fine SVD without an acceptance test.\n\n"
        "**Why it often fails:** with so few tie points a few wrong matches, unavoidable on binary images "
        "(paper 4.1), pull the SVD far off; nothing rejects them, so a scan can come out rotated or even "
        "upside down, and the fine stage, which needs a close start, cannot repair it. Ground left in the "
        "scans also fills the projection images. The app marks such transforms with ⚠ (stages 3 and 7). "
        "To recover, set `coarse.estimator` to `ransac`, or apply the robust preset."
    ),
}


#: One sentence for the message line when a preset is applied.
ABOUT_SHORT: dict[str, str] = {
    "paper": ("The paper's literal settings often give a wrong coarse transform (few tie points, no outlier "
              "rejection): the Files tab says why; ⚠ marks a failed registration."),
}


def _fmt(v: Any) -> str:
    if isinstance(v, list):
        return ", ".join(f"{x:g}" if isinstance(x, float) else str(x) for x in v) if len(v) <= 4 else \
            f"{len(v)} values, {v[0]:g} … {v[-1]:g}"
    return "none" if v is None else str(v)


def differences(name: str, base: str = "robust") -> list[tuple[str, str, str]]:
    """(section.field, value in `base`, value in `name`) for every field the two presets set differently."""
    a, b = P.to_dict(P.PRESETS[base]), P.to_dict(P.PRESETS[name])
    return [(f"{s}.{k}", _fmt(a[s][k]), _fmt(b[s][k])) for s in a for k in a[s] if a[s][k] != b[s][k]]


def preset_note(name: str) -> str:
    """Markdown: what the preset is and, for other than the default, what it changes."""
    text = ABOUT.get(name, "")
    diff = differences(name) if name != "robust" else []
    if diff:
        text += f"\n\nIt changes {len(diff)} parameters:\n\n" + md_table(("parameter", "robust", name), diff)
    return text
