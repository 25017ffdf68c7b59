"""Accuracy in wind (issue 30, item 1): the pose from what does not move.

A bend and a tilt of the scanner move a stem alike, and where the stem bends from (the root plate,
below the lowest point the scans see) is not known; the ground does not sway. The full families:
`benchmarks/bench_wind.py`.
"""

from __future__ import annotations

import numpy as np
import pytest

from treereg_core.fine.bend import cantilever
from treereg_core.fine.pose import _hinge_fit
from treereg_core.fine.stem import StemProfile
from treereg_core.geometry.rigid import mean_displacement, rotation_error_deg
from treereg_core.params import Params
from treereg_core.pipeline import Pipeline
from treereg_core.simulate.cases import CaseSpec
from treereg_core.verify.evidence import VERIFIED


def _spec(wind_m: float) -> CaseSpec:
    # The stage contract's small windy pair (under 10 s a run), on ground.
    return CaseSpec(seed=101, height_m=8.5, angular_step_deg=(0.07, 0.07), n_stations=2, wind_m=wind_m, ground=True)


def _run(case, params: Params):
    pipe = Pipeline(list(case.scans), params, case.truth())
    pipe.run("verify")
    v, f = pipe.output("verify").items[0], pipe.output("fine").items[0]
    T = pipe._as_given(v.T_ref_target, 0, 1)
    T_true = case.T_ref_scan[1]
    return v, f, rotation_error_deg(T, T_true), mean_displacement(T, T_true, case.scans[1].points)


@pytest.fixture(scope="module")
def windy():
    case = _spec(0.15).build()
    return case, _run(case, Params())


def test_the_hinge_fit_finds_where_the_stem_bends_from():
    lo, hi, depth = -1.5, 7.0, 0.3
    z = np.arange(lo + 0.2, lo + 4.5, 0.25)
    shift, offset_top = np.array([0.002, -0.001]), np.array([-0.12, 0.05])
    off = shift[None] + cantilever((z - (lo - depth)) / (hi - (lo - depth)))[:, None] * offset_top[None]
    prof = StemProfile(z, off, np.full(len(z), 0.001), np.full(len(z), 0.1), lo, hi - lo, None, np.zeros(2))
    got = _hinge_fit(prof, lo, hi, 1.0)
    assert got is not None
    d, s, top = got
    assert d == pytest.approx(depth, abs=0.051)
    assert np.allclose(s, shift, atol=5e-4) and np.allclose(top, -offset_top, atol=0.01)
    # A stem bending from its lowest point traced is found there.
    off0 = cantilever((z - lo) / (hi - lo))[:, None] * offset_top[None]
    prof0 = StemProfile(z, off0, np.full(len(z), 0.001), np.full(len(z), 0.1), lo, hi - lo, None, np.zeros(2))
    assert _hinge_fit(prof0, lo, hi, 1.0)[0] == pytest.approx(0.0, abs=0.051)


def test_a_windy_pair_on_ground_is_right_within_a_tenth_of_a_degree_and_5_mm(windy):
    case, (v, f, rot, disp) = windy
    assert v.verdict == VERIFIED, v.reasons
    assert rot < 0.1 and disp < 0.005, (rot, disp)  # before issue 30: 0.159 deg, 9.2 mm
    assert f.anchored == "ground" and 0.1 <= f.hinge_depth_m <= 0.6  # the simulator's trunk sinks 0.3 m
    true = float(np.linalg.norm(case.relative_sway_m(1)))
    assert f.bend is not None and abs(f.bend.sway_m - true) <= 0.15 * true  # before: 13% short and more
    metrics = {m.description: m.value for m in f.metrics}
    assert metrics["tilt taken from what does not move (wind)"] == "the ground"
    assert abs(metrics["crown moved between the stations (stem top)"] - true) <= 0.15 * true
    assert 0.0 < metrics["stem stands as the reference's up to (above its base)"] < 3.0


@pytest.mark.slow
def test_without_the_anchor_the_crown_pulls_the_tilt_and_in_still_air_nothing_changes(windy):
    case, (_, _, rot, disp) = windy
    _, f_off, rot_off, disp_off = _run(case, Params().with_value("wind", "ground_anchor", False))
    assert f_off.anchored == "" and rot_off > 0.1 and rot_off > 2 * rot and disp_off > disp
    still = _spec(0.0).build()
    _, f_on, *err_on = _run(still, Params())
    _, f_off, *err_off = _run(still, Params().with_value("wind", "ground_anchor", False))
    assert f_on.anchored == "" and np.array_equal(f_on.T_ref_target, f_off.T_ref_target) and err_on == err_off
