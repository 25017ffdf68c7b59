"""All parameters, as one tree of frozen dataclasses: a section per stage.

Every field has a default, a unit and a one-line doc in its metadata (`_f`). The CLI, the app's
panels and config files are all built from this tree; a stage function receives its own section
only. `PRESETS["paper"]` holds the paper's literal settings, `PRESETS["robust"]` (the default) the
robust variant.
"""

from __future__ import annotations

import dataclasses
import json
import math
import types
import typing
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from .io.atomic import write_text_atomic
from .io.json_input import load_json
from .errors import ConfigError

#: Instrument angular steps treereg works with, degrees: finer than any TLS (0.001 deg is 1.7 mm at
#: 100 m) to coarser than any tree scan worth registering. Scans, estimates and simulations obey it too.
ANGULAR_STEP_RANGE_DEG: tuple[float, float] = (0.001, 1.0)


#: Most heights a quantile list may name: a slice or a branch search each (a million sat 230 s at 2.8 GB);
#: 64 is a slice every 15 cm up a 10 m stem.
MAX_QUANTILES = 64


#: Whole numbers a random seed may be (numpy's legacy generators take 32 bits).
SEED_RANGE: tuple[int, int] = (0, 2**32 - 1)


def _f(default: Any, unit: str, doc: str, choices: tuple[Any, ...] | None = None,
       lo: float | None = None, hi: float | None = None, looser: str | None = None,
       parts: tuple[str, ...] | None = None, one_for_all: bool = False, max_len: int | None = None) -> Any:
    """A parameter field: default plus metadata the CLI and the app render.

    `looser` marks a threshold of the verdict "verified": "lower" or "higher" values verify more.
    Its range stops where, measured on the benchmark's wrong scans, a looser value would verify one
    (`benchmarks/bench_verify.py --loosest`); `loosened` names the fields set looser than the default.
    A fixed-length tuple names its `parts` (("x", "y")) for the message when a number is missing;
    `one_for_all` lets one number stand for all of them (an angular step 0.05 is 0.05 x 0.05).
    A list of any length has a `max_len`: each value is work (a slice, a branch height).
    """
    if looser not in (None, "lower", "higher"):
        raise ValueError(f"looser must be 'lower' or 'higher', not {looser!r}")
    meta = {"unit": unit, "doc": doc, "choices": choices, "min": lo, "max": hi, "looser": looser,
            "parts": parts, "one_for_all": one_for_all, "max_len": max_len}
    if isinstance(default, (list, dict)):
        raise TypeError("use tuples for sequence defaults (sections are frozen)")
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class ResolutionParams:
    """the working resolution: a scan sampled finer than this is reduced once, before anything else."""

    spacing_m: float | None = _f(0.01, "m", "working point spacing at the scan's median range: a finer scan is reduced to one point per angular cell of this size (None = use every point)", lo=0.0005, hi=0.5)
    depth_m: float = _f(0.02, "m", "a cell's point is the mean of its points within this range of its nearest one (averages the range noise, keeps what lies behind apart)", lo=0.0, hi=1.0)


@dataclass(frozen=True)
class PrepareParams:
    """per-scan preparation before anything is matched."""

    angular_step_deg: tuple[float, float] | None = _f(
        None, "deg", "instrument angular steps (horizontal phi, vertical varphi); None = estimate from the data",
        lo=ANGULAR_STEP_RANGE_DEG[0], hi=ANGULAR_STEP_RANGE_DEG[1], parts=("phi", "varphi"), one_for_all=True)
    remove_ground: bool = _f(True, "", "remove the ground before projection (robust plane through the lowest point of each cell)")
    ground_cell_m: float = _f(1.0, "m", "cell size of the lowest-point grid used to find the ground", lo=0.1, hi=10.0)
    ground_band_m: float = _f(0.3, "m", "points within this height above the ground plane are removed", lo=0.0, hi=5.0)
    crop_radius_m: float | None = _f(None, "m", "keep points within this horizontal radius of the stem (None = keep all)", lo=0.1)
    crop_z_min_m: float | None = _f(None, "m", "keep points above this height in the scanner frame (None = no limit)")
    crop_z_max_m: float | None = _f(None, "m", "keep points below this height in the scanner frame (None = no limit)")
    returns: str = _f("first", "", "several returns per pulse: keep the first of each pulse, or all (applies when a file is read; files without return numbers keep every point)",
                      choices=("first", "all"))
    mixed_pixels: bool = _f(True, "", "remove mixed pixels: returns just behind a range jump on the scan's angular grid with no neighbour at their own range (the comet tails behind every stem's edge)")
    mixed_tolerance_m: float = _f(0.02, "m", "mixed pixels: a neighbouring return continues a surface when its range differs by at most this (plus the slope allowance)", lo=0.001, hi=1.0)
    mixed_slope: float = _f(4.0, "", "mixed pixels: steepest surface kept, as the range change per cell over the cell's width (4 = 76 deg incidence)", lo=0.5, hi=100.0)
    mixed_dense_share: float = _f(0.02, "", "mixed pixels: tails are many when the returns behind a jump that nothing continues are this share of a scan (clean stations: 0.1-0.8%); then a return needs a neighbour not behind a jump, or two, to be kept", lo=0.0, hi=1.0)
    mixed_max_share: float = _f(0.4, "", "mixed pixels: the filter stands down when it would remove more than this share of a scan (a surface rougher than the angular grid, not tails)", lo=0.0, hi=1.0)
    ground_max_slope_deg: float = _f(30.0, "deg", "ground: the plane may be tilted at most this much from level (terrain slope + scanner tilt; raise it on a steep slope)", lo=0.0, hi=90.0)
    ground_min_cells: int = _f(8, "cells", "ground: the plane needs at least this many cells with their lowest point on it", lo=3, hi=1_000_000)
    ground_min_cell_share: float = _f(0.3, "", "ground: ...and at least this share of all cells", lo=0.0, hi=1.0)
    ground_max_below_share: float = _f(0.01, "", "ground: at most this share of the points may lie more than ground_band_m below the plane (else it is no ground: a tree cut out of a larger cloud)", lo=0.0, hi=1.0)
    level: bool = _f(True, "", "level a scan whose up is not its z (a scanner not levelled, a tilt mount, a scan upside down or y-up), found from its ground near the scanner and its stem, else its file's pose; the transforms are of the scans as given")
    level_min_deg: float = _f(3.0, "deg", "level: a scan whose ground's normal is less than this off z is left as given (a gentle slope, or a tilt the stages tolerate)", lo=0.0, hi=90.0)
    level_stem_margin_deg: float = _f(3.0, "deg", "level: the ground slopes under a plumb stem (the stem's axis is the up, not the ground's normal) when the stem's axis is this much nearer z than the ground's normal (stems waver and lean a few degrees)", lo=0.0, hi=45.0)


@dataclass(frozen=True)
class TargetParams:
    """which tree of a plot is registered: the target stem, and the crop around it."""

    select: str = _f("auto", "", "auto: when a station holds several stems, register the target tree and its surroundings; off: use every point",
                     choices=("auto", "off"))
    tree_at: tuple[float, float] | None = _f(None, "m", "the target stem's x y in the reference scan's frame; None = the stem the stations surround",
                                              parts=("x", "y"))
    radius_m: float = _f(5.0, "m", "keep points within this horizontal distance of the target stem (neighbours farther away swamp the coarse stage; nearer ones help it)", lo=0.5, hi=100.0)
    min_stems: int = _f(3, "stems", "auto selects a target only when a station holds at least this many stems (a scan cut to one tree is left as it is)", lo=2, hi=100)
    stem_band_m: tuple[float, float] = _f((1.0, 1.6), "m", "stems are looked for in this band of heights above the ground (breast height; raise it over undergrowth)", lo=0.0, hi=20.0,
                                         parts=("lowest", "highest"))
    stem_cell_m: float = _f(0.05, "m", "grid cell of the stem search: a stem is a group of connected cells (one cell of dilation joins a far stem's sparse points)", lo=0.005, hi=1.0)
    stem_max_range_m: float = _f(60.0, "m", "stems are looked for within this horizontal range of the scanner", lo=1.0, hi=1000.0)
    stem_radius_m: tuple[float, float] = _f((0.03, 0.8), "m", "plausible stem radii (smallest, largest)", lo=0.005, hi=5.0,
                                           parts=("smallest", "largest"))
    stem_min_points: int = _f(15, "points", "a stem needs this many points in the band", lo=3, hi=100_000)
    stem_min_arc_deg: float = _f(40.0, "deg", "...and a fitted circle covering this much arc", lo=0.0, hi=360.0)
    match_gate_m: float = _f(0.35, "m", "stem maps: two stations' stems match when their centres are this close under the stem-map transform", lo=0.01, hi=10.0)
    match_radius_tolerance: float = _f(0.4, "", "stem maps: ...and their radii differ by at most this fraction (+ 2 cm; partial arcs measure radii loosely)", lo=0.0, hi=10.0)
    min_matched: int = _f(3, "stems", "fewest matched stems for a station's stem map to place it (else it keeps all its points)", lo=2, hi=1000)
    pick_radius_m: float = _f(2.0, "m", "tree_at picks the nearest stem within this distance (a point farther from every stem found is refused)", lo=0.01, hi=100.0)


@dataclass(frozen=True)
class ProjectionParams:
    """spherical projection images (paper eq. 2-3) and rotation sequences (2.1.2)."""

    pixel_factor: int = _f(2, "steps", "a pixel covers k*phi x k*varphi (paper: k = 2)", lo=1, hi=10)
    square_pixels: bool = _f(True, "", "steps differing by more than 1.5x (e.g. 0.622 x 0.048 deg) get square pixels of k times the finer step, the gaps between scan lines closed (paper: k*phi x k*varphi)")
    border_px: tuple[int, int] = _f((10, 10), "px", "image borders r1, r2 (paper eq. 2)", lo=0, hi=1000, parts=("r1", "r2"))
    relative_azimuth: bool = _f(True, "", "measure azimuth from the scan centroid's azimuth, so a tree never straddles +-180 deg")
    theta_deg: float = _f(10.0, "deg", "rotation step of the image sequence (paper: 10)", lo=0.5, hi=90.0)
    span_deg: float | None = _f(None, "deg", "sequence covers [-span, +span]; None = 360/n, n = number of scans (paper)", lo=0.0, hi=180.0)
    min_span_deg: float = _f(90.0, "deg", "never span less than this: two sequences of +-90 deg cover any relative heading (paper: 0, so n > 4 scans leave gaps)", lo=0.0, hi=180.0)
    max_image_px: int | None = _f(700, "px", "enlarge pixels so no image is longer than this (ORB cost); None = no limit (paper)", lo=64, hi=20000)


@dataclass(frozen=True)
class MatchingParams:
    """similar image pairs, ORB features and tie points."""

    similarity: str = _f("chamfer", "", "how two projection images are compared",
                         choices=("iou", "chamfer", "ncc"))
    n_pairs: int = _f(15, "pairs", "most similar image pairs to match (paper: 3)", lo=1, hi=400)
    image_mode: str = _f("ramp", "", "what ORB sees: the bare binary image or a grey distance ramp around occupied pixels",
                         choices=("binary", "ramp"))
    ramp_px: float = _f(8.0, "px", "cap of the distance ramp", lo=1.0, hi=50.0)
    orb_nfeatures: int = _f(1500, "", "ORB: features per image", lo=10, hi=20000)
    orb_edge_threshold: int = _f(15, "px", "ORB: border where no features are detected", lo=3, hi=100)
    orb_patch_size: int = _f(31, "px", "ORB: size of the descriptor patch", lo=7, hi=101)
    orb_fast_threshold: int = _f(10, "", "ORB: FAST corner threshold", lo=1, hi=100)
    matches_per_pair: int = _f(60, "matches", "best Hamming matches kept per image pair (paper: 5)", lo=1, hi=5000)
    beta_check: bool = _f(False, "", "paper 4.1: drop matches whose |beta1-beta2| lies outside mean +- sigma")
    snap_px: int = _f(0, "px", "move a keypoint on an empty pixel to the nearest occupied pixel within this radius (0 = drop it; snapping measured worse on sparse scans)", lo=0, hi=20)


@dataclass(frozen=True)
class CoarseParams:
    """the coarse rigid transform from tie points."""

    estimator: str = _f("ransac", "", "plain SVD over all tie points (paper) or RANSAC", choices=("svd", "ransac"))
    dof: int = _f(4, "", "4 = yaw + 3-D translation (levelled scanners), 6 = full rigid", choices=(4, 6))
    refit_6dof: bool = _f(True, "", "refit all 6 DOF on the 4-DOF inliers (absorbs a small scanner tilt)")
    inlier_m: float = _f(0.4, "m", "RANSAC inlier distance", lo=0.01, hi=5.0)
    final_inlier_m: float | None = _f(0.05, "m", "after RANSAC, narrow the inlier distance step by step to this and refit (None = keep inlier_m)", lo=0.005, hi=5.0)
    iterations: int = _f(2000, "", "RANSAC iterations", lo=10, hi=100000)
    min_ties: int = _f(4, "pairs", "fewest tie pairs (or inliers) accepted for a transform (paper: > 4)", lo=3, hi=1000, looser="lower")
    seed: int = _f(0, "", "random seed of RANSAC", lo=SEED_RANGE[0], hi=SEED_RANGE[1])
    modes: int = _f(4, "", "RANSAC keeps this many distinct solutions (other headings, other trunk positions) for the hypotheses stage", lo=1, hi=20)
    chance_shuffles: int = _f(3, "", "RANSAC is also run on this many random re-pairings of the ties: what chance reaches (0 = not measured)", lo=0, hi=50)
    max_tilt_deg: float | None = _f(30.0, "deg", "reject a transform that tilts the scan more than this (scanners stand nearly level); None = no check", lo=0.0, hi=180.0)
    start_gates_m: tuple[float, ...] = _f((1.0, 0.5, 0.25, 0.1, 0.05, 0.02), "m", "a start pose the user gave (register --initial) is aligned by the surfaces, the pairing distance narrowing through these (the widest: how far off a start may be)", lo=0.005, hi=5.0, max_len=20)
    start_iterations: int = _f(10, "", "iterations of that alignment at each pairing distance", lo=1, hi=200)
    start_snap_m: float = _f(3.0, "m", "...and, when the start puts the target's stem at most this far from the reference's, also from the start shifted so the stems meet (the better aligned is kept)", lo=0.0, hi=50.0)
    start_ties_m: float = _f(2.0, "m", "...and from the transform RANSAC finds on the tie points the start puts at most this far from their partners", lo=0.05, hi=50.0)


@dataclass(frozen=True)
class HypothesesParams:
    """Competing pose hypotheses: RANSAC's distinct modes and quarter turns, polished and scored by the surfaces."""

    enabled: bool = _f(True, "", "score competing hypotheses and start the fine stage from the one the surfaces prefer (off: RANSAC's transform, as the paper)")
    turns: bool = _f(True, "", "also try the coarse transform turned about the tree's stem by 90, 120, 180, 240 and 270 deg (a crown with two-, three- or fourfold symmetry looks alike from several headings)")
    min_mode_support: int = _f(6, "ties", "a distinct RANSAC mode is a candidate when this many ties agree with it", lo=3, hi=100000)
    polish_gate_m: float = _f(0.02, "m", "each candidate is aligned by the surfaces down to this pairing distance", lo=0.001, hi=1.0)
    polish_iterations: int = _f(5, "", "iterations of that alignment at each pairing distance (10 cm, 5 cm, final)", lo=1, hi=200)
    polish_points: int = _f(4000, "points", "points of the target's surface used by that alignment at its final pairing distance", lo=100, hi=1_000_000)
    wide_points: int = _f(1000, "points", "...and at the wide pairing distances (10 and 5 cm), where it only has to find the candidate's basin", lo=100, hi=1_000_000)
    finish_within: float = _f(0.15, "", "only candidates at most this much less consistent than the best after the wide pairing distances are aligned at the final one (1 = all)", lo=0.0, hi=1.0)
    tolerance_m: float = _f(0.02, "m", "free-space test: a target point agrees with the reference's view within this range difference (plus the cell's depth)", lo=0.001, hi=0.04, looser="higher")
    cell_steps: float = _f(2.0, "steps", "free-space test: the reference's range image has cells of this many angular steps", lo=1.0, hi=20.0)
    loss_scale_m: float = _f(0.005, "m", "residual scale of the robust loss of the alignment", lo=0.0001, hi=0.5)
    violation_weight: float = _f(4.0, "", "a hypothesis keeps its polished pose when that scores better: points seen alike minus this many times the points in the reference's free space", lo=0.0, hi=1000.0)
    min_overlap_share: float = _f(0.25, "", "a hypothesis competes only if at least this share as many points agree with the reference's view as with the best-overlapping one", lo=0.0, hi=1.0)
    distinct_deg: float = _f(15.0, "deg", "hypotheses differing by at least this rotation are distinct", lo=0.1, hi=180.0)
    distinct_m: float = _f(0.3, "m", "...or by at least this displacement of the tree", lo=0.001, hi=100.0)


@dataclass(frozen=True)
class SlicesParams:
    """horizontal slices of reference and target after coarse."""

    quantiles: tuple[float, ...] = _f(tuple(round(0.05 * k, 2) for k in range(1, 20)), "",
                                      "slice heights as quantiles of tree height (paper: quartiles 0.25 0.5 0.75)", lo=0.0, hi=1.0,
                                      max_len=MAX_QUANTILES)
    thickness_m: float = _f(0.1, "m", "slice thickness (paper: 10 cm)", lo=0.01, hi=2.0)


@dataclass(frozen=True)
class ArcParams:
    """arcs by angular connectivity in each scan's own (alpha, beta)."""

    connectivity: float = _f(3.0, "steps", "neighbours when d_alpha <= c*phi and d_beta <= c*varphi (paper: 3)", lo=1.0, hi=20.0)
    min_points: int = _f(15, "points", "smallest arc kept", lo=3, hi=100000)
    max_range_jump_m: float | None = _f(0.3, "m", "split an arc where the range jumps by more than this (None = paper: angles only)", lo=0.01, hi=100.0)


@dataclass(frozen=True)
class SectionsParams:
    """circle (Taubin) and cylinder fits, correspondence and the fine transform."""

    min_arc_deg: float = _f(45.0, "deg", "smallest arc (angle covered about the centre) trusted for a fit", lo=0.0, hi=360.0)
    max_rms_m: float = _f(0.02, "m", "fits with a larger RMS residual are implausible", lo=0.0001, hi=1.0)
    max_radius_m: float = _f(1.0, "m", "fits with a larger radius are implausible", lo=0.01, hi=10.0)
    gate_m: float = _f(0.3, "m", "sections correspond when their centres are this close after coarse", lo=0.01, hi=5.0)
    max_radius_ratio: float | None = _f(1.5, "", "sections correspond only when their radii differ by at most this factor (None = paper: centres only)", lo=1.0, hi=100.0)
    refine_cylinders: bool = _f(False, "", "refine each scan's cylinder fits by least squares (paper; the joint adjustment refines them anyway)")
    circle_lowest: bool = _f(True, "", "fit the lowest slice's arcs by circles (trunk), the others by cylinders (paper)")
    taper_check: bool = _f(True, "", "paper 4.2: drop a part whose radius exceeds that of the part below on the same stem")
    taper_tolerance: float = _f(0.3, "", "4.2 check: allowed relative excess of the radius over the part below (paper: 0)", lo=0.0, hi=10.0)


@dataclass(frozen=True)
class FineParams:
    """Fine pose: iterate slices -> arcs -> fits -> update until the update is below the tolerance."""

    method: str = _f("joint", "", "tie points of separately fitted sections (paper) or one cylinder per section pair fitted to both scans with the pose",
                     choices=("ties", "joint"))
    max_iterations: int = _f(5, "", "re-slice with the new pose until the update is below the tolerance (paper: 1)", lo=1, hi=50)
    tolerance_m: float = _f(0.001, "m", "stop iterating when the update moves points less than this", lo=0.0, hi=1.0)
    min_pairs: int = _f(3, "pairs", "fewest corresponding sections to estimate an update", lo=1, hi=1000)
    gate_factor: float | None = _f(4.0, "", "after the first iteration, pairs farther apart than this times the median distance are dropped (None = off)", lo=1.0, hi=100.0)
    min_gate_m: float = _f(0.02, "m", "the adaptive gate is never tighter than this", lo=0.001, hi=5.0)
    estimator: str = _f("ransac", "", "ties: plain SVD (paper) or RANSAC over the tie points", choices=("svd", "ransac"))
    inlier_m: float = _f(0.05, "m", "ties: RANSAC inlier distance", lo=0.001, hi=1.0)


@dataclass(frozen=True)
class JointParams:
    """Fine pose, method joint: one cylinder per section pair fitted to both scans with the pose."""

    loss_scale_m: float = _f(0.005, "m", "residual scale of the robust loss (about the range noise)", lo=0.0001, hi=0.5)
    refine_loss: str = _f("cauchy", "", "loss after the first iteration (soft-L1 always first; Cauchy ignores wrong pairs near the solution)",
                          choices=("soft_l1", "cauchy"))
    influence_factor: float | None = _f(2.0, "", "drop the pair the pose hinges on when its influence exceeds this times the next largest (None = off)", lo=1.0, hi=1000.0)
    influence_min_m: float = _f(0.003, "m", "influences below this are never a reason to drop a pair", lo=0.0, hi=1.0)
    max_section_points: int = _f(150, "points", "points per section and scan used in the adjustment", lo=10, hi=100000)
    max_solver_iterations: int = _f(30, "", "Gauss-Newton iterations per adjustment", lo=1, hi=1000)
    prior_m: float = _f(0.05, "m", "prior std of the translation away from coarse (holds directions the sections hardly constrain)", lo=0.001, hi=100.0)
    prior_deg: float = _f(2.0, "deg", "prior std of the rotation away from coarse", lo=0.001, hi=180.0)
    max_direction_sigma_m: float | None = _f(0.02, "m", "pose directions the sections determine worse than this (noise std) are not updated by them (None = update all)", lo=1e-6, hi=10.0)


@dataclass(frozen=True)
class SurfaceParams:
    """Fine pose: oriented-normal point-to-plane terms of the target's surface against the reference's."""

    refine: bool = _f(True, "", "pose directions the sections fix only weakly are taken from the surfaces")
    sigma_m: float = _f(0.003, "m", "directions the sections determine worse than this (noise std) are weak", lo=1e-6, hi=10.0)
    polish: bool = _f(False, "", "finish with all six pose directions from the surfaces (not only the weak ones)")
    fallback: bool = _f(True, "", "with too few corresponding sections, align the surfaces instead (kept only if they then agree better)")
    gate_m: float = _f(0.015, "m", "final pairing distance (a wide gate pairs points past the edge of the other scan's view)", lo=0.001, hi=1.0)
    iterations: int = _f(20, "", "iterations at the final gate", lo=1, hi=1000)
    voxel_m: float = _f(0.01, "m", "voxel size of both scans' surfaces (also for the acceptance measure)", lo=0.0, hi=0.5)


@dataclass(frozen=True)
class WindParams:
    """Wind between the stations: the crown's motion estimated with the pose, as a nuisance."""

    enabled: bool = _f(True, "", "when the crowns do not line up rigidly, fit the stem's bend between the stations (a cantilever: nothing at the base, the most at the top) with the pose")
    min_sway_m: float = _f(0.02, "m", "a bend is fitted only when the stem top moved at least this much between the stations", lo=0.0, hi=10.0)
    significance: float = _f(3.0, "", "...and by this many times its own noise", lo=0.0, hi=100.0)
    stable_tolerance_m: float = _f(0.005, "m", "the stem 'stands where the reference's did' up to the height where the two differ by more than this", lo=0.0001, hi=1.0)
    flutter_share: float = _f(0.5, "", "the branches' own flutter, beyond the stem's bend, granted as moved at most this times the stem top's sway, in proportion to a point's height above the stem base (nothing at the base, all of it at the top); never more than verify.max_motion_m", lo=0.0, hi=1.0)
    base_share: float = _f(1.0 / 3.0, "", "a bend is wind only when the two stems agree, the bend taken out, within wind.stable_tolerance_m (or 3 times the profile's noise) below this share of the tree's height: a cantilever's base does not move", lo=0.1, hi=0.6)
    ground_anchor: bool = _f(True, "", "when the crown moved (a bend fitted, or a rigid fit whose stems lean against each other): take the scan's tilt and height from the ground both stations saw (it does not sway) and refit the bend and the stem's shift to the stem profile under that tilt; without ground, a rigid fit's tilt from the stems")
    max_hinge_depth_m: float = _f(1.0, "m", "ground anchor: the stem may bend from down to this far below its lowest point traced (the root plate)", lo=0.0, hi=5.0)
    lean_deg: float = _f(0.1, "deg", "ground anchor: a rigid fit whose stems lean against each other by at least this (and 1.25 times its noise) had its tilt pulled by the crown's moving twigs: its tilt is taken from the ground (else from the stems)", lo=0.0, hi=5.0)


@dataclass(frozen=True)
class AcceptanceParams:
    """Fine pose: which candidate pose ends the stage, and whether it is kept at all."""

    select: bool = _f(True, "", "joint: end at the pose with the lowest trimmed point-to-plane residual among coarse, the sections' result and that result polished by the surfaces in all six directions")
    select_coarse_polish: bool = _f(True, "", "also consider the coarse pose polished by the surfaces in all six directions (a safety net when the sections go astray)")
    polish_tolerance_m: float = _f(1e-4, "m", "a polish stops once a step moves the paired points less than this", lo=0.0, hi=0.01)
    select_trim: float = _f(0.7, "", "residual: mean over this fraction of the closest surface pairs (of the fewest any candidate pose has)", lo=0.05, hi=1.0)
    test: bool = _f(True, "", "keep the fine update unless the independent alignment measure clearly worsens")
    gate_m: float = _f(0.02, "m", "measure: a target point pairs with a reference point within this distance", lo=0.001, hi=1.0)
    tolerance_m: float = _f(0.005, "m", "measure: a paired point lies on the surface when its point-to-plane distance is below this", lo=0.0001, hi=1.0)
    margin: float = _f(0.01, "", "reject fine when the surface agreement falls by more than this (fraction of points)", lo=0.0, hi=1.0)
    stem_tilt_deg: float = _f(0.15, "deg", "the stems line up: by the stem profile, the target's stem leans at most this much against the reference's (or 3 times the profile's noise); a candidate pose whose stems do not is not chosen, a final pose whose stems do not is not verified", lo=0.0, hi=0.5, looser="higher")
    stem_shift_m: float = _f(0.005, "m", "...and the two stems stand at most this far apart (or 3 times the noise)", lo=0.0, hi=0.02, looser="higher")


@dataclass(frozen=True)
class VerifyParams:
    """The evidence a registration must show to be called verified (thresholds chosen by measurement, see RESULTS.md)."""

    min_consistency: float = _f(0.95, "", "free-space test at the final pose: fraction of the points both stations see that agree", lo=0.93, hi=1.0, looser="lower")
    min_seen: int = _f(200, "points", "at least this many target points must be seen by both stations to judge", lo=100, hi=10_000_000, looser="lower")
    min_margin: float = _f(0.03, "", "the best distinct competing hypothesis must be at least this much less consistent", lo=0.02, hi=1.0, looser="lower")
    chance_factor: float = _f(2.0, "", "coarse support: inliers at least this many times what RANSAC reaches on randomly re-paired ties", lo=1.5, hi=100.0, looser="lower")
    max_residual_factor: float = _f(3.0, "", "the trimmed surface residual at most this many times the scans' noise floor", lo=1.0, hi=5.0, looser="higher")
    max_tilt_deg: float = _f(5.0, "deg", "plausibility: the transform tilts the target's scanner at most this much (scanners stand nearly level)", lo=0.0, hi=10.0, looser="higher")
    max_height_difference_m: float = _f(1.0, "m", "plausibility: both scanners' heights above the ground differ at most this much (when both see ground)", lo=0.0, hi=2.0, looser="higher")
    max_loop_m: float = _f(0.02, "m", "with 3 or more scans: loops of pairwise transforms close within this (mean displacement of the tree)", lo=0.0, hi=0.05, looser="higher")
    max_heading_deg: float = _f(0.5, "deg", "wind, when the sections leave the turn about the stem open: the heading the free-space evidence prefers must lie within this of the pose's", lo=0.0, hi=2.0, looser="higher")
    max_motion_m: float = _f(0.1, "m", "wind: with the stem's bend taken out, the branches may still have moved this much on their own between the stations (beyond it the motion cannot be told from a wrong pose)", lo=0.0, hi=0.15, looser="higher")
    ground_radius_m: float = _f(5.0, "m", "plausibility, scanner height: judged only when each scan shows its ground within this horizontal distance of its scanner", lo=0.5, hi=50.0)
    min_ground_points: int = _f(100, "points", "...at least this many points there on its ground plane", lo=10, hi=1_000_000)
    ground_fit_m: float = _f(0.05, "m", "...within this of the plane (the plane fits the ground near the scanner, not another surface)", lo=0.005, hi=0.5)
    other_tree_consistency: float = _f(0.8, "", "not the same tree: a pair whose tie support is at chance level and whose free-space consistency is below this fails as showing another tree, and no scan is placed from it (measured: right pairs 0.94 or more, pairs of two different trees 0.07 to 0.94)", lo=0.0, hi=0.9)


@dataclass(frozen=True)
class GraphParams:
    """Many stations: which pairs are registered, and how all scans are placed together."""

    extra_pairs: int = _f(1, "pairs", "besides a spanning tree of the most alike scans, register each scan with this many more partners (loops to check)", lo=0, hi=10)
    loss_scale_m: float = _f(0.005, "m", "joint solve of all poses: residual scale of the soft-L1 loss of its first pass", lo=0.0001, hi=1.0)
    refine_scale_m: float = _f(0.001, "m", "joint solve, second pass: residual scale of the Cauchy loss (pairs far from the consensus lose their pull)", lo=0.0001, hi=1.0)
    sample_points: int = _f(300, "points", "points per scan by which an edge's disagreement is measured", lo=10, hi=100_000)
    coarse_weight: float = _f(0.05, "", "joint solve: a pair whose fine update was not kept (its coarse pose, several mm less certain) counts this much", lo=0.001, hi=1.0)


@dataclass(frozen=True)
class SurveyParams:
    """Whole-plot surveys: every station registered on every stem and the ground it shares with its neighbours (treereg_core/survey)."""

    mode: str = _f("auto", "", "auto: a survey when the stations do not stand round one tree (more than 8, or some far nearer the chosen tree than others); survey: always; one_tree: register the tree the stations surround (target.tree_at also keeps it)",
                   choices=("auto", "survey", "one_tree"))
    heights_m: tuple[float, ...] = _f((0.5, 0.9, 1.3, 1.8, 2.4, 3.1, 3.9, 4.8, 5.8, 7.0), "m", "stem sections are cut at these heights above the ground (the paper's slices, on every shared stem)", lo=0.0, hi=50.0, max_len=32)
    slab_m: float = _f(0.12, "m", "thickness of a stem section", lo=0.01, hi=1.0)
    margin_m: float = _f(0.06, "m", "a section takes the points within the stem's radius plus this of its centre", lo=0.005, hi=0.5)
    max_section_points: int = _f(120, "points", "points per station and section used in the pair's fit (more cost time, not accuracy)", lo=10, hi=10_000)
    max_fit_rms_m: float = _f(0.012, "m", "a station's circle fit of a section with a larger RMS residual is not used (a branch, a shrub)", lo=0.001, hi=0.1)
    min_stems: int = _f(4, "stems", "a pair is registered on at least this many stems both stations see", lo=3, hi=1000)
    neighbours: int = _f(3, "pairs", "each station is paired with this many stations it shares most stems with (besides a spanning tree; 4x4 survey: 3 gave 0.33 mm median in 40 pairs, 4 0.31 mm in 53, 2 0.95 mm)", lo=1, hi=20)
    loss_scale_m: float = _f(0.003, "m", "robust (soft-L1) scale of the pair fit's residuals", lo=0.0001, hi=0.1)
    max_stem_offset_m: float = _f(0.004, "m", "after the fit a stem whose two views stand farther apart than this is left out (it moved, or is another stem)", lo=0.0005, hi=0.1)
    max_residual_m: float = _f(0.006, "m", "a pair is verified when its stems' robust residual is at most this", lo=0.001, hi=0.05)
    max_pose_sd_m: float = _f(0.003, "m", "a pair is verified when its pose's uncertainty (one standard deviation) moves a point 20 m from the scanner at most this much (few or thin stems, short sections)", lo=0.0001, hi=0.1)
    ground_voxel_m: float = _f(0.25, "m", "ground points in the pair's fit, one per this cell", lo=0.02, hi=5.0)
    ground_range_m: float = _f(25.0, "m", "ground points used lie within this of both scanners", lo=1.0, hi=500.0)
    cloud_voxel_m: float = _f(0.1, "m", "a station's whole cloud, one point per this cell: the check that the crowns agree too, and the joint placement's samples", lo=0.01, hi=2.0)
    ambiguity: float = _f(0.9, "", "a stem map that also fits shifted (a regular planting): the pair is refused when the second fit's crowns agree at least this share as well as the first's", lo=0.5, hi=1.0)
    max_loop_m: float = _f(0.002, "m", "loops of pairs close within this (mean displacement of the stations' points within 20 m of the scanner; right pairs of a 3 x 3 survey at 0.25 deg: 0.1-0.8 mm)", lo=0.0005, hi=0.1)


@dataclass(frozen=True)
class IcpParams:
    """Baseline: trimmed ICP from the coarse result."""

    method: str = _f("point_to_plane", "", "ICP error metric", choices=("point_to_point", "point_to_plane"))
    max_iterations: int = _f(50, "", "ICP iterations", lo=1, hi=1000)
    trim: float = _f(0.5, "", "fraction of closest correspondences kept each iteration", lo=0.1, hi=1.0)
    max_distance_m: float = _f(0.5, "m", "correspondences farther than this are ignored", lo=0.001, hi=10.0)
    voxel_m: float = _f(0.02, "m", "voxel size for subsampling before ICP", lo=0.0, hi=1.0)
    enabled: bool = _f(True, "", "run the ICP baseline from the coarse result (the evaluation compares it with fine)")


@dataclass(frozen=True)
class EvaluationParams:
    """The paper's evaluation model (3.3, eq. 8)."""

    layers: int = _f(3, "", "layers per branch (bottom, middle, top)", lo=1, hi=20)
    layer_thickness_m: float = _f(0.1, "m", "thickness of an evaluation layer", lo=0.01, hi=2.0)
    layer_spacing_m: float = _f(0.15, "m", "height between a branch's layers", lo=0.01, hi=5.0)
    quantiles: tuple[float, ...] = _f((0.2, 0.35, 0.5, 0.65, 0.8), "", "heights (quantiles of tree height) where branches are searched", lo=0.0, hi=1.0,
                                      max_len=MAX_QUANTILES)
    margin_m: float = _f(0.03, "m", "a layer takes the points within the branch radius plus this of its axis", lo=0.001, hi=1.0)
    min_arc_deg: float = _f(60.0, "deg", "evaluation fits covering less arc are not used", lo=0.0, hi=360.0)
    max_rms_m: float = _f(0.01, "m", "evaluation fits with a larger RMS residual are not used", lo=0.0001, hi=1.0)
    max_radius_m: float = _f(1.0, "m", "evaluation fits with a larger radius are not used", lo=0.01, hi=10.0)
    max_branches: int = _f(30, "", "most branches evaluated (spread over the heights)", lo=1, hi=1000)
    gate_m: float = _f(1.0, "m", "a target layer whose centre is farther than this from the branch is not used", lo=0.01, hi=10.0)


@dataclass(frozen=True)
class Params:
    """Everything treereg's pipeline needs, one section per stage."""

    prepare: PrepareParams = field(default_factory=PrepareParams)
    target: TargetParams = field(default_factory=TargetParams)
    resolution: ResolutionParams = field(default_factory=ResolutionParams)
    projection: ProjectionParams = field(default_factory=ProjectionParams)
    matching: MatchingParams = field(default_factory=MatchingParams)
    coarse: CoarseParams = field(default_factory=CoarseParams)
    hypotheses: HypothesesParams = field(default_factory=HypothesesParams)
    slices: SlicesParams = field(default_factory=SlicesParams)
    arcs: ArcParams = field(default_factory=ArcParams)
    sections: SectionsParams = field(default_factory=SectionsParams)
    fine: FineParams = field(default_factory=FineParams)
    joint: JointParams = field(default_factory=JointParams)
    surface: SurfaceParams = field(default_factory=SurfaceParams)
    wind: WindParams = field(default_factory=WindParams)
    acceptance: AcceptanceParams = field(default_factory=AcceptanceParams)
    verify: VerifyParams = field(default_factory=VerifyParams)
    graph: GraphParams = field(default_factory=GraphParams)
    survey: SurveyParams = field(default_factory=SurveyParams)
    icp: IcpParams = field(default_factory=IcpParams)
    evaluation: EvaluationParams = field(default_factory=EvaluationParams)

    def with_value(self, section: str, name: str, value: Any) -> "Params":
        """A copy with one field changed (value checked and coerced to the field's type)."""
        if section not in SECTIONS:
            raise ConfigError(f"{section}.{name}: no such section; sections are {', '.join(SECTIONS)}")
        sec = getattr(self, section)
        fld = {f.name: f for f in fields(sec)}.get(name)
        if fld is None:
            raise ConfigError(f"{section}.{name}: no such parameter")
        return replace(self, **{section: replace(sec, **{name: _coerce(f"{section}.{name}", fld, value)})})

    def pick(self, *sections: str) -> dict[str, Any]:
        """The named sections as keyword arguments of a stage function: `fn(..., **params.pick("fine", "joint"))`."""
        return {s: getattr(self, s) for s in sections}


SECTIONS: tuple[str, ...] = tuple(f.name for f in fields(Params))
#: Sections read outside the one-tree pipeline's stages: the survey registration (treereg_core/survey).
SURVEY_SECTIONS: tuple[str, ...] = ("survey",)
#: The sections a stage owns (tests/test_stage_contract.py: each exactly one stage's).
STAGE_SECTIONS: tuple[str, ...] = tuple(s for s in SECTIONS if s not in SURVEY_SECTIONS)

#: Parameters that moved to another section or name: config files written before still load.
MOVED: dict[tuple[str, str], tuple[str, str]] = {
    **{("fine", k): ("joint", k) for k in (
        "loss_scale_m", "refine_loss", "influence_factor", "influence_min_m", "max_section_points",
        "max_solver_iterations", "prior_m", "prior_deg", "max_direction_sigma_m")},
    ("fine", "surface_refine"): ("surface", "refine"), ("fine", "surface_sigma_m"): ("surface", "sigma_m"),
    ("fine", "surface_polish"): ("surface", "polish"), ("fine", "surface_fallback"): ("surface", "fallback"),
    ("fine", "surface_gate_m"): ("surface", "gate_m"), ("fine", "surface_iterations"): ("surface", "iterations"),
    ("fine", "measure_voxel_m"): ("surface", "voxel_m"),
    ("fine", "select"): ("acceptance", "select"), ("fine", "select_coarse_polish"): ("acceptance", "select_coarse_polish"),
    ("fine", "polish_tolerance_m"): ("acceptance", "polish_tolerance_m"), ("fine", "select_trim"): ("acceptance", "select_trim"),
    ("fine", "accept_test"): ("acceptance", "test"), ("fine", "measure_gate_m"): ("acceptance", "gate_m"),
    ("fine", "measure_tolerance_m"): ("acceptance", "tolerance_m"), ("fine", "accept_margin"): ("acceptance", "margin"),
    ("evaluation", "run_icp"): ("icp", "enabled"),
}
#: Sections renamed after their stage (issue 19): every field of the old name is taken at the new.
RENAMED_SECTIONS: dict[str, str] = {"slicing": "slices", "fitting": "sections"}
MOVED.update({(old, f.name): (new, f.name) for old, new in RENAMED_SECTIONS.items()
              for f in fields(getattr(Params(), new))})


def moved(section: str, name: str) -> tuple[str, str]:
    """Where `section.name` lives now (`MOVED`; an unknown field of a renamed section is looked up,
    and reported, under the section's new name)."""
    return MOVED.get((section, name), (RENAMED_SECTIONS.get(section, section), name))


def _paper() -> Params:
    """The paper's settings taken literally (sections 2.1-2.2, 4.1)."""
    p = Params()
    return replace(
        p,
        prepare=replace(p.prepare, remove_ground=False, mixed_pixels=False),
        projection=replace(p.projection, relative_azimuth=False, max_image_px=None, min_span_deg=0.0, square_pixels=False),
        matching=replace(p.matching, n_pairs=3, matches_per_pair=5, beta_check=True, image_mode="binary", snap_px=0),
        coarse=replace(p.coarse, estimator="svd", dof=6, refit_6dof=False, final_inlier_m=None),
        slices=replace(p.slices, quantiles=(0.25, 0.5, 0.75), thickness_m=0.1),
        arcs=replace(p.arcs, connectivity=3.0, max_range_jump_m=None),
        sections=replace(p.sections, max_radius_ratio=None, refine_cylinders=True, circle_lowest=True,
                        taper_check=True, taper_tolerance=0.0, min_arc_deg=0.0, max_rms_m=1.0),
        fine=replace(p.fine, method="ties", estimator="svd", max_iterations=1, gate_factor=None),
        acceptance=replace(p.acceptance, test=False),
        wind=replace(p.wind, enabled=False),
        hypotheses=replace(p.hypotheses, enabled=False),
        icp=replace(p.icp, method="point_to_point"),
    )


PRESETS: dict[str, Params] = {"robust": Params(), "paper": _paper()}


def field_info(section: str) -> list[dataclasses.Field]:
    """The fields of one section, in order, with their metadata (unit, doc, choices, min, max, looser)."""
    return list(fields(getattr(Params(), section)))


def thresholds() -> list[tuple[str, dataclasses.Field]]:
    """("section.name", field) of every threshold of the verdict "verified" (`looser` in its metadata)."""
    return [(f"{s}.{f.name}", f) for s in SECTIONS for f in field_info(s) if f.metadata.get("looser")]


def _is_looser(fld: dataclasses.Field, value: Any, default: Any) -> bool:
    return value < default if fld.metadata["looser"] == "lower" else value > default


def loosened(params: Params) -> dict[str, tuple[Any, Any]]:
    """{"section.name": (value, default)} of the verification thresholds set looser than the default
    (tightened ones are not listed: they cannot verify more)."""
    out = {}
    for key, fld in thresholds():
        s, n = key.split(".")
        value, default = getattr(getattr(params, s), n), fld.default
        if _is_looser(fld, value, default):
            out[key] = (value, default)
    return out


def loosened_text(changes: dict[str, tuple[Any, Any]]) -> str:
    """"verified under loosened thresholds (verify.min_margin 0.01 < default 0.03)" ("" when none)."""
    if not changes:
        return ""
    parts = [f"{k} {v:g} {'<' if v < d else '>'} default {d:g}" for k, (v, d) in changes.items()]
    return f"verified under loosened thresholds ({', '.join(parts)})"


def loosest(params: Params | None = None) -> Params:
    """`params` (default: robust) with every verification threshold at its loosest allowed value."""
    p = params or Params()
    for key, fld in thresholds():
        s, n = key.split(".")
        p = p.with_value(s, n, fld.metadata["min"] if fld.metadata["looser"] == "lower" else fld.metadata["max"])
    return p


def set_text(value: Any) -> str:
    """A value as `--set` takes it: 5, 0.02, true, null, 1,1.6 (a tuple)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, tuple):
        return ",".join(set_text(v) for v in value)
    if isinstance(value, float):  # shortest exact text: 0.05, 1e-06, 10
        return repr(value).removesuffix(".0")
    return str(value)


def set_flag(key: str, value: Any) -> str:
    """How a hint suggests a parameter change: "--set projection.theta_deg=5". The key and value are
    checked (`with_value`), so a hint can name no parameter that does not exist, nor a value out of range."""
    section, _, name = key.partition(".")
    Params().with_value(section, name, value)
    return f"--set {key}={set_text(value)}"


def changed_from_defaults(params: Params) -> dict[str, list[Any]]:
    """{"section.name": [value, default]} of every parameter that differs from the robust default."""
    now, default = to_dict(params), to_dict(Params())
    return {f"{s}.{k}": [v, default[s][k]] for s in SECTIONS for k, v in now[s].items() if v != default[s][k]}


def to_dict(params: Params) -> dict[str, dict[str, Any]]:
    """JSON-ready nested dict (tuples become lists)."""
    out: dict[str, dict[str, Any]] = {}
    for s in SECTIONS:
        sec = getattr(params, s)
        out[s] = {f.name: (list(v) if isinstance(v := getattr(sec, f.name), tuple) else v) for f in fields(sec)}
    return out


def from_dict(data: dict[str, Any], base: Params | None = None, source: str = "parameters") -> Params:
    """Parameters from a nested dict; missing keys keep `base` (default: robust). Unknown keys are errors.

    A top-level `"preset": "paper"` starts from that preset; a top-level `"starts"` (the start poses the
    app saves beside the parameters, `io.start.starts_doc`) is not read here.
    """
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a JSON object of sections")
    data = dict(data)
    # The start poses the app saves beside its parameters (`io.start.STARTS_KEY`): not parameters; the
    # app restores them, `register --initial SCAN=params.json` reads them.
    data.pop("starts", None)
    preset = data.pop("preset", None)
    if preset is not None:
        if not isinstance(preset, str):  # a list or object is unhashable: `in PRESETS` would raise TypeError
            raise ConfigError(f"{source}: preset: {_shown(preset)} is not a preset name; "
                              f"give one of {sorted(PRESETS)} as a string, e.g. \"preset\": \"paper\"")
        if preset not in PRESETS:
            raise ConfigError(f"{source}: unknown preset {preset!r}; choose one of {sorted(PRESETS)}")
        base = PRESETS[preset]
    p = base or Params()
    for s, values in data.items():
        if s not in SECTIONS and s not in RENAMED_SECTIONS:
            raise ConfigError(f"{source}: unknown section {s!r}; sections are {', '.join(SECTIONS)}")
        if not isinstance(values, dict):
            raise ConfigError(f"{source}: section {s!r} must be an object")
        for k, v in values.items():
            sec, name = moved(s, k)
            try:
                p = p.with_value(sec, name, v)
            except ConfigError as e:
                raise ConfigError(f"{source}: {e}") from None
    return p


def load(path: str | Path, base: Params | None = None) -> Params:
    """Read a parameter JSON file (as written by `save`, or any subset of it) over `base`."""
    return from_dict(load_json(path, "parameter file"), base=base, source=str(path))


def save(params: Params, path: str | Path) -> None:
    """Write parameters as JSON, atomically."""
    write_text_atomic(Path(path), json.dumps(to_dict(params), indent=2) + "\n")


def _coerce(key: str, fld: dataclasses.Field, value: Any) -> Any:
    """Check `value` against the field's annotated type, range and choices."""
    hint = typing.get_type_hints(_owner_of(fld))[fld.name]
    meta = fld.metadata
    optional = False
    args = typing.get_args(hint)
    if typing.get_origin(hint) in (typing.Union, types.UnionType) and type(None) in args:
        optional = True
        hint = next(a for a in args if a is not type(None))
    if value is None:
        if optional:
            return None
        raise ConfigError(f"{key}: a value is required")
    try:
        if hint is bool:
            if isinstance(value, str):
                if value.lower() not in ("true", "false", "1", "0", "yes", "no"):
                    raise ValueError(value)
                value = value.lower() in ("true", "1", "yes")
            elif not isinstance(value, (bool, int)):
                raise ValueError(value)
            out: Any = bool(value)
        elif hint in (int, float):
            if isinstance(value, bool):
                raise ValueError(value)
            f = float(value)
            if not math.isfinite(f):
                raise ConfigError(f"{key}: {_shown(value)} is not a finite number")
            if hint is int:
                if f != int(f):
                    raise ValueError(value)
                out = int(f)
            else:
                out = f
            if out != out:  # NaN
                raise ValueError(value)
            _check_range(key, (out,), meta)
        elif hint is str:
            out = str(value)
        elif typing.get_origin(hint) is tuple:
            if isinstance(value, str):
                value = [v for v in value.replace(",", " ").split() if v]
            elif isinstance(value, (int, float)) and not isinstance(value, bool):
                value = [value]
            elem = typing.get_args(hint)
            seq = list(value)
            if len(elem) == 2 and elem[1] is Ellipsis:
                if not seq:
                    raise ConfigError(f"{key}: needs at least one value")
                if len(seq) > meta["max_len"]:  # before converting any: a million values is refused at once
                    raise ConfigError(f"{key}: {len(seq):,} values given; at most {meta['max_len']} are allowed")
                out = tuple(_element(elem[0], v) for v in seq)
            else:
                if len(seq) == 1 and meta.get("one_for_all"):
                    seq = seq * len(elem)  # one value for all, as `--angular-step 0.05` means 0.05 x 0.05
                if len(seq) != len(elem):
                    raise ConfigError(f"{key}: needs {_count_text(len(elem))} numbers {','.join(meta['parts'])}, "
                                      f"got {len(seq):,}")
                out = tuple(_element(t, v) for t, v in zip(elem, seq))
            bad = [v for v in out if isinstance(v, float) and not math.isfinite(v)]
            if bad:
                raise ConfigError(f"{key}: {bad[0]:g} is not a finite number")
            _check_range(key, out, meta)
        else:
            out = value
    except ConfigError:  # a ValueError too: keep its precise message (range, length)
        raise
    except (TypeError, ValueError, OverflowError):
        raise ConfigError(f"{key}: {_shown(value)} is not a valid {_type_name(hint)}") from None
    choices = meta.get("choices")
    if choices is not None and out not in choices:
        raise ConfigError(f"{key}: {out!r} is not one of {list(choices)}")
    return out


def _check_range(key: str, values: tuple[Any, ...], meta: Any) -> None:
    """Every number of a value (a scalar, or each element of a tuple) within the field's [min, max]."""
    lo, hi = meta.get("min"), meta.get("max")
    unit = f" {meta['unit']}" if meta.get("unit") and meta["unit"] not in ("steps",) else ""
    for v in values:
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            allowed = f"{number_text(lo)} to {number_text(hi)}{unit}" if lo is not None and hi is not None else \
                f"at least {number_text(lo)}{unit}" if lo is not None else f"at most {number_text(hi)}{unit}"
            raise ConfigError(f"{key}: {number_text(v)}{unit} is outside the allowed range ({allowed})")


def _count_text(n: int) -> str:
    """"two" numbers, not "2" (a message reads as a sentence)."""
    return {1: "one", 2: "two", 3: "three", 4: "four"}.get(n, str(n))


def number_text(v: float) -> str:
    """A number as a message shows it: whole numbers in full (a seed's 4294967295), others short."""
    return str(v) if isinstance(v, int) else f"{v:g}"


def _element(typ: type, v: Any) -> Any:
    """One number of a list parameter: no booleans, no fractions where a whole number is meant."""
    if isinstance(v, bool):
        raise ValueError(v)
    f = float(v)
    if typ is int:
        if f != int(f):
            raise ValueError(v)
        return int(f)
    return typ(f) if typ is float else typ(v)


def _shown(value: Any) -> str:
    """A rejected value as a message quotes it (cut short: a config file may hold anything)."""
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _type_name(hint: Any) -> str:
    """How a message names a field's type: 'number', 'whole number', 'list of 2 numbers'."""
    if hint is float:
        return "number"
    if hint is int:
        return "whole number"
    if hint is bool:
        return "true/false value"
    if typing.get_origin(hint) is tuple:
        elem = typing.get_args(hint)
        n = "numbers" if len(elem) == 2 and elem[1] is Ellipsis else f"{len(elem)} numbers"
        return f"list of {n}"
    return getattr(hint, "__name__", str(hint))


def _owner_of(fld: dataclasses.Field) -> type:
    for s in fields(Params):
        cls = s.default_factory  # type: ignore[attr-defined]
        if any(f is fld for f in fields(cls)):
            return cls
    raise KeyError(fld.name)
