"""The real RIEGL VZ-400i station in shared/data: its angular step read right, its projection not striped."""

import pytest

from conftest import REAL_TREES, needs
from treereg_core.coarse.sequences import build_sequence
from treereg_core.io.scans import read_scan
from treereg_core.params import Params
from treereg_core.prepare.ground import prepare_scans
from treereg_core.prepare.image_check import stripe_fraction

STATION = REAL_TREES / "rtls_single_scan_scanner_at_origin.xyz.gz"


@pytest.fixture(scope="module")
def station():
    return read_scan(STATION)


@needs(STATION)
def test_the_step_estimate_matches_the_instruments_grid(station):
    # rTLS documents this scan as 0.622 deg horizontal x 0.048 deg vertical (580 x 2082 lines):
    # the instrument did not scan a square grid here.
    phi, varphi = station.angular_step_deg
    assert phi == pytest.approx(0.622, rel=0.02)
    assert varphi == pytest.approx(0.048, rel=0.03)
    assert station.step.source == "estimated" and not station.step.low
    assert station.n_points < 1_046_843  # first returns only by default (the file numbers them)


@needs(STATION)
def test_its_projection_is_not_striped(station):
    p = Params()
    (prepared,) = prepare_scans([station], prepare=p.prepare, target=p.target)
    seq = build_sequence(prepared.scan, projection=p.projection, n_scans=3)
    assert seq.pixel_deg[0] == pytest.approx(seq.pixel_deg[1])  # square pixels for a 13:1 grid
    occ = seq.projections[len(seq) // 2].image == 0
    assert max(stripe_fraction(occ)) < 0.05
    assert seq.message == ""
    # The paper's k*phi x k*varphi pixels squash the scene 13:1 (what the issue saw).
    paper = build_sequence(prepared.scan, projection=Params().projection.__class__(square_pixels=False), n_scans=3)
    assert paper.pixel_deg[0] > 10 * paper.pixel_deg[1]
