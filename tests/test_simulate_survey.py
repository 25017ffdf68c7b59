"""Simulated surveys (issue 31): stations on a grid over a whole plot, truth onto the first station,
an orchard of turned clones, and `treereg simulate --survey` writing a folder `io.cases` reads."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from treereg_cli.main import main
from treereg_core.errors import ConfigError
from treereg_core.geometry.rigid import apply_transform, make_transform
from treereg_core.io.cases import read_case
from treereg_core.simulate.survey import SurveySpec, station_names, survey_cases

#: A tiny survey: 3 x 2 stations 8 m apart, coarse steps (~50 k points a station), a fraction of a second.
TINY = SurveySpec(seed=3, grid=(3, 2), spacing_m=8.0, jitter_m=0.5, margin_m=3.0, n_trees=(8, 8),
                  tree_height_m=(6.0, 9.0), angular_step_deg=(0.5, 0.5))


@pytest.fixture(scope="module")
def tiny():
    return TINY.build()


def test_same_seed_same_points_station_by_station(tiny):
    again = TINY.build()
    assert tiny.names == again.names == station_names(6) == ("st01.ply", "st02.ply", "st03.ply", "st04.ply", "st05.ply", "st06.ply")
    for a, b in zip(tiny.scans, again.scans):
        assert np.array_equal(a.points, b.points)
    # One station alone (as write_survey streams them) is the same station.
    assert np.array_equal(TINY.world().scan(4).scan.points, tiny.scans[4].points)
    other = TINY.__class__(**{**TINY.to_dict(), "seed": 4, "grid": (3, 2)})
    assert not np.array_equal(other.build().scans[0].points[:100], tiny.scans[0].points[:100])


def test_stations_stand_on_the_grid_at_the_spacing_each_turned_its_own_way(tiny):
    xy = np.array([st.position_m[:2] for st in tiny.stations])
    grid = np.array([[(i - 1) * 8.0, (j - 0.5) * 8.0] for j in range(2) for i in range(3)])  # row by row
    assert np.abs(xy - grid).max() <= 0.5 + 1e-9
    headings = np.array([st.heading_deg for st in tiny.stations])
    assert np.ptp(headings) > 30 and all(st.tilt_deg == 0 for st in tiny.stations)
    for k, scan in enumerate(tiny.scans):
        assert 30_000 < scan.n_points < 150_000
        counts, _ = np.histogram(scan.azimuth_deg, bins=36, range=(-180, 180))
        assert (counts > 0).all(), f"{scan.name}: not a full panorama"
        # Trees keep clear of the stations; every station sees several trees.
        ids = tiny.tree_ids[k]
        assert len(np.unique(ids[ids >= 0])) >= 4
    bases = np.array([t.base_m[:2] for t in tiny.trees])
    assert np.min(np.hypot(*(bases[:, None] - xy[None]).transpose(2, 0, 1))) >= 1.5


def test_truth_maps_each_station_onto_the_same_trees_as_the_first(tiny):
    ref, ref_ids = tiny.scans[0].points, tiny.tree_ids[0]
    index = cKDTree(ref)
    for k in range(1, len(tiny.scans)):
        ids = tiny.tree_ids[k]
        on = ids >= 0
        for shift, share in ((0.0, 0.3), (0.3, 0.0)):  # the truth, and the truth 30 cm off (the test's control)
            T = make_transform(np.eye(3), [shift, 0.0, 0.0]) @ tiny.T_ref_scan[k]
            d, j = index.query(apply_transform(T, tiny.scans[k].points[on]), distance_upper_bound=0.5)
            near = d < 0.1  # the points are ~9 cm apart at 10 m (0.5 deg steps)
            if shift == 0.0:
                assert near.mean() > share, tiny.names[k]
                # Where they meet the first station's points, those are of the same tree.
                assert (ref_ids[j[near]] == ids[on][near]).mean() > 0.98, tiny.names[k]
            else:
                assert near.mean() < 0.1, tiny.names[k]
    assert np.array_equal(tiny.T_ref_scan[0], np.eye(4))


def test_orchard_copies_are_one_tree_each_turned():
    spec = SurveySpec(seed=2, grid=(2, 2), spacing_m=8.0, margin_m=2.0, orchard=True, angular_step_deg=(0.6, 0.6))
    world = spec.world()
    trees = world.trees
    assert len(trees) == world.n_trees == len(world.turns_deg) >= 12  # no shrubs in an orchard
    bases = np.array([t.base_m[:2] for t in trees])
    steps = np.diff(np.unique(np.round(bases[:, 0], 6)))
    assert np.allclose(steps % 3.0, 0) or np.allclose(steps, 3.0)  # 3 m along a row
    assert np.allclose(np.diff(np.unique(np.round(bases[:, 1], 6))) % 4.0, 0)  # rows 4 m apart
    a, b = trees[0].scene.cylinders.p1 - trees[0].base_m, trees[1].scene.cylinders.p1 - trees[1].base_m
    assert a.shape == b.shape
    turn = np.radians(world.turns_deg[1] - world.turns_deg[0])
    R = np.array([[np.cos(turn), -np.sin(turn), 0], [np.sin(turn), np.cos(turn), 0], [0, 0, 1]])
    assert np.allclose(a @ R.T, b, atol=1e-9)  # the same tree, turned about its vertical
    spread = (np.array(world.turns_deg) - world.turns_deg[0] + 180) % 360 - 180
    assert np.ptp(spread) > 90


@pytest.mark.parametrize("options, word", [
    ({"grid": (1, 1)}, "grid"), ({"grid": (3,)}, "grid"), ({"grid": (2.5, 3)}, "grid"), ({"grid": (20, 20)}, "grid"),
    ({"spacing_m": 0.5}, "spacing_m"), ({"spacing_m": float("nan")}, "spacing_m"), ({"jitter_m": 5.0}, "jitter_m"),
    ({"n_trees": (5, 2)}, "n_trees"), ({"n_trees": (-1, 2)}, "n_trees"), ({"tree_height_m": (1.0, 5.0)}, "tree_height_m"),
    ({"ground_slope_deg": 45.0}, "ground_slope_deg"), ({"angular_step_deg": (0.0, 0.1)}, "angular_step_deg"),
    ({"elevation_deg": (60.0, -40.0)}, "elevation_deg"), ({"dropout": 1.0}, "dropout"), ({"seed": -1}, "seed"),
    ({"tilt_deg": 20.0}, "tilt_deg"), ({"range_sigma_m": -0.1}, "range_sigma_m"),
])
def test_bad_spec_values_are_one_config_error_naming_them(options, word):
    with pytest.raises(ConfigError, match=word):
        SurveySpec(**options)


def test_benchmark_set_names_every_survey_and_small_ones_are_tiny():
    full, small = survey_cases(), survey_cases(small=True)
    assert list(full) == list(small) == ["3x3 leaf-off", "3x3 leafy", "4x4", "6x6", "3x3 sloped", "orchard 3x3", "10x6"]
    assert full["6x6"].n_stations == 36 and full["10x6"].n_stations == 60 and full["orchard 3x3"].orchard
    assert full["3x3 sloped"].ground_slope_deg == 12.0 and full["3x3 leafy"].leaves
    assert all(s.angular_step_deg[0] >= 0.5 for s in small.values())


def test_cli_writes_a_survey_folder_the_case_reader_reads(tmp_path, capsys):
    out = tmp_path / "survey"
    args = ["simulate", "--survey", "3x2", "--spacing", "8", "--trees", "8", "--seed", "3", "--angular-step", "0.5",
            "--out", str(out)]
    assert main(args) == 0
    assert "wrote 6 stations (st01.ply ... st06.ply)" in capsys.readouterr().out
    case = read_case(out)
    assert [s.name for s in case.scans] == list(station_names(6)) and case.scans[0].angular_step_deg == (0.5, 0.5)
    spec = SurveySpec(seed=3, grid=(3, 2), spacing_m=8.0, n_trees=(8, 8), angular_step_deg=(0.5, 0.5))
    world = spec.world()
    for k, T in enumerate(world.truth()):
        assert np.allclose(case.truth[spec.names[k]], T, atol=1e-9)
    assert np.array_equal(case.scans[2].points, world.scan(2).scan.points)
    assert case.truth_file.extra["simulation"]["survey"]["grid"] == [3, 2]


@pytest.mark.parametrize("args, says", [
    (["--survey", "3by3"], "--survey: needs COLSxROWS"), (["--survey", "3x3", "--spacing", "-4"], "--spacing"),
    (["--survey", "3x3", "--trees", "-1"], "--trees"), (["--survey", "3x3", "--stations", "4"], "--stations: only for a single-tree"),
    (["--orchard"], "--orchard: only with --survey"), (["--survey", "3x3", "--slope", "50"], "--slope"),
])
def test_cli_bad_survey_values_are_one_line_and_exit_2(tmp_path, capsys, args, says):
    assert main(["simulate", *args, "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0]
    assert not (tmp_path / "x").exists()
