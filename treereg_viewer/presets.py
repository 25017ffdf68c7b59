"""What each parameter preset is, what it changes against the default, and where it breaks.

Shown under the preset selector (Files tab) and in the message when a preset is applied, so a
user who loads the paper's settings and sees a scan come out upside down knows why.
"""

from __future__ import annotations

from typing import Any

from treereg_core import params as P

from .draw.common import md_table

def _about_robust(p: P.Params) -> str:
    return (
        f"treereg's defaults: the ground is {'removed' if p.prepare.remove_ground else 'kept'}, azimuth is "
        f"measured from the tree's direction (no wrap at ±180°), ORB sees "
        f"{'a grey distance ramp around the occupied pixels' if p.matching.image_mode == 'ramp' else 'the binary image'}, "
        f"{p.matching.n_pairs} image pairs with up to {p.matching.matches_per_pair} matches each, "
        f"{p.coarse.estimator.upper()} ({p.coarse.dof} DOF{', then a full refit' if p.coarse.refit_6dof else ''}) "
        f"for the coarse transform, {len(p.slices.quantiles)} slices, and a fine update"
        f"{' that is kept only when it improves the alignment' if p.acceptance.test else ''}."
    )


def _about_paper(p: P.Params) -> str:
    # The weaknesses are those seen on the bundled demo (a scan turned upside down, one rotated 146 deg).
    return (
        f"The paper's settings taken literally (2.1-2.2, 4.1): ground {'removed' if p.prepare.remove_ground else 'kept'}, "
        f"{p.matching.n_pairs} image pairs with the {p.matching.matches_per_pair} best ORB matches each"
        f"{', checked by β' if p.matching.beta_check else ''}, one {p.coarse.estimator.upper()} over all "
        f"{p.matching.n_pairs * p.matching.matches_per_pair} or fewer tie points ({p.coarse.dof} DOF), "
        f"{len(p.slices.quantiles)} slices, {p.fine.max_iterations} fine iteration(s)"
        f"{'' if p.acceptance.test else ' without an acceptance test'}.\n\n"
        "**Why it often fails:** with so few tie points a few wrong matches, unavoidable on binary images "
        "(paper 4.1), pull the SVD far off; nothing rejects them, so a scan can come out rotated or even "
        "upside down, and the fine stage, which needs a close start, cannot repair it. Ground left in the "
        "scans also fills the projection images. The app marks such transforms with ⚠ (stages 3 and 7). "
        "To recover, set `coarse.estimator` to `ransac`, or apply the robust preset."
    )


#: One paragraph per preset, from the preset's own values.
ABOUT = {"robust": _about_robust, "paper": _about_paper}


#: One sentence for the message line when a preset is applied.
ABOUT_SHORT: dict[str, str] = {
    "paper": ("The paper's literal settings often give a wrong coarse transform (few tie points, no outlier "
              "rejection): the Files tab says why; ✗ marks a failed registration, ⚠ an unverified one."),
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
    text = ABOUT[name](P.PRESETS[name]) if name in ABOUT else ""
    diff = differences(name) if name != "robust" else []
    if diff:
        text += f"\n\nIt changes {len(diff)} parameters:\n\n" + md_table(("parameter", "robust", name), diff)
    return text
