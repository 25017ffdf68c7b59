"""The sections stage (paper 2.2.3): every arc fitted by a circle or a cylinder, and the sections
of the target paired with those of the reference.

The lowest slice's arcs are fitted by Taubin circles (the trunk), the others by cylinders; the
paper's 4.2 taper check drops a part wider than the part below it. A target arc is fitted only
when a plausible reference section of the same slice lies within reach (leaves and twigs with no
counterpart cost no fit). Corresponding sections become the fine stage's tie points: a circle's
centre; a cylinder's axis point at the slice height and the point one unit further towards +z.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Sequence, TypeVar

import numpy as np

from ..geometry.rigid import apply_transform
from ..params import ArcParams, SectionsParams, SlicesParams
from ..results import Metric
from ..scan import Scan
from .arcs import ArcResult, SliceArcs, separate_slices
from .correspondence import Correspondences, match_sections
from .fitting import Section, check_taper, fit_section, unfitted_section
from .slicing import SliceResult, slice_scans


@dataclass(frozen=True, kw_only=True)
class ScanSections:
    """Fitted sections of one scan (in the reference frame), and each section's point indices."""

    sections: tuple[Section, ...]
    members: tuple[np.ndarray, ...]

    @property
    def n_plausible(self) -> int:
        return int(sum(s.plausible for s in self.sections))


@dataclass(frozen=True, kw_only=True)
class SectionsResult:
    """The sections stage's result for one pair (or the fine stage's, at its final pose).

    Attributes
    ----------
    ok, message, metrics
        As every stage result; ok whenever the fits ran (too few corresponding sections is for the
        fine stage to handle: it then aligns the surfaces), the message says when none correspond.
    T_ref_target
        The pose the target's sections were fitted at.
    ref, tgt
        Sections of the reference and of the target (reference frame).
    correspondences
        Pairs (index into ref.sections, index into tgt.sections).
    tie_points_ref, tie_points_tgt
        K x 3 tie points of the corresponding sections (paper 2.2.3), reference frame.
    """

    ok: bool
    message: str
    metrics: tuple[Metric, ...]
    T_ref_target: np.ndarray
    ref: ScanSections
    tgt: ScanSections
    correspondences: Correspondences
    tie_points_ref: np.ndarray
    tie_points_tgt: np.ndarray

    @property
    def n_pairs(self) -> int:
        return int(len(self.correspondences.pairs))


def fit_scan_sections(scan: Scan, arcs: Sequence[ArcResult], heights: np.ndarray, T: np.ndarray, p: SectionsParams,
                      guide: ScanSections | None = None) -> ScanSections:
    """Fit every arc of every slice of `scan` (points mapped by `T` into the reference frame).

    With a `guide` (the other scan's sections), an arc is fitted only if its centroid lies within
    reach of a plausible guide section of the same slice (the gate plus three radii: the centroid
    of a visible arc sits up to a radius from the centre); the others get an unfitted, implausible
    section.
    """
    sections: list[Section] = []
    members: list[np.ndarray] = []
    near: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    if guide is not None:
        for s in guide.sections:
            if s.plausible:
                c, r = near.get(s.slice_index, (np.empty((0, 3)), np.empty(0)))
                near[s.slice_index] = (np.vstack([c, s.centre_m]), np.r_[r, s.radius_m])
    for k, (ar, h) in enumerate(zip(arcs, heights)):
        circle = p.circle_lowest and k == 0
        for j, members_j in enumerate(ar.arcs()):
            pts = apply_transform(T, scan.points[members_j])
            members.append(members_j)
            if guide is not None:
                c, r = near.get(k, (np.empty((0, 3)), np.empty(0)))
                d = np.linalg.norm(c[:, :2] - pts[:, :2].mean(axis=0), axis=1)
                if not np.any(d <= p.gate_m + 3.0 * r):
                    sections.append(unfitted_section(len(pts), k, j, float(h), "no section of the other scan nearby"))
                    continue
            sections.append(fit_section(pts, k, j, float(h), circle, p))
    if p.taper_check:
        sections = check_taper(sections, p.taper_tolerance, p.gate_m)
    return ScanSections(sections=tuple(sections), members=tuple(members))


def match_scan_sections(ref: ScanSections, tgt: ScanSections, p: SectionsParams, gate_m: float | None = None) -> Correspondences:
    """Pair plausible sections of the two scans, slice by slice, nearest centres within the gate."""
    ri = np.array([i for i, s in enumerate(ref.sections) if s.plausible], dtype=np.int64)
    ti = np.array([i for i, s in enumerate(tgt.sections) if s.plausible], dtype=np.int64)
    rc = np.array([ref.sections[i].centre_m for i in ri]).reshape(-1, 3)
    tc = np.array([tgt.sections[i].centre_m for i in ti]).reshape(-1, 3)
    rg = np.array([ref.sections[i].slice_index for i in ri])
    tg = np.array([tgt.sections[i].slice_index for i in ti])
    rr = np.array([ref.sections[i].radius_m for i in ri])
    tr = np.array([tgt.sections[i].radius_m for i in ti])
    c = match_sections(rc, tc, p.gate_m if gate_m is None else gate_m, rg, tg, rr, tr, p.max_radius_ratio)
    if c.ok:
        c = Correspondences(c.ok, c.message, c.metrics, np.c_[ri[c.pairs[:, 0]], ti[c.pairs[:, 1]]], c.distances_m)
    return c


def section_tie_points(s: Section) -> np.ndarray:
    """Paper 2.2.3: a circle's centre; a cylinder's axis point and the point one unit further towards +z."""
    if s.kind == "circle":
        return s.centre_m[None, :]
    return np.vstack([s.centre_m, s.centre_m + s.axis])


def tie_points(ref: ScanSections, tgt: ScanSections, corr: Correspondences) -> tuple[np.ndarray, np.ndarray]:
    """The tie points of every corresponding pair of sections (reference's, target's)."""
    a, b = [], []
    if corr.ok:
        for i, j in corr.pairs:
            ta, tb = section_tie_points(ref.sections[i]), section_tie_points(tgt.sections[j])
            n = min(len(ta), len(tb))
            a.append(ta[:n])
            b.append(tb[:n])
    return (np.vstack(a), np.vstack(b)) if a else (np.empty((0, 3)), np.empty((0, 3)))


def sections_at(ref_scan: Scan, tgt_scan: Scan, ref: ScanSections, tgt_arcs: Sequence[ArcResult], heights: np.ndarray,
                T_ref_target: np.ndarray, p: SectionsParams) -> SectionsResult:
    """The target's sections at the pose `T_ref_target`, paired with the reference's `ref`."""
    T = np.asarray(T_ref_target, dtype=float)
    tgt = fit_scan_sections(tgt_scan, tgt_arcs, heights, T, p, guide=ref)
    corr = match_scan_sections(ref, tgt, p)
    ties_r, ties_t = tie_points(ref, tgt, corr)
    metrics = (
        Metric("sections fitted, reference", "", len(ref.sections)),
        Metric("plausible sections, reference", "", ref.n_plausible),
        Metric("sections fitted, target", "", len(tgt.sections)),
        Metric("plausible sections, target", "", tgt.n_plausible),
        Metric("corresponding sections", "", int(len(corr.pairs))),
        Metric("tie points", "", int(len(ties_r))),
    )
    message = "" if corr.ok else (f"no corresponding sections ({corr.message}): the fine stage will align the "
                                  "surfaces instead")
    return SectionsResult(ok=True, message=message, metrics=metrics, T_ref_target=T, ref=ref, tgt=tgt, correspondences=corr,
                          tie_points_ref=ties_r, tie_points_tgt=ties_t)


def fit_sections(ref_scan: Scan, tgt_scan: Scan, ref_arcs: Sequence[ArcResult], tgt_arcs: Sequence[ArcResult],
                 heights: np.ndarray, T_ref_target: np.ndarray, *, sections: SectionsParams,
                 ref_sections: ScanSections | None = None) -> SectionsResult:
    """The sections stage: fit both scans' arcs and pair the sections.

    `ref_sections` passes the reference's sections when already fitted (they depend on the
    reference alone, so several targets share them).
    """
    ref = ref_sections if ref_sections is not None else fit_scan_sections(ref_scan, ref_arcs, heights, np.eye(4), sections)
    return sections_at(ref_scan, tgt_scan, ref, tgt_arcs, heights, T_ref_target, sections)


@dataclass(frozen=True, kw_only=True)
class PoseFit:
    """Slices, arcs and sections of one pair at one pose (`sections.T_ref_target`): what the slices,
    arcs and sections stages make at the start pose, and what each fine iteration makes again.

    `arcs` and `sections` are None when not made: the slicing failed (`slices.message` says why),
    or `fit_at_pose` was asked to stop before them.
    """

    slices: SliceResult
    arcs: SliceArcs | None = None
    sections: SectionsResult | None = None


# Eleven parameters, all but the pose keyword-only: the three stages' sections plus the work already
# done (by the stage before, by an earlier iteration, or for the reference once) that it must not redo.
def fit_at_pose(ref: Scan, tgt: Scan, T_ref_target: np.ndarray, *, slices: SlicesParams | None,
                arcs: ArcParams | None, sections: SectionsParams | None, done: PoseFit | None = None,
                ref_arcs: tuple[ArcResult, ...] | None = None, ref_sections: ScanSections | None = None,
                seen: Scan | None = None, until: Literal["slices", "arcs", "sections"] = "sections") -> PoseFit:
    """Slice both scans at the pose `T_ref_target`, separate the slices into arcs and fit the arcs
    (paper 2.2.1-2.2.3): the one place the three steps are chained, for the stages and the fine
    stage's iterations.

    Parameters
    ----------
    ref, tgt
        Reference and target scans (each in its scanner frame); the target's arcs are separated on
        its own angular grid.
    T_ref_target
        The pose the target is sliced and fitted at.
    slices, arcs, sections
        The three stages' parameter sections; None for a step given in `done` or after `until` (a
        stage passes only the sections it reads).
    done
        Steps already made (a stage's upstream results): only the rest is computed.
    ref_arcs, ref_sections
        The reference's arcs and sections when already known (shared by all its pairs, and the same
        at every pose: the reference's slices do not move).
    seen
        The target as sliced and fitted, when not `tgt` itself (the target unbent, `Bend.warp`).
    until
        The last step made.
    """
    seen = tgt if seen is None else seen
    T = np.asarray(T_ref_target, dtype=float)
    sl = done.slices if done is not None else slice_scans(ref, seen, T, slices=_given(slices, "slices"))
    if until == "slices" or not sl.ok:
        return PoseFit(slices=sl)
    ar = done.arcs if done is not None and done.arcs is not None else separate_slices(
        ref, tgt, sl.ref_indices, sl.tgt_indices, arcs=_given(arcs, "arcs"), ref_arcs=ref_arcs)
    if until == "arcs":
        return PoseFit(slices=sl, arcs=ar)
    return PoseFit(slices=sl, arcs=ar, sections=fit_sections(ref, seen, ar.ref, ar.tgt, sl.heights_m, T,
                                                             sections=_given(sections, "sections"),
                                                             ref_sections=ref_sections))


P = TypeVar("P")


def _given(section: P | None, name: str) -> P:
    if section is None:
        raise ValueError(f"fit_at_pose: the {name} step is made here, but its parameter section was not given")
    return section
