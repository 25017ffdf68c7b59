"""The paper's evaluation model (3.3, eq. 8) and, where truth is known, errors against it.

Paper: for corresponding branches of two scans, three layers are sliced from each branch (bottom,
middle, top); a cylinder is fitted to each layer in each scan; on the two axes the points at the
layer's height are taken, and their distances d1..dn averaged: d = (d1 + ... + dn) / n (eq. 8),
per branch (Figs. 13-14) and overall (Table 2).

The paper picked its branches by hand. Here they are found in the reference scan: at a few
heights, the reference is sliced and its arcs fitted; every plausible cylinder whose axis is not
near-horizontal (where "the axis point at height z" is ill-defined) is a branch. Its layers are
slabs at heights around that slice; each layer takes the points of either scan within the
branch's radius plus a margin of the branch's axis. Which target points belong to the branch is
decided under the true transform when it is given (as a person picking branches would), otherwise
under the transform being evaluated — then a branch the transform misses by more than the margin
drops out, and the count of branches says so.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..fine.arcs import separate_arcs
from ..fine.fitting import CylinderFit, fit_cylinder
from ..params import ArcParams, EvaluationParams
from ..results import Metric
from ..geometry.rigid import apply_transform, mean_displacement, rotation_error_deg
from ..scan import Scan
from ..fine.slicing import tree_extent

#: Branch axes flatter than this (|axis_z|) have no well-defined point at a given height.
_MIN_AXIS_Z = 0.3
#: Fewest points of a layer per scan for a cylinder fit.
_MIN_LAYER_POINTS = 12
#: A layer's fit must agree with its branch: radius within this factor, axis within acos(_MIN_AXIS_COS).
_MAX_RADIUS_RATIO = 1.3
_MIN_AXIS_COS = float(np.cos(np.radians(20.0)))


@dataclass(frozen=True)
class BranchError:
    """The evaluation of one branch: its layers and the distances of their centre points.

    Attributes
    ----------
    index
        Branch number: its place among the branches found in the reference (bottom to top), the same
        in the evaluation of every transform.
    height_m
        Height of the branch's middle layer (reference frame).
    radius_m
        Radius fitted to the reference's middle layer.
    layer_z_m
        Height of each evaluated layer.
    ref_centres_m, tgt_centres_m
        Axis points at each layer height: of the reference's fit and of the target's fit (target
        mapped by the evaluated transform), reference frame.
    distances_m
        d_i per layer.
    point_m, axis
        The branch as found in the reference: a point of its axis at the middle layer's height and
        the unit axis direction (where its cross-sections are seen from).
    """

    index: int
    height_m: float
    radius_m: float
    layer_z_m: np.ndarray
    ref_centres_m: np.ndarray
    tgt_centres_m: np.ndarray
    distances_m: np.ndarray
    point_m: np.ndarray
    axis: np.ndarray

    @property
    def mean_m(self) -> float:
        return float(self.distances_m.mean())


@dataclass(frozen=True)
class EvaluationResult:
    """Accuracy of one transform of a target onto the reference.

    Attributes
    ----------
    ok, message, metrics
        `ok` is False when no branch could be evaluated (the message says why).
    T_ref_target
        The transform evaluated.
    branches
        Per branch, the layer distances (paper Figs. 13-14).
    mean_distance_m
        The paper's registration error d (eq. 8) over all layer pairs of all branches (NaN if none).
    rotation_error_deg, mean_displacement_m
        Against the true transform, when it was given (else None).
    """

    ok: bool
    message: str
    metrics: tuple[Metric, ...]
    T_ref_target: np.ndarray
    branches: tuple[BranchError, ...]
    mean_distance_m: float
    rotation_error_deg: float | None
    mean_displacement_m: float | None

    @property
    def n_pairs(self) -> int:
        return int(sum(len(b.distances_m) for b in self.branches))


def _slab(z_sorted: np.ndarray, order: np.ndarray, z: float, half: float) -> np.ndarray:
    lo, hi = np.searchsorted(z_sorted, [z - half, z + half])
    return order[lo:hi]


def _near_axis(points: np.ndarray, point: np.ndarray, axis: np.ndarray, radius: float) -> np.ndarray:
    """Mask of `points` within `radius` of the line through `point` along `axis`."""
    d = points - point
    perp = d - np.outer(d @ axis, axis)
    return np.einsum("ij,ij->i", perp, perp) <= radius * radius


def _usable(fit: CylinderFit, p: EvaluationParams) -> bool:
    return bool(fit.ok and fit.arc_deg >= p.min_arc_deg and fit.rms_m <= p.max_rms_m
                and fit.radius_m <= p.max_radius_m and abs(fit.axis[2]) >= _MIN_AXIS_Z)


def _same_branch(fit: CylinderFit, branch: CylinderFit, centre: np.ndarray, margin_m: float) -> bool:
    """A layer's fit belongs to the branch: similar radius and direction, axis through the branch.

    Near a fork a layer can take in points of the other limb; its fit then describes neither.
    """
    ratio = fit.radius_m / branch.radius_m
    cos = abs(float(fit.axis @ branch.axis))
    off = float(np.linalg.norm(fit.point_at_z(centre[2]) - centre))
    return bool(1 / _MAX_RADIUS_RATIO <= ratio <= _MAX_RADIUS_RATIO and cos >= _MIN_AXIS_COS
                and off <= branch.radius_m + margin_m)


def find_branches(ref: Scan, *, evaluation: EvaluationParams) -> list[CylinderFit]:
    """Branch sections of the reference: plausible cylinder fits to the arcs of a few slices.

    Returns at most `evaluation.max_branches` fits (reference frame), bottom to top.
    """
    p = evaluation
    z = ref.points[:, 2]
    lo, hi = tree_extent(z)
    order = np.argsort(z, kind="stable")
    zs = z[order]
    arc_p = ArcParams(connectivity=3.0, min_points=_MIN_LAYER_POINTS, max_range_jump_m=0.3)
    found: list[CylinderFit] = []
    for q in p.quantiles:
        h = lo + q * (hi - lo)
        idx = _slab(zs, order, h, p.layer_thickness_m / 2.0)
        if len(idx) < _MIN_LAYER_POINTS:
            continue
        arcs = separate_arcs(ref, idx, arc_p)
        for members in arcs.arcs():
            fit = fit_cylinder(ref.points[members])
            if _usable(fit, p):
                # Re-anchor the axis point at the slice height: that is where the branch was found.
                found.append(CylinderFit(fit.ok, fit.point_at_z(h), fit.axis, fit.radius_m, fit.rms_m,
                                         fit.arc_deg, fit.n_points, fit.length_m))
    if len(found) > p.max_branches:
        keep = np.linspace(0, len(found) - 1, p.max_branches).round().astype(int)
        found = [found[i] for i in keep]
    return found


@dataclass(frozen=True)
class ReferenceLayer:
    """One evaluation layer of a branch in the reference: its height, the branch axis point there and
    the reference's cylinder fit (None when the layer has too few points or the fit does not
    describe the branch)."""

    z_m: float
    centre: np.ndarray
    fit: CylinderFit | None


def reference_layers(ref: Scan, branches: list[CylinderFit], *, evaluation: EvaluationParams) -> list[list[ReferenceLayer]]:
    """The reference's side of every branch's layers (paper 3.3: three layers per branch, a cylinder
    fitted to each). They depend on the reference alone: fitted once for all transforms evaluated."""
    p = evaluation
    z = ref.points[:, 2]
    order = np.argsort(z, kind="stable")
    zs = z[order]
    half = p.layer_thickness_m / 2.0
    offsets = (np.arange(p.layers) - (p.layers - 1) / 2.0) * p.layer_spacing_m
    out = []
    for b in branches:
        lays = []
        for dz in offsets:
            zl = float(b.point_m[2] + dz)
            centre = b.point_at_z(zl)
            ir = _slab(zs, order, zl, half)
            ir = ir[_near_axis(ref.points[ir], centre, b.axis, b.radius_m + p.margin_m)]
            fit = None
            if len(ir) >= _MIN_LAYER_POINTS:
                fr = fit_cylinder(ref.points[ir], axis_hint=b.axis)
                if _usable(fr, p) and _same_branch(fr, b, centre, p.margin_m):
                    fit = fr
            lays.append(ReferenceLayer(zl, centre, fit))
        out.append(lays)
    return out


def evaluate_pair(ref: Scan, tgt: Scan, T_ref_target: np.ndarray, *, evaluation: EvaluationParams,
                  T_true: np.ndarray | None = None,
                  branches: list[CylinderFit] | None = None,
                  ref_layers: list[list[ReferenceLayer]] | None = None) -> EvaluationResult:
    """The paper's branch-centre error of `T_ref_target`, and errors against `T_true` when given.

    Parameters
    ----------
    ref, tgt
        Reference and target scans (each in its scanner frame).
    T_ref_target
        The transform to evaluate.
    evaluation
        Layers per branch, layer thickness and spacing, search heights, fit thresholds.
    T_true
        The true transform, if known.
    branches
        `find_branches(ref, evaluation=...)`, when the caller evaluates several transforms against the same
        reference (they depend on the reference alone); found here when None.
    ref_layers
        `reference_layers(ref, branches, ...)` likewise (the reference's layer fits, the same for
        every transform evaluated).

    Returns
    -------
    EvaluationResult
    """
    p = evaluation
    T = np.asarray(T_ref_target, dtype=float)
    T_sel = T if T_true is None else np.asarray(T_true, dtype=float)
    rot = disp = None
    if T_true is not None:
        rot = rotation_error_deg(T, T_true)
        disp = mean_displacement(T, T_true, tgt.points)
    branches = find_branches(ref, evaluation=p) if branches is None else branches
    tgt_sel = apply_transform(T_sel, tgt.points)
    z_tgt = tgt_sel[:, 2]
    o_tgt = np.argsort(z_tgt, kind="stable")
    zs_tgt = z_tgt[o_tgt]
    half = p.layer_thickness_m / 2.0
    out: list[BranchError] = []
    layers = reference_layers(ref, branches, evaluation=p) if ref_layers is None else ref_layers
    for number, (b, b_layers) in enumerate(zip(branches, layers)):
        zs_l, rc, tc = [], [], []
        reach = b.radius_m + p.margin_m
        for lay in b_layers:
            if lay.fit is None:  # the reference's layer is unusable: nothing to compare with
                continue
            zl, centre = lay.z_m, lay.centre
            it = _slab(zs_tgt, o_tgt, zl, half)
            it = it[_near_axis(tgt_sel[it], centre, b.axis, reach)]
            if len(it) < _MIN_LAYER_POINTS:
                continue
            ft = fit_cylinder(apply_transform(T, tgt.points[it]), axis_hint=b.axis)
            if not (_usable(ft, p) and _same_branch(ft, b, centre, p.margin_m + p.gate_m)):
                continue
            zs_l.append(zl)
            rc.append(lay.fit.point_at_z(zl))
            tc.append(ft.point_at_z(zl))
        if zs_l:
            rc_a, tc_a = np.array(rc), np.array(tc)
            # Numbered as found (not as kept): branch k is the same branch in every transform's result.
            out.append(BranchError(number, float(b.point_m[2]), float(b.radius_m), np.array(zs_l), rc_a, tc_a,
                                   np.linalg.norm(rc_a - tc_a, axis=1), np.asarray(b.point_m, float),
                                   np.asarray(b.axis, float)))
    d = np.concatenate([b.distances_m for b in out]) if out else np.empty(0)
    mean_d = float(d.mean()) if len(d) else float("nan")
    metrics = [
        Metric("branches evaluated", "", len(out)),
        Metric("layer pairs", "", int(len(d))),
        Metric("branch-centre error d (paper eq. 8)", "m", mean_d),
    ]
    if rot is not None:
        metrics += [Metric("rotation error", "deg", rot), Metric("mean displacement", "m", disp)]
    ok = bool(out)
    msg = "" if ok else (
        f"no branch could be evaluated: {len(branches)} branch sections found in the reference, none with "
        "usable layers in both scans (is the transform far off, or are evaluation.min_arc_deg / max_rms_m too strict?)")
    return EvaluationResult(ok, msg, tuple(metrics), T, tuple(out), mean_d, rot, disp)
