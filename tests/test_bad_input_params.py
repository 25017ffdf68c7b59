"""Hostile parameters, round 3 (issue 29): a preset that is not a name, a list of a million
heights, a 2-vector given one number. Each is one line naming where it came from, exit 2, at once,
for a config file and `--set` alike (both go through `Params.with_value`, as the app's inputs do)."""

from __future__ import annotations

import json
import time
import typing

import pytest

from hostile import cli, one_line
from treereg_core import params as P
from treereg_core.errors import ConfigError


@pytest.mark.parametrize("preset", [["paper"], {"name": "paper"}, 3])
def test_a_preset_that_is_not_a_name_is_one_line_naming_the_file_and_key(tmp_path, capsys, preset):
    cfg = tmp_path / "p.json"
    cfg.write_text(json.dumps({"preset": preset}))
    rc, err = cli(capsys, "params", "--config", cfg)
    assert rc == 2
    one_line(err, r"^treereg: error: .*p\.json: preset: .* is not a preset name; give one of \['paper', 'robust'\] "
                  r"as a string, e\.g\. \"preset\": \"paper\"$")


@pytest.mark.parametrize("key", ["slices.quantiles", "evaluation.quantiles"])
def test_a_million_quantiles_are_refused_at_once(tmp_path, capsys, key):
    section, name = key.split(".")
    cfg = tmp_path / "q.json"
    cfg.write_text(json.dumps({section: {name: [0.5] * 1_000_000}}))
    for args in (["--config", cfg], ["--set", f"{key}=" + ",".join(["0.5"] * 1_000_000)]):
        start = time.monotonic()
        rc, err = cli(capsys, "params", *args)
        assert rc == 2 and time.monotonic() - start < 5.0
        one_line(err, rf"^treereg: error: .*{key}: 1,000,000 values given; at most {P.MAX_QUANTILES} are allowed$")
    # the most allowed is taken, one more is not
    assert len(P.Params().with_value(section, name, [0.5] * P.MAX_QUANTILES).__getattribute__(section).quantiles) == 64
    with pytest.raises(ConfigError, match=rf"{key}: 65 values given"):
        P.Params().with_value(section, name, [0.5] * (P.MAX_QUANTILES + 1))


def test_every_list_parameter_is_bounded_and_every_pair_names_its_numbers():
    """A list of any length has a max_len (each value is work); a fixed tuple names its parts."""
    for section in P.SECTIONS:
        hints = typing.get_type_hints(type(getattr(P.Params(), section)))
        for f in P.field_info(section):
            hint = hints[f.name]
            hint = next((a for a in typing.get_args(hint) if typing.get_origin(a) is tuple), hint)
            if typing.get_origin(hint) is not tuple:
                continue
            elem = typing.get_args(hint)
            if elem[-1] is Ellipsis:
                assert isinstance(f.metadata["max_len"], int) and f.metadata["max_len"] >= 1, f"{section}.{f.name}"
            else:
                assert f.metadata["parts"] and len(f.metadata["parts"]) == len(elem), f"{section}.{f.name}"


@pytest.mark.parametrize("setting, pattern", [
    ("target.tree_at=1", r"--set target\.tree_at: needs two numbers x,y, got 1$"),
    ("target.tree_at=1,2,3", r"--set target\.tree_at: needs two numbers x,y, got 3$"),
    ("target.stem_band_m=1.3", r"--set target\.stem_band_m: needs two numbers lowest,highest, got 1$"),
    ("projection.border_px=4", r"--set projection\.border_px: needs two numbers r1,r2, got 1$"),
])
def test_a_pair_given_one_number_is_refused(capsys, setting, pattern):
    rc, err = cli(capsys, "params", "--set", setting)
    assert rc == 2
    one_line(err, r"^treereg: error: " + pattern)


def test_an_angular_step_given_once_still_means_both():
    """The one pair where one number means both (0.05 is 0.05 x 0.05), as --angular-step and the app take it."""
    assert P.Params().with_value("prepare", "angular_step_deg", 0.05).prepare.angular_step_deg == (0.05, 0.05)
    assert P.Params().with_value("prepare", "angular_step_deg", "0.05").prepare.angular_step_deg == (0.05, 0.05)
