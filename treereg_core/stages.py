"""The registry of stages, in the order they run.

Each entry names its stage, the parameter sections it reads, the stages it depends on, its result
type, and a small run function that unpacks the pipeline's state into the stage function's own
arguments (a stage function never sees the whole parameter tree). Adding a stage: write its
module (a function returning a frozen result with `ok`, `message`, `metrics`) and add one entry.
"""

from __future__ import annotations

from dataclasses import replace
import numpy as np

from .coarse.estimate import CoarseResult, estimate_coarse
from .coarse.matching import MatchResult, match_sequences
from .coarse.sequences import ImageSequence, build_sequence
from .evaluate.branches import find_branches
from .fine.fitting import CylinderFit
from .evaluate.icp import IcpResult, align_icp, icp_off
from .evaluate.report import PairReport, evaluate_registration
from .fine.arcs import ArcResult, SliceArcs, separate_scan_slices, separate_slices
from .fine.pose import FINE_SECTIONS, FineResult, FineSections, FineStart, StemSeeds, profile_bend, register_fine, straightened
from .fine.sections import ScanSections, SectionsResult, fit_scan_sections, fit_sections
from .fine.slicing import SliceResult, slice_scans
from .fine.surface import Surface, scan_surface, surface_of
from .geometry.rigid import invert, mean_displacement, rotation_error_deg
from .prepare.ground import PreparedScan, prepare_scans, stem_position
from .prepare.mixed import remove_mixed
from .prepare.resolution import working_resolution
from .results import Metric
from .scan import Scan
from .stage import Pair, Stage, StageContext, StageResult
from .verify.evidence import VERIFIED, PairResults, PairScene, PairVerification, gather_evidence, judge, verification
from .verify.graph import Edge, Placement, place_scans
from .verify.hypotheses import HypothesesResult, pass_through, score_hypotheses
from .verify.visibility import RangeImage, range_image, scan_range_image


def _scan(ctx: StageContext, i: int) -> Scan:
    """Scan `i` as prepared (ground removed, cropped): what every stage after preparation uses."""
    return _prep(ctx, i).scan


def _prep(ctx: StageContext, i: int) -> PreparedScan:
    return ctx.item("prepare", i, PreparedScan)


def _label(ctx: StageContext, k: int) -> str:
    p = ctx.pairs[k]
    return f"{ctx.scans[p.tgt].name} -> {ctx.scans[p.ref].name}"


def _run_prepare(ctx: StageContext) -> list[StageResult | None]:
    # First each station at the working resolution (prepare/resolution.py); then ground and crops,
    # across scans: the target tree of a plot is chosen from every station's stems at once.
    given = ctx.params.prepare.angular_step_deg

    def station(i: int) -> Scan:
        # The instrument's steps, when given (e.g. typed in the app after loading), over the estimate.
        s = ctx.scans[i]
        return s.with_angular_step(given) if given is not None and tuple(given) != s.angular_step_deg else s

    pp = ctx.params.prepare
    # prepare depends on nothing: every scan is live
    work = [w for w in ctx.each(lambda i: working_resolution(station(i), resolution=ctx.params.resolution),
                    lambda i: f"working resolution: {ctx.scans[i].name}") if w is not None]
    ctx.progress(0.8, "mixed pixels")
    mixed = [remove_mixed(w.scan, enabled=pp.mixed_pixels, tolerance_m=pp.mixed_tolerance_m, slope=pp.mixed_slope,
                          dense_share=pp.mixed_dense_share, max_share=pp.mixed_max_share)
             for w in work]
    ctx.progress(0.9, "ground, stems and the target tree")
    preps = prepare_scans([m.scan for m in mixed], **ctx.params.pick("prepare", "target"))
    return [replace(p, station=m.scan, mixed_points=w.scan.points[m.mixed],
                    metrics=(w.metrics if w.reduced else ()) + m.metrics + p.metrics)
            for w, m, p in zip(work, mixed, preps)]


def _run_projection(ctx: StageContext) -> list[StageResult | None]:
    n = len(ctx.scans)
    return ctx.each(lambda i: build_sequence(_scan(ctx, i), projection=ctx.params.projection, n_scans=n),
                    lambda i: ctx.scans[i].name)


def _run_matching(ctx: StageContext) -> list[StageResult | None]:
    def one(k: int) -> MatchResult:
        p = ctx.pairs[k]
        return match_sequences(ctx.item("projection", p.ref, ImageSequence), ctx.item("projection", p.tgt, ImageSequence),
                               _scan(ctx, p.ref), _scan(ctx, p.tgt), matching=ctx.params.matching)
    return ctx.each(one, lambda k: _label(ctx, k))


def _run_coarse(ctx: StageContext) -> list[StageResult | None]:
    return ctx.each(lambda k: estimate_coarse(ctx.item("matching", k, MatchResult), coarse=ctx.params.coarse), lambda k: _label(ctx, k))


def _surface(ctx: StageContext, i: int, max_points: int | None = None) -> Surface:
    """Scan i's (prepared) surface at the voxel size of the surfaces section, shared by every stage."""
    scan = _scan(ctx, i)
    return scan_surface(scan, scan.points, ctx.params.surface.voxel_m, max_points)


def _range_image(ctx: StageContext, i: int) -> RangeImage:
    """Scan i's station as a range image for the free-space test, blind where its mixed pixels were."""
    return scan_range_image(_station(ctx, i), ctx.params.hypotheses.cell_steps, _prep(ctx, i).mixed_points)


def _station(ctx: StageContext, i: int) -> Scan:
    """Scan i's whole station at the working resolution (ground and neighbours included): what the
    free-space test compares with."""
    return _prep(ctx, i).station or ctx.scans[i]


def _run_hypotheses(ctx: StageContext) -> list[StageResult | None]:
    hp = ctx.params.hypotheses

    def one(k: int) -> HypothesesResult:
        p, c = ctx.pairs[k], ctx.item("coarse", k, CoarseResult)
        if not hp.enabled:
            return pass_through(c.T_ref_target)
        tgt, ref = _scan(ctx, p.tgt), _scan(ctx, p.ref)
        image, ref_surf = _range_image(ctx, p.ref), _surface(ctx, p.ref)
        seeds = _seeds(ctx, p)
        bend = profile_bend(ref, tgt, c.T_ref_target, ctx.params.wind, ctx.params.joint.loss_scale_m, seeds)
        adjust = None
        if bend is not None:
            # The crown moved between the stations: every candidate is judged against the reference
            # bent as the target's tree stood (the stems' bend does not depend on the heading).
            station = _station(ctx, p.ref)
            h_step, v_step = station.angular_step_deg
            image = range_image(bend.bend(station.points), (hp.cell_steps * h_step, hp.cell_steps * v_step),
                                _prep(ctx, p.ref).mixed_points)
            ref_surf = surface_of(bend.bend(ref.points), ctx.params.surface.voxel_m)

            def adjust(T: np.ndarray) -> np.ndarray:
                return straightened(ref, tgt, T, ctx.params.joint.loss_scale_m, seeds)
        return score_hypotheses(image, ref_surf, _surface(ctx, p.tgt, hp.polish_points), tgt.points, c.T_ref_target,
                                list(c.modes), hypotheses=hp, choose=ctx.choices.get(_label(ctx, k)),
                                axis_xy=_stem_xy(ctx, p.tgt), adjust=adjust)
    return ctx.each(one, lambda k: _label(ctx, k))


def _stem_xy(ctx: StageContext, i: int) -> np.ndarray | None:
    """Scan i's stem at breast height (its frame): the found stem nearest to its points' centroid,
    when within 2 m of it; None when none was found."""
    prep = _prep(ctx, i)
    stems = prep.stems
    if len(stems) == 0:
        return None
    d = np.hypot(*(stems[:, :2] - prep.scan.points[:, :2].mean(axis=0)).T)
    return stems[int(d.argmin()), :2] if d.min() <= 2.0 else None


def _seeds(ctx: StageContext, pair: Pair) -> StemSeeds:
    """Where the prepare stage put each scan's stem (the target's, in a plot): the stem profile
    traces from there, not from a neighbour's."""
    return StemSeeds(ref_xy=_prep(ctx, pair.ref).stem_xy, tgt_xy=_prep(ctx, pair.tgt).stem_xy)


def _ref_stem_xy(ctx: StageContext, i: int) -> np.ndarray:
    """Scan i's stem at its base (its own frame): what a turn about the stem turns about (the
    target's, where the prepare stage chose one)."""
    chosen = _prep(ctx, i).stem_xy
    if chosen is not None:
        return np.asarray(chosen, dtype=float)
    pts = _scan(ctx, i).points
    return stem_position(pts, pts[:, 2] - float(np.quantile(pts[:, 2], 0.001)))


def _start(ctx: StageContext, k: int) -> np.ndarray:
    """Where fine registration starts for pair k: the hypothesis the surfaces preferred."""
    return ctx.item("hypotheses", k, HypothesesResult).T_ref_target


def _run_slices(ctx: StageContext) -> list[StageResult | None]:
    def one(k: int) -> SliceResult:
        p = ctx.pairs[k]
        return slice_scans(_scan(ctx, p.ref), _scan(ctx, p.tgt), _start(ctx, k), slicing=ctx.params.slicing)
    return ctx.each(one, lambda k: _label(ctx, k))


def _run_arcs(ctx: StageContext) -> list[StageResult | None]:
    shared: dict[int, tuple[ArcResult, ...]] = {}  # a reference's arcs depend on it alone: shared by its pairs

    def one(k: int) -> SliceArcs:
        p, sl = ctx.pairs[k], ctx.item("slices", k, SliceResult)
        ref = _scan(ctx, p.ref)
        if p.ref not in shared:
            shared[p.ref] = separate_scan_slices(ref, sl.ref_indices, ctx.params.arcs)
        return separate_slices(ref, _scan(ctx, p.tgt), sl.ref_indices, sl.tgt_indices, arcs=ctx.params.arcs,
                               ref_arcs=shared[p.ref])
    return ctx.each(one, lambda k: _label(ctx, k))


def _run_sections(ctx: StageContext) -> list[StageResult | None]:
    shared: dict[int, ScanSections] = {}  # as for arcs: one fit of the reference's sections

    def one(k: int) -> SectionsResult:
        p, sl, ar = ctx.pairs[k], ctx.item("slices", k, SliceResult), ctx.item("arcs", k, SliceArcs)
        ref = _scan(ctx, p.ref)
        if p.ref not in shared:
            shared[p.ref] = fit_scan_sections(ref, ar.ref, sl.heights_m, np.eye(4), ctx.params.fitting)
        return fit_sections(ref, _scan(ctx, p.tgt), ar.ref, ar.tgt, sl.heights_m, _start(ctx, k),
                            fitting=ctx.params.fitting, ref_sections=shared[p.ref])
    return ctx.each(one, lambda k: _label(ctx, k))


def _run_fine(ctx: StageContext) -> list[StageResult | None]:
    def one(k: int) -> FineResult:
        p = ctx.pairs[k]
        sl = ctx.outputs["slices"].items[k]
        start = (FineStart(slices=sl, arcs=ctx.ok_item("arcs", k, SliceArcs), sections=ctx.ok_item("sections", k, SectionsResult))
                 if isinstance(sl, SliceResult) else None)
        return register_fine(_scan(ctx, p.ref), _scan(ctx, p.tgt), _start(ctx, k), start=start,
                             seeds=_seeds(ctx, p), params=FineSections.of(ctx.params))
    return ctx.each(one, lambda k: _label(ctx, k))


def _run_verify(ctx: StageContext) -> list[StageResult | None]:
    hp = ctx.params.hypotheses

    def one(k: int) -> PairVerification:
        p, f = ctx.pairs[k], ctx.item("fine", k, FineResult)
        tgt = _scan(ctx, p.tgt)
        # With wind, the surfaces compared are the target's unbent (as the reference's tree stood).
        tgt_surf = (_surface(ctx, p.tgt, SURFACE_SAMPLE) if f.bend is None else
                    surface_of(f.bend.warp(tgt, f.T_ref_target).points, ctx.params.surface.voxel_m, SURFACE_SAMPLE))
        scene = PairScene(ref_image=_range_image(ctx, p.ref), ref_surface=_surface(ctx, p.ref), tgt_surface=tgt_surf,
                          tgt_points=tgt.points, ref_plane=_prep(ctx, p.ref).plane, tgt_plane=_prep(ctx, p.tgt).plane,
                          ref_stem_xy=_ref_stem_xy(ctx, p.ref))
        found = PairResults(coarse=ctx.item("coarse", k, CoarseResult), hypotheses=ctx.item("hypotheses", k, HypothesesResult),
                            T_ref_target=f.T_ref_target, bend=f.bend, profile=f.profile, turn_held=f.turn_held)
        e = gather_evidence(scene, found, verify=ctx.params.verify, hypotheses=hp, acceptance=ctx.params.acceptance,
                            wind=ctx.params.wind,
                            support_inlier_m=ctx.params.coarse.final_inlier_m or ctx.params.coarse.inlier_m)
        return verification(f.T_ref_target, e, *judge(e, verify=ctx.params.verify, coarse=ctx.params.coarse,
                                                      acceptance=ctx.params.acceptance))
    return ctx.each(one, lambda k: _label(ctx, k))


def _run_graph(ctx: StageContext) -> list[StageResult | None]:
    """Every scan placed onto the reference from the verified pairs, jointly (one run for all scans)."""
    ver = ctx.outputs.get("verify")
    edges: list[Edge] = []
    for k, p in enumerate(ctx.pairs):
        it = ver.items[k] if ver is not None else None
        if isinstance(it, PairVerification):
            edges.append(Edge(i=p.ref, j=p.tgt, T=it.T_ref_target, verdict=it.verdict, reasons=it.reasons,
                              weight=float(max(it.evidence.seen_by_both, 1))))
        else:  # the pair failed before verification: no transform
            edges.append(Edge(i=p.ref, j=p.tgt, T=np.eye(4), verdict="failed",
                              reasons=((it.message if it is not None else "") or "not registered",)))
    rng = np.random.default_rng(0)
    samples: dict[int, np.ndarray] = {}
    for i in range(len(ctx.scans)):
        pts = _scan(ctx, i).points
        samples[i] = pts[rng.choice(len(pts), min(ctx.params.graph.sample_points, len(pts)), replace=False)]
    placed = place_scans(len(ctx.scans), edges, samples, graph=ctx.params.graph, max_loop_m=ctx.params.verify.max_loop_m)
    return [_with_truth(ctx, i, _with_step_doubt(ctx, i, pl)) for i, pl in enumerate(placed)]


def _with_step_doubt(ctx: StageContext, i: int, pl: Placement) -> Placement:
    """A scan left unverified while its (or the reference's) angular step is a doubtful estimate: the
    projection images were drawn at a guessed pixel size, so the step is the first thing to give."""
    if pl.verdict == VERIFIED or ctx.params.prepare.angular_step_deg is not None:
        return pl
    scans = [ctx.scans[j] for j in dict.fromkeys((0, i))]
    doubtful = [(s.name, s.step) for s in scans if s.step is not None and s.step.low]
    if not doubtful:
        return pl
    why = tuple(f"the angular step of {name}, {step.describe()}, is doubtful, so its projection images may "
                "be distorted" for name, step in doubtful)
    hint = "give the instrument's angular steps (--angular-step H V, or prepare.angular_step_deg in the Scans stage)"
    reasons = pl.reasons + why
    return replace(pl, reasons=reasons, message="; ".join(reasons), hint=f"{hint}; {pl.hint}" if pl.hint else hint)


def _with_truth(ctx: StageContext, i: int, pl: Placement) -> Placement:
    """A placement with its error against the truth among its metrics, when the truth is known."""
    ref, scan = ctx.scans[0], ctx.scans[i]
    if not ctx.truth or pl.T_ref_scan is None or scan.name not in ctx.truth or ref.name not in ctx.truth:
        return pl
    T_true = invert(ctx.truth[ref.name]) @ ctx.truth[scan.name]
    rows = (Metric("rotation error against truth", "deg", rotation_error_deg(pl.T_ref_scan, T_true)),
            Metric("mean displacement against truth", "m", mean_displacement(pl.T_ref_scan, T_true, scan.points)))
    return replace(pl, metrics=pl.metrics + rows)


def _run_icp(ctx: StageContext) -> list[StageResult | None]:
    def one(k: int) -> IcpResult:
        p, T = ctx.pairs[k], ctx.item("coarse", k, CoarseResult).T_ref_target
        if not ctx.params.icp.enabled:
            return icp_off(T)
        return align_icp(_scan(ctx, p.ref).points, _scan(ctx, p.tgt).points, T, icp=ctx.params.icp)
    return ctx.each(one, lambda k: _label(ctx, k))


def _run_evaluation(ctx: StageContext) -> list[StageResult | None]:
    branches: dict[int, list[CylinderFit]] = {}  # a reference's branches: found once for all its pairs and transforms

    def one(k: int) -> PairReport:
        p = ctx.pairs[k]
        ref, tgt = _scan(ctx, p.ref), _scan(ctx, p.tgt)
        if p.ref not in branches:
            branches[p.ref] = find_branches(ref, evaluation=ctx.params.evaluation)
        T_true = None
        if ctx.truth and tgt.name in ctx.truth and ref.name in ctx.truth:
            T_true = invert(ctx.truth[ref.name]) @ ctx.truth[tgt.name]
        return evaluate_registration(ref, tgt, ctx.item("coarse", k, CoarseResult).T_ref_target,
                                     ctx.item("fine", k, FineResult).T_ref_target,
                                     _icp_result(ctx, k), evaluation=ctx.params.evaluation,
                                     T_true=T_true, branches=branches[p.ref])
    return ctx.each(one, lambda k: _label(ctx, k))


def _icp_result(ctx: StageContext, k: int) -> IcpResult | None:
    """ICP's result even when it failed (it then keeps its start, which is still worth evaluating)."""
    out = ctx.outputs.get("icp")
    item = out.items[k] if out is not None and k < len(out.items) else None
    return item if isinstance(item, IcpResult) else None


STAGES: tuple[Stage, ...] = (
    Stage("prepare", "Scans", "Each station at the working resolution; the ground removed, the target tree found and the scan cropped to it.",
          "scan", ("prepare", "resolution", "target"), (), PreparedScan, _run_prepare, stop_on_failure=True),
    Stage("projection", "Projection", "Spherical binary images of each scan, rotated in steps about the tree (2.1.1-2.1.2).",
          "scan", ("projection",), ("prepare",), ImageSequence, _run_projection, stop_on_failure=True),
    Stage("matching", "Matching", "The most similar image pairs, ORB matches and 3-D tie points (2.1.3-2.1.4, 4.1).",
          "pair", ("matching",), ("projection",), MatchResult, _run_matching),
    Stage("coarse", "Coarse", "The rigid transform that maps the target's tie points onto the reference's (2.1.4).",
          "pair", ("coarse",), ("matching",), CoarseResult, _run_coarse),
    Stage("hypotheses", "Hypotheses", "Competing poses (other headings, other RANSAC modes) polished and scored by the surfaces.",
          "pair", ("hypotheses", "wind"), ("coarse",), HypothesesResult, _run_hypotheses),
    Stage("slices", "Slices", "Both scans cut into thin horizontal slices at the coarse pose (2.2.1).",
          "pair", ("slicing",), ("hypotheses",), SliceResult, _run_slices),
    Stage("arcs", "Arcs", "Each slice separated into arcs by angular connectivity (2.2.2).",
          "pair", ("arcs",), ("slices",), SliceArcs, _run_arcs),
    Stage("sections", "Fits", "Circles and cylinders fitted to the arcs, and corresponding sections paired (2.2.3, 4.2).",
          "pair", ("fitting",), ("arcs",), SectionsResult, _run_sections),
    Stage("fine", "Fine", "The fine transform from the corresponding sections, iterated and checked against the surfaces.",
          "pair", FINE_SECTIONS, ("hypotheses",), FineResult, _run_fine, uses=("slices", "arcs", "sections")),
    Stage("verify", "Verify", "The evidence that each registration is right: support, free space, residual, ambiguity, plausibility.",
          "pair", ("verify", "hypotheses", "acceptance", "wind"), ("fine",), PairVerification, _run_verify),
    Stage("graph", "Placement", "Every scan placed onto the reference from the verified pairs, loops closed, all poses solved together.",
          "scan", ("graph", "verify"), (), Placement, _run_graph, uses=("verify",)),
    Stage("icp", "ICP", "The ICP baseline, started from the coarse transform (3.3).",
          "pair", ("icp",), ("coarse",), IcpResult, _run_icp),
    Stage("evaluation", "Result", "The paper's branch-centre error (eq. 8) of coarse, fine and ICP, and errors against truth.",
          "pair", ("evaluation",), ("coarse", "fine"), PairReport, _run_evaluation, uses=("icp",)),
)

#: Target surface points the verify stage uses (its residual is a trimmed mean: more change nothing).
SURFACE_SAMPLE = 20_000

#: Where a run stops when a user says "--until coarse|fine": fine includes verification and the
#: placement of every scan (the graph stage), so every scan gets its verdict.
UNTIL = {"coarse": "coarse", "fine": "graph"}

#: Stage names in run order.
STAGE_NAMES: tuple[str, ...] = tuple(s.name for s in STAGES)
BY_NAME: dict[str, Stage] = {s.name: s for s in STAGES}


def stage(name: str) -> Stage:
    """The registered stage `name` (KeyError naming the known ones otherwise)."""
    try:
        return BY_NAME[name]
    except KeyError:
        raise KeyError(f"no stage {name!r}; stages are {', '.join(STAGE_NAMES)}") from None


def downstream(name: str) -> tuple[str, ...]:
    """`name` and every stage that depends on it, directly or not, in run order."""
    hit = {name}
    for s in STAGES:
        if any(u in hit for u in s.upstream):
            hit.add(s.name)
    return tuple(s for s in STAGE_NAMES if s in hit)


def _check() -> None:
    seen: set[str] = set()
    for s in STAGES:
        missing = [u for u in s.upstream if u not in seen]
        if missing:
            raise RuntimeError(f"stage {s.name!r} comes before {missing}, which it depends on")
        seen.add(s.name)


_check()
