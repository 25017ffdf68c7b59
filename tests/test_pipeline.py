"""The pipeline: stages run in order, cache, and re-run only what a parameter change touches."""

import numpy as np
import pytest

from treereg_core.params import Params
from treereg_core.pipeline import Pipeline, register
from treereg_core.stages import STAGE_NAMES
from treereg_core.geometry.rigid import mean_displacement, rotation_error_deg
from treereg_core.simulate.cases import benchmark_cases


@pytest.fixture(scope="module")
def case():
    return benchmark_cases(3, seed=0, small=True)[1].build()


def test_register_reaches_truth_and_caches(case):
    pipe = Pipeline(list(case.scans), Params(), case.truth())
    out = pipe.run("fine")
    assert out.ok, out.message
    upto = STAGE_NAMES.index("fine") + 1
    assert [pipe.status(s) for s in STAGE_NAMES] == ["done"] * upto + ["stale"] * (len(STAGE_NAMES) - upto)
    for scan, T_true in zip(case.scans[1:], case.T_ref_scan[1:]):
        T = pipe.transforms()[scan.name]
        assert rotation_error_deg(T, T_true) < 0.5
        assert mean_displacement(T, T_true, scan.points) < 0.03

    coarse_before = pipe.output("coarse")
    # A fine-stage parameter leaves coarse (and everything before it) cached...
    stale = pipe.set_params(pipe.params.with_value("fine", "max_iterations", 2))
    assert stale == ["fine"]
    assert pipe.output("coarse") is coarse_before
    # ...and a preparation parameter invalidates everything.
    stale = pipe.set_params(pipe.params.with_value("prepare", "ground_band_m", 0.2))
    assert stale == list(STAGE_NAMES[: STAGE_NAMES.index("fine")])  # fine had been dropped already
    assert all(pipe.status(s) == "stale" for s in STAGE_NAMES)


def test_a_parameter_change_reruns_only_the_stages_that_depend_on_it(case):
    pipe = Pipeline(list(case.scans), Params(), case.truth())
    pipe.run("evaluation")
    assert all(pipe.runs[s] == 1 for s in STAGE_NAMES)
    slices = pipe.output("slices")
    # An arcs parameter: arcs and what follows from it, never slicing, coarse or the ICP baseline.
    assert pipe.set_params(pipe.params.with_value("arcs", "min_points", 20)) == \
        ["arcs", "sections", "fine", "verify", "graph", "evaluation"]
    pipe.run("evaluation")
    assert pipe.output("slices") is slices
    again = {"arcs", "sections", "fine", "verify", "graph", "evaluation"}
    assert {s: pipe.runs[s] for s in STAGE_NAMES} == {s: 2 if s in again else 1 for s in STAGE_NAMES}
    # A verdict threshold: the verdicts and placement only, nothing is registered again.
    assert pipe.set_params(pipe.params.with_value("verify", "min_consistency", 0.97)) == ["verify", "graph"]
    # An ICP parameter: the baseline and the evaluation that compares it, nothing of the registration.
    assert pipe.set_params(pipe.params.with_value("icp", "trim", 0.6)) == ["icp", "evaluation"]
    # An evaluation parameter: the evaluation alone.
    assert pipe.set_params(pipe.params.with_value("evaluation", "layers", 4)) == []  # already dropped
    pipe.run("evaluation")
    assert pipe.set_params(pipe.params.with_value("evaluation", "layers", 3)) == ["evaluation"]


def test_failed_stage_stops_the_run_with_a_message(case):
    # Asking for more tie points than RANSAC can ever find makes coarse fail, not raise.
    params = Params().with_value("coarse", "min_ties", 1000)
    reg = register(case.scans, params, until="fine")
    assert not reg.ok
    assert reg.pipeline.status("coarse") == "failed"
    assert reg.pipeline.status("fine") == "stale"
    assert "scan2.ply" in reg.message and reg.message
    assert set(reg.transforms) == {"scan1.ply"}  # no transform claimed for a failed pair


def test_unchanged_params_change_nothing(case):
    pipe = Pipeline(list(case.scans[:2]), Params())
    pipe.run("matching")
    assert pipe.set_params(Params()) == []
    assert pipe.status("matching") == "done"
    assert np.isfinite(pipe.output("matching").seconds)


def _fail_pairs(pipe, stage, bad):
    """Replace the items of pairs `bad` of `stage`'s output with failures (as if the stage had failed there)."""
    from dataclasses import replace

    from treereg_core.stage import StageOutput

    out = pipe.output(stage)
    items = tuple(replace(it, ok=False, message="only 2 of 900 tie points agree") if k in bad else it
                  for k, it in enumerate(out.items))
    pipe._out[stage] = StageOutput(stage, False, "only 2 of 900 tie points agree", items, out.seconds)


def test_one_failed_pair_does_not_stop_the_others_and_its_scan_is_placed_through_them(case):
    """With three scans, a pair whose coarse stage fails is skipped by the later stages while the other
    pairs go on; its scan is still placed, through its pair with the third scan, and verified."""
    pipe = Pipeline(list(case.scans), Params(), case.truth())
    assert pipe.run("coarse").ok
    assert [(p.ref, p.tgt) for p in pipe.pairs] == [(0, 1), (0, 2), (1, 2)]
    _fail_pairs(pipe, "coarse", {1})  # scan3 -> scan1
    out = pipe.run("evaluation")
    assert out.stage == "evaluation"
    fine = pipe.output("fine")
    assert fine.items[0].ok and not fine.items[1].ok and fine.items[2].ok
    assert fine.items[1].message == "not run: coarse failed for this pair (only 2 of 900 tie points agree)"
    assert pipe.output("evaluation").items[0].ok and not pipe.output("evaluation").items[1].ok
    verdicts = pipe.verdicts()
    assert all(v[0] == "verified" for v in verdicts.values()), verdicts
    assert pipe.output("graph").items[2].via == (1,)  # scan3 rests on scan2 alone
    T = pipe.transforms()
    for k in (1, 2):
        assert mean_displacement(T[case.scans[k].name], case.T_ref_scan[k], case.scans[k].points) < 0.03


def test_a_scan_no_pair_reaches_fails_and_gets_no_transform(case):
    pipe = Pipeline(list(case.scans), Params(), case.truth())
    pipe.run("coarse")
    _fail_pairs(pipe, "coarse", {1, 2})  # both of scan3's pairs
    pipe.run("graph")
    verdicts = pipe.verdicts()
    assert verdicts["scan2.ply"][0] == "verified"
    assert verdicts["scan3.ply"][0] == "failed" and "coarse failed" in "; ".join(verdicts["scan3.ply"][1])
    assert set(pipe.transforms()) == {"scan1.ply", "scan2.ply"}  # no transform claimed for the failed one
