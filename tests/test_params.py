"""The parameter tree: round trips, the paper preset, and errors that name the key."""

from __future__ import annotations

import json
import typing
from dataclasses import FrozenInstanceError, fields

import pytest

from treereg_core import params as P
from treereg_core.errors import ConfigError

# The paper's literal settings, with where the paper says so.
PAPER_VALUES = {
    ("projection", "pixel_factor"): 2,  # 2.1.1: a pixel covers 2 phi x 2 varphi
    ("projection", "theta_deg"): 10.0,  # 2.1.2: rotation degree theta typically 10 deg
    ("projection", "span_deg"): None,  # 2.1.2: from -360/n to 360/n
    ("matching", "n_pairs"): 3,  # 2.1.3: three pairs of similar images
    ("matching", "matches_per_pair"): 5,  # 2.1.3: the five best matching pairs per image pair
    ("coarse", "estimator"): "svd",  # 2.1.4: SVD (Challis, 1995) over the tie points
    ("slices", "quantiles"): (0.25, 0.5, 0.75),  # 2.2.1: quartiles of tree height
    ("slices", "thickness_m"): 0.1,  # 2.2.1: 10 cm
    ("arcs", "connectivity"): 3.0,  # 2.2.2: d_alpha, d_beta compared with 3 phi, 3 varphi
    ("fine", "estimator"): "svd",  # 2.2.3: SVD over the fitted centres
    ("fine", "max_iterations"): 1,  # one fine step
    ("evaluation", "layers"): 3,  # 3.3: bottom, middle and top layers of a branch
    ("fine", "method"): "ties",  # 2.2.3: centres and axis points as tie points
    ("arcs", "max_range_jump_m"): None,  # 2.2.2: connectivity by angles only
}

# Where our default deliberately departs from the paper.
ROBUST_DEPARTURES = {
    ("matching", "n_pairs"),
    ("matching", "matches_per_pair"),
    ("coarse", "estimator"),
    ("fine", "estimator"),
    ("fine", "max_iterations"),
    ("slices", "quantiles"),
}


def test_default_is_the_robust_preset():
    assert P.to_dict(P.Params()) == P.to_dict(P.PRESETS["robust"])


@pytest.mark.parametrize("key, value", sorted(PAPER_VALUES.items()))
def test_paper_preset_holds_the_papers_values(key, value):
    section, name = key
    assert getattr(getattr(P.PRESETS["paper"], section), name) == value


def test_paper_preset_differs_from_default_where_the_paper_says():
    paper, robust = P.to_dict(P.PRESETS["paper"]), P.to_dict(P.Params())
    differing = {(s, k) for s in paper for k in paper[s] if paper[s][k] != robust[s][k]}
    assert ROBUST_DEPARTURES <= differing


@pytest.mark.parametrize("preset", sorted(P.PRESETS))
def test_to_dict_from_dict_round_trip(preset):
    p = P.PRESETS[preset]
    d = P.to_dict(p)
    assert json.loads(json.dumps(d)) == d  # JSON-ready
    back = P.from_dict(json.loads(json.dumps(d)))
    assert P.to_dict(back) == d
    assert back == p  # tuples restored, not lists


def test_save_load_round_trip(tmp_path):
    p = P.PRESETS["paper"].with_value("coarse", "inlier_m", 0.25).with_value("prepare", "angular_step_deg", (0.04, 0.05))
    path = tmp_path / "sub" / "params.json"
    P.save(p, path)
    assert P.load(path) == p
    assert [f.name for f in path.parent.iterdir()] == ["params.json"]  # no temporary files left


def test_partial_file_keeps_the_base(tmp_path):
    path = tmp_path / "p.json"
    path.write_text(json.dumps({"matching": {"n_pairs": 7}}))
    p = P.load(path)
    assert p.matching.n_pairs == 7 and p.coarse == P.Params().coarse
    on_paper = P.load(path, base=P.PRESETS["paper"])
    assert on_paper.matching.n_pairs == 7 and on_paper.coarse == P.PRESETS["paper"].coarse
    path.write_text(json.dumps({"preset": "paper", "fine": {"max_iterations": 2}}))
    p = P.load(path)
    assert p.fine.max_iterations == 2 and p.matching == P.PRESETS["paper"].matching


def test_a_config_with_the_old_section_names_means_the_same(tmp_path):
    """`slicing` and `fitting` were renamed after their stages (`slices`, `sections`): a config file,
    transforms.json's params or `--set` written with the old names still sets the same fields."""
    from treereg_cli.common import apply_sets

    old = {"slicing": {"thickness_m": 0.2, "quantiles": [0.3, 0.6]}, "fitting": {"gate_m": 0.4, "taper_check": False}}
    path = tmp_path / "old.json"
    path.write_text(json.dumps(old))
    new = P.Params().with_value("slices", "thickness_m", 0.2).with_value("slices", "quantiles", (0.3, 0.6))
    new = new.with_value("sections", "gate_m", 0.4).with_value("sections", "taper_check", False)
    assert P.load(path) == new != P.Params()
    assert apply_sets(P.Params(), ["slicing.thickness_m=0.2"]).slices.thickness_m == 0.2
    assert "slicing" not in P.SECTIONS and "fitting" not in P.SECTIONS
    with pytest.raises(ConfigError, match="sections.no_such"):
        P.from_dict({"fitting": {"no_such": 1}})


def test_values_are_coerced_from_text():
    p = P.Params()
    assert p.with_value("coarse", "inlier_m", "0.25").coarse.inlier_m == 0.25
    assert p.with_value("coarse", "iterations", "300").coarse.iterations == 300
    assert p.with_value("matching", "beta_check", "yes").matching.beta_check is True
    assert p.with_value("projection", "border_px", "4, 6").projection.border_px == (4, 6)
    assert p.with_value("slices", "quantiles", [0.3, 0.6]).slices.quantiles == (0.3, 0.6)
    assert p.with_value("prepare", "crop_radius_m", None).prepare.crop_radius_m is None


@pytest.mark.parametrize(
    "data, message",
    [
        ({"nosuch": {}}, r"p\.json: unknown section 'nosuch'; sections are prepare, .*projection"),
        ({"coarse": {"inlier": 0.3}}, r"p\.json: coarse\.inlier: no such parameter"),
        ({"coarse": {"inlier_m": 99}}, r"p\.json: coarse\.inlier_m: 99 m is outside the allowed range \(0\.01 to 5 m\)"),
        ({"matching": {"n_pairs": 0}}, r"matching\.n_pairs: 0 pairs is outside the allowed range \(1 to 400 pairs\)"),
        ({"coarse": {"iterations": 2.5}}, r"coarse\.iterations: 2\.5 is not a valid whole number"),
        ({"coarse": {"iterations": "many"}}, r"coarse\.iterations: 'many' is not a valid whole number"),
        ({"coarse": {"estimator": "lsq"}}, r"coarse\.estimator: 'lsq' is not one of \['svd', 'ransac'\]"),
        ({"coarse": {"dof": 5}}, r"coarse\.dof: 5 is not one of \[4, 6\]"),
        ({"matching": {"beta_check": "maybe"}}, r"matching\.beta_check: 'maybe' is not a valid true/false value"),
        ({"projection": {"border_px": [1, 2, 3]}}, r"projection\.border_px: needs two numbers r1,r2, got 3"),
        ({"coarse": {"inlier_m": None}}, r"coarse\.inlier_m: a value is required"),
        ({"coarse": {"inlier_m": float("nan")}}, r"coarse\.inlier_m: nan is not a finite number"),
        ({"coarse": 3}, r"p\.json: section 'coarse' must be an object"),
        ({"preset": "fast"}, r"p\.json: unknown preset 'fast'; choose one of \['paper', 'robust'\]"),
    ],
)
def test_bad_values_name_the_file_and_key(tmp_path, data, message):
    path = tmp_path / "p.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ConfigError, match=message):
        P.load(path)


def test_bad_files(tmp_path):
    with pytest.raises(ConfigError, match=r"none\.json: no such parameter file"):
        P.load(tmp_path / "none.json")
    (tmp_path / "bad.json").write_text("{oops")
    with pytest.raises(ConfigError, match=r"bad\.json: not valid JSON"):
        P.load(tmp_path / "bad.json")
    (tmp_path / "list.json").write_text("[1, 2]")
    with pytest.raises(ConfigError, match=r"list\.json: expected a JSON object of sections"):
        P.load(tmp_path / "list.json")


@pytest.mark.parametrize("section", P.SECTIONS)
def test_every_field_is_documented_and_its_default_valid(section):
    """What the CLI and the app render: a doc and a unit for every field; defaults within range."""
    hints = typing.get_type_hints(type(getattr(P.Params(), section)))
    for f in P.field_info(section):
        meta = f.metadata
        assert isinstance(meta.get("doc"), str) and meta["doc"], f"{section}.{f.name} has no doc"
        assert isinstance(meta.get("unit"), str), f"{section}.{f.name} has no unit"
        assert f.name in hints
        default = f.default
        # every default passes the same check a user's value passes
        assert getattr(P.Params().with_value(section, f.name, default), section) == getattr(P.Params(), section)
        if meta.get("choices") is not None:
            assert default in meta["choices"]


def test_sections_are_frozen():
    p = P.Params()
    with pytest.raises(FrozenInstanceError, match="cannot assign to field 'inlier_m'"):
        p.coarse.inlier_m = 1.0  # type: ignore[misc]
    assert [f.name for f in fields(P.Params)] == list(P.SECTIONS)


@pytest.mark.parametrize("section, name", [("slices", "quantiles"), ("evaluation", "quantiles")])
def test_quantiles_outside_zero_one_are_rejected(section, name):
    with pytest.raises(ConfigError, match=rf"{section}\.{name}: 1\.5 is outside the allowed range \(0 to 1\)"):
        P.Params().with_value(section, name, (0.25, 0.5, 1.5))
    assert getattr(P.Params().with_value(section, name, "0.1, 0.9"), section).__getattribute__(name) == (0.1, 0.9)
