"""The stage contract: a stage reads only the parameter sections it declares, so that a parameter
change re-runs exactly what it can alter and the cache never holds a stale result."""

import dataclasses
import math
from collections import Counter

import numpy as np
import pytest

from treereg_core.fine.pose import FineSections
from treereg_core.params import SECTIONS, STAGE_SECTIONS, Params
from treereg_core.pipeline import Pipeline
from treereg_core.simulate.cases import CaseSpec, benchmark_cases
from treereg_core.stage import DeclaredParams, UndeclaredSection
from treereg_core.stages import STAGE_NAMES, STAGES, affected_by

#: One field of every section (but those of the prepare stage: see GROUPS), changed within its range,
#: to a value that alters some stage's result on the windy pair below (the test checks each group's
#: change does): `surface.voxel_m` and `joint.loss_scale_m` alter the hypotheses, which once
#: declared neither.
CHANGES = {
    "projection": ("theta_deg", 12.0),
    "matching": ("n_pairs", 12),
    "coarse": ("final_inlier_m", 0.04),
    "hypotheses": ("polish_gate_m", 0.025),
    "slices": ("thickness_m", 0.08),
    "arcs": ("min_points", 20),
    "sections": ("max_rms_m", 0.015),
    "fine": ("max_iterations", 2),
    "joint": ("loss_scale_m", 0.007),
    "surface": ("voxel_m", 0.02),
    "wind": ("stable_tolerance_m", 0.002),
    "acceptance": ("gate_m", 0.01),
    "verify": ("max_residual_factor", 2.0),
    "graph": ("coarse_weight", 0.1),
    "icp": ("trim", 0.6),
    "evaluation": ("layers", 4),
}
#: Sections no change of which alters a result here: with two scans the placement is the one pair's.
INERT_HERE = {"graph"}


#: Sections whose changes re-run the same stages are changed together: a stage that read one of
#: them undeclared stays cached just as it would for one alone, and is caught the same. Not those
#: the prepare stage reads: a change to them re-runs every stage, nothing cached can go stale.
GROUPS = [tuple(sec for sec in STAGE_SECTIONS if affected_by(sec) == d) for d in dict.fromkeys(map(affected_by, STAGE_SECTIONS))
          if d != STAGE_NAMES]


def test_a_stage_reads_only_the_sections_it_declares():
    params = Params()
    view = DeclaredParams.of(params, "arcs", ("arcs",))
    assert isinstance(view, Params) and view.arcs is params.arcs and view.pick("arcs") == {"arcs": params.arcs}
    for read in (lambda p: p.slices, lambda p: p.pick("arcs", "slices"), lambda p: FineSections.of(p),
                 lambda p: getattr(p, "sections", None)):  # not an AttributeError a default would swallow
        with pytest.raises(UndeclaredSection, match="stage 'arcs' read parameter section '(slices|sections|fine)'"):
            read(view)
    assert "arcs" in repr(view)
    with pytest.raises(ValueError, match="unknown parameter sections"):
        DeclaredParams.of(params, "arcs", ("arc",))


def test_every_section_is_one_stages_own_and_borrowed_ones_are_declared_apart():
    owners = Counter(sec for s in STAGES for sec in s.sections)
    # The app's folder of the owner edits it (`stage_panel.build_folders`): each shown once.
    assert owners == Counter(STAGE_SECTIONS), owners
    for s in STAGES:
        assert set(s.borrows) <= set(SECTIONS) and not set(s.borrows) & set(s.sections), s.name
        assert s.reads == s.sections + s.borrows
    # A section named after a stage is that stage's own.
    by_name = {s.name: s for s in STAGES}
    assert all(sec in by_name[sec].sections for sec in SECTIONS if sec in by_name)


@pytest.fixture(scope="module")
def windy():
    """A small windy pair (14 k and 6 k points, under 2 s a run): the crown moved, so the hypotheses
    read the stem profile's loss scale as well as the surfaces' voxel."""
    case = CaseSpec(seed=101, height_m=8.5, angular_step_deg=(0.07, 0.07), n_stations=2, wind_m=0.15).build()
    base = Pipeline(list(case.scans), Params(), case.truth())
    assert base.run("evaluation").ok
    assert base.output("fine").items[0].bend is not None  # the wind is seen
    return case, base


def _same(a, b) -> bool:
    """Two results agree in every field (numbers, arrays, nested results; NaN agreeing with NaN) but
    the wall times (`seconds`)."""
    if type(a) is not type(b):
        return False
    if dataclasses.is_dataclass(a):
        return all(_same(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a) if f.name != "seconds")
    if isinstance(a, np.ndarray):
        return a.shape == b.shape and np.array_equal(a, b, equal_nan=a.dtype.kind in "fc")
    if isinstance(a, (tuple, list)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    return bool(a == b)


@pytest.mark.slow
@pytest.mark.parametrize("group", GROUPS, ids="+".join)
def test_a_parameter_change_gives_what_a_fresh_run_gives(windy, group):
    case, base = windy
    params = base.params
    for section in group:
        params = params.with_value(section, *CHANGES[section])
    changed = ", ".join(f"{sec}.{CHANGES[sec][0]}={CHANGES[sec][1]}" for sec in group)
    # The base run's cache, shared by every change (its outputs are frozen).
    cached = dataclasses.replace(base, _out=base.outputs, runs=Counter())
    dropped = cached.set_params(params)
    cached.run("evaluation")
    assert set(cached.runs) == set(dropped)
    fresh = Pipeline(list(case.scans), params, case.truth())
    fresh.run("evaluation")
    stale = [s for s in STAGE_NAMES if not _same(cached.output(s), fresh.output(s))]
    assert not stale, f"{changed}: {stale} cached differ from a fresh run (re-ran {dropped})"
    # The change matters here: otherwise a stage reading it undeclared would go unnoticed.
    assert set(group) <= INERT_HERE or any(not _same(base.output(s), fresh.output(s)) for s in dropped), \
        f"{changed} alters nothing"


def test_the_pairs_following_a_parameter_re_run_every_pair_stage():
    # With four scans or more the pairs are chosen (`graph.extra_pairs` of them per scan beyond a
    # spanning tree): another choice must not leave items of the old pairs cached.
    case = benchmark_cases(1, seed=3, small=True)[0]
    scans = list(dataclasses.replace(case, n_stations=4).build().scans)
    pipe = Pipeline(scans, Params())
    pipe.run("matching")
    before = pipe.pairs
    assert pipe.set_params(pipe.params.with_value("graph", "extra_pairs", 0)) == ["matching"]
    assert pipe.pairs != before
    pipe.run("matching")
    assert len(pipe.output("matching").items) == len(pipe.pairs)
