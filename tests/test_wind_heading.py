"""Issue 30: a heading about the stem that the free-space evidence cannot fix within
verify.max_heading_deg is not verified.

bench_wind's new seeded set (seed 1) has a leaf-on tree without ground (tree 2) whose scan2 -> scan1
came out at a 20 cm top sway 0.557° (11.1 mm) off the truth, all but 0.1° of it a turn about the
stem, and was verified: the heading scan's vertex lay 0.43° from the pose (<= 0.5), but its top was
broad and all on one side — turns of -1.0° to 0° all within 0.005 of the best consistency (the
leaves flutter), none the other way: the pose sits at the edge of what the evidence fits, which
bounds its heading no closer than 1.0°. Such a pair is now unverified, its reason naming the
heading. A broad top that the pose sits inside (right pairs of the same tree at 5-10 cm) still
passes on its vertex.
"""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from treereg_core.geometry.rigid import invert, rotation_error_deg
from treereg_core.params import Params
from treereg_core.pipeline import Pipeline
from treereg_core.verify import evidence
from treereg_core.verify.evidence import VERIFIED, Evidence, assess

#: The wrong pair's heading scan (turn about the stem from the pose, deg: consistency of the target
#: unbent), as the verify stage measured it at verify.max_heading_deg = 0.5 (reach 2°).
WRONG_CURVE = dict(zip(np.linspace(-2.0, 2.0, 17).round(2).tolist(), (
    0.8754, 0.8872, 0.8921, 0.8998, 0.9048, 0.9065, 0.9092, 0.9089, 0.9060,
    0.8982, 0.8928, 0.8833, 0.8702, 0.8578, 0.8380, 0.8142, 0.7939)))
#: A right pair's (the same tree's scan3 -> scan2, 0.35° off): the best within 0.5° of the pose, every
#: turn beyond it at least 0.005 worse.
RIGHT_CURVE = dict(zip(np.linspace(-2.0, 2.0, 17).round(2).tolist(), (
    0.9154, 0.9249, 0.9338, 0.9398, 0.9449, 0.9508, 0.9545, 0.9566, 0.9558,
    0.9547, 0.9531, 0.9504, 0.9477, 0.9409, 0.9340, 0.9257, 0.9195)))

#: A right pair's whose top is as broad but holds the pose (the same tree's scan3 -> scan2 at 10 cm,
#: 0.14° off: turns of -1.0° to +0.25° within 0.005 of the best).
INSIDE_CURVE = dict(zip(np.linspace(-2.0, 2.0, 17).round(2).tolist(), (
    0.9671, 0.9748, 0.9831, 0.9866, 0.9884, 0.9906, 0.9915, 0.9929, 0.9914,
    0.9901, 0.9858, 0.9759, 0.9679, 0.9601, 0.9512, 0.9451, 0.9348)))


def _scan(curve, monkeypatch) -> tuple[float, bool]:
    """`_heading_offset` on a recorded curve: the pose the identity, the stem at the origin, so each
    turn tried is read off its transform."""
    def visibility(ref_image, pts, T, tolerance_m, unbend=None):
        return SimpleNamespace(consistency=curve[round(float(np.degrees(np.arctan2(T[1, 0], T[0, 0]))), 2)])
    monkeypatch.setattr(evidence, "visibility", visibility)
    p = Params().verify
    return evidence._heading_offset(None, np.zeros((1, 3)), np.eye(4), np.zeros(2), None, 0.02,
                                    4.0 * p.max_heading_deg, p.max_heading_deg)


def _heading_check(offset: float, flat: bool):
    P = Params()
    e = Evidence(inliers=127, ties=900, chance_inliers=12, consistency=0.977, seen_by_both=4755, violations=110,
                 residual_m=0.002, noise_m=0.007, chosen="coarse", rival="RANSAC mode 3", margin=0.17, tilt_deg=0.1,
                 height_difference_m=None, sway_m=0.23, motion_m=0.1, motion_needed_m=0.065, consistency_still=0.906,
                 stem_tilt_deg=0.03, stem_tilt_std_deg=0.13, stem_shift_m=0.001, stem_shift_std_m=0.003,
                 base_offset_m=0.0015, base_offset_std_m=0.001, base_height_m=3.0,
                 heading_offset_deg=offset, heading_flat=flat)
    return assess(e, verify=P.verify, coarse=P.coarse, acceptance=P.acceptance, wind=P.wind)


def test_a_broad_heading_top_reaching_past_the_limit_is_flat_and_refused(monkeypatch):
    offset, flat = _scan(WRONG_CURVE, monkeypatch)
    assert flat and offset == pytest.approx(1.0)
    j = _heading_check(offset, flat)
    assert j.verdict != VERIFIED
    assert any("heading" in r for r in j.reasons), j.reasons


@pytest.mark.parametrize("curve", [RIGHT_CURVE, INSIDE_CURVE], ids=["narrow", "broad-around-the-pose"])
def test_a_heading_fixed_within_the_limit_still_passes(curve, monkeypatch):
    offset, flat = _scan(curve, monkeypatch)
    assert not flat and abs(offset) <= Params().verify.max_heading_deg
    assert _heading_check(offset, flat).verdict == VERIFIED


@pytest.fixture(scope="module")
def wrong_pair():
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from bench_wind import spec
    case = spec(2, 1, 0.2).build()
    scans, truth = list(case.scans), case.truth()
    pipe = Pipeline(scans, Params(), truth, workers=1)
    pipe.run("verify")
    k = next(i for i, p in enumerate(pipe.pairs) if (scans[p.tgt].name, scans[p.ref].name) == ("scan2.ply", "scan1.ply"))
    p, item = pipe.pairs[k], pipe.output("verify").items[k]
    T_true = invert(truth[scans[p.ref].name]) @ truth[scans[p.tgt].name]
    return item, rotation_error_deg(pipe._as_given(item.T_ref_target, p.ref, p.tgt), T_true)


@pytest.mark.slow
def test_the_leaf_on_pair_turned_about_its_stem_in_wind_is_not_verified(wrong_pair):
    item, rot_deg = wrong_pair
    # Verified only within 0.5° of the truth (it comes out 0.557° off, all but 0.1° about the stem).
    assert item.verdict != VERIFIED or rot_deg < 0.5, (rot_deg, item.reasons)
    if item.verdict != VERIFIED:
        assert any("heading" in r or "crown moved" in r for r in item.reasons), item.reasons
