"""Every parameter on the command line (issue 19): `--set section.field=value` on register, view,
batch and evaluate; hints that name the key and the `--set` they suggest; thresholds moved into Params."""

import ast
import json
import re
from pathlib import Path

import pytest

from hostile import cli, one_line
from treereg_cli.common import apply_sets, load_params, set_value
from treereg_cli.main import build_parser, main
from treereg_core import params as P
from treereg_core.coarse.matching import match_hints
from treereg_core.demo import DEMO_DIR, demo_case
from treereg_core.errors import ConfigError
from treereg_core.params import Params, PrepareParams, TargetParams
from treereg_core.prepare.ground import find_ground
from treereg_core.prepare.mixed import remove_mixed
from treereg_core.prepare.target import find_stems

REPO = Path(__file__).resolve().parents[1]
DEMO = [str(DEMO_DIR / f"scan{k}.ply") for k in (1, 2)]
BAD = [("projection.bogus=1", r"--set projection\.bogus: no such parameter"),
       ("bogus.theta_deg=1", r"--set bogus\.theta_deg: no such section"),
       ("projection.theta_deg=100", r"--set projection\.theta_deg: 100 deg is outside the allowed range"),
       ("projection.theta_deg=abc", r"--set projection\.theta_deg: 'abc' is not a valid number"),
       ("theta_deg=5", r"--set theta_deg=5: expected section\.field=value")]


@pytest.fixture(scope="module")
def coarse_file(tmp_path_factory):
    """The demo registered to the coarse stage with --set projection.theta_deg=5."""
    out = tmp_path_factory.mktemp("set") / "t.json"
    rc = main(["register", *DEMO, "--set", "projection.theta_deg=5", "--until", "coarse", "--out", str(out)])
    assert rc == 1  # stopped before verification: written, every scan unverified
    return out


def test_register_takes_a_set_parameter(coarse_file):
    params = json.loads(coarse_file.read_text())["params"]
    assert params["projection"]["theta_deg"] == 5.0
    assert params["projection"]["span_deg"] is None  # the rest as the default


@pytest.mark.parametrize("setting,message", BAD)
def test_a_bad_set_is_one_line_exit_2_on_register_batch_and_evaluate(setting, message, coarse_file, tmp_path, capsys):
    for command in (["register", *DEMO, "--out", str(tmp_path / "x.json")],
                    ["batch", str(tmp_path / "nothing-here")],
                    ["evaluate", str(coarse_file)]):
        rc, err = cli(capsys, *command, "--set", setting)
        assert rc == 2, (command, err)
        one_line(err, message)
    assert not (tmp_path / "x.json").exists()


def test_view_takes_set_after_config_and_before_the_flags(tmp_path, capsys):
    cfg = tmp_path / "p.json"
    cfg.write_text(json.dumps({"projection": {"theta_deg": 20}, "prepare": {"angular_step_deg": [0.1, 0.1]}}))
    args = build_parser().parse_args(["view", "--config", str(cfg), "--set", "projection.theta_deg=5",
                                      "--set", "prepare.angular_step_deg=0.2,0.3", "--angular-step", "0.05"])
    p = load_params(args)
    assert p.projection.theta_deg == 5.0  # --set over --config
    assert p.prepare.angular_step_deg == (0.05, 0.05)  # the specific flag over --set
    # A bad value stops `treereg view` before it serves anything: one line, exit 2.
    rc, err = cli(capsys, "view", "--port", "0", "--set", "projection.theta_deg=0")
    assert rc == 2
    one_line(err, r"--set projection\.theta_deg: 0 deg is outside the allowed range")


def test_set_values_are_json_first_then_text():
    assert [set_value(t) for t in ("5", "0.02", "true", "null", "None", "[1, 1.6]", "ramp", "1,1.6", '"auto"')] == \
        [5, 0.02, True, None, None, [1, 1.6], "ramp", "1,1.6", "auto"]
    p = apply_sets(Params(), ["coarse.final_inlier_m=null", "target.stem_band_m=1.2,2", "matching.beta_check=True",
                              "matching.image_mode=binary", "fine.loss_scale_m=0.004"])  # a moved key: joint
    assert p.coarse.final_inlier_m is None and p.target.stem_band_m == (1.2, 2.0) and p.matching.beta_check
    assert p.matching.image_mode == "binary" and p.joint.loss_scale_m == 0.004
    assert apply_sets(Params(), ["projection.theta_deg=5", "projection.theta_deg=7"]).projection.theta_deg == 7.0
    with pytest.raises(ConfigError, match=r"--set coarse\.dof: 5 is not one of \[4, 6\]"):
        apply_sets(Params(), ["coarse.dof=5"])


def test_explain_lists_every_key_as_a_set(capsys):
    assert main(["params", "--explain", "--set", "projection.theta_deg=5"]) == 0
    out = capsys.readouterr().out
    assert "--set SECTION.FIELD=VALUE" in out and "--preset, then --config, then each --set" in out
    shown = re.findall(r"^  --set (\w+\.\w+)=", out, flags=re.M)
    assert shown == [f"{s}.{f.name}" for s in P.SECTIONS for f in P.field_info(s)]
    assert "  --set projection.theta_deg=5 (deg)" in out
    for line in out.splitlines():  # each line's value is one --set takes back
        if m := re.match(r"^  --set (\w+)\.(\w+)=(\S*)", line):
            Params().with_value(m[1], m[2], set_value(m[3]))


def _literals(path: Path) -> list[tuple[int, str]]:
    """The string literals of a module (f-strings with their fields as {}), docstrings left out."""
    tree = ast.parse(path.read_text())
    docs = {id(n.body[0].value) for n in ast.walk(tree)
            if isinstance(n, (ast.Module, ast.FunctionDef, ast.ClassDef)) and n.body
            and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.JoinedStr):
            out.append((node.lineno, "".join(v.value if isinstance(v, ast.Constant) else "{}" for v in node.values)))
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docs:
            out.append((node.lineno, node.value))
    return out


#: Words by which a hint asks for a parameter to change.
CHANGE = re.compile(r"\b(smaller|larger|more|fewer|lower|raise|higher|widen|narrower|coarser|finer)\b")
KEY = re.compile(r"\b(" + "|".join(P.SECTIONS) + r")\.([a-z_0-9]+)\b")


def test_every_hint_names_keys_that_exist():
    fields = {f"{s}.{f.name}" for s in P.SECTIONS for f in P.field_info(s)}
    hints, missing = [], []
    for path in sorted([*REPO.glob("treereg_core/**/*.py"), *REPO.glob("treereg_cli/**/*.py")]):
        rel = str(path.relative_to(REPO))
        for line, text in _literals(path):
            if re.search(r"\btry\b", text) or "--set" in text:
                hints.append((rel, line, text))
                for m in KEY.finditer(text):
                    assert m[0] in fields, f"{rel}:{line} names {m[0]}, which is no parameter"
                # A hint asking for a parameter change says which parameter.
                if re.search(r"\btry\b", text) and CHANGE.search(text) and not KEY.search(text):
                    missing.append(f"{rel}:{line}: {text}")
    assert len(hints) >= 5, hints  # the search finds them at all
    assert not missing, "\n".join(missing)


def test_the_matching_hints_name_their_keys():
    hints = match_hints(P.PRESETS["paper"].matching).split(", ")
    assert len(hints) == 5
    for hint in hints:
        flag = re.search(r"--set (\w+)\.(\w+)=(\S+?)\)?$", hint)
        assert flag, hint
        Params().with_value(flag[1], flag[2], set_value(flag[3]))  # a value the key takes
    assert "a smaller projection.theta_deg (e.g. --set projection.theta_deg=5)" in hints
    with pytest.raises(ConfigError):  # a hint cannot name a parameter that does not exist
        P.set_flag("projection.theta", 5)


def test_moved_thresholds_reach_the_prepare_functions():
    scan = demo_case().scans[0]
    plane, _ = find_ground(scan.points, PrepareParams())
    assert plane is not None
    refused, why = find_ground(scan.points, PrepareParams(ground_min_cells=1_000_000))
    assert refused is None and "cells" in why
    heights = scan.points @ plane[:3] + plane[3]
    assert len(find_stems(scan.points, heights, TargetParams())) >= 1
    assert len(find_stems(scan.points, heights, TargetParams(stem_band_m=(40.0, 41.0)))) == 0
    kw = dict(enabled=True, tolerance_m=0.02, slope=4.0)
    default = remove_mixed(scan, **kw)
    assert default.n_removed > 0 and default.not_filtered == ""
    stood_down = remove_mixed(scan, **kw, max_share=0.0)
    assert stood_down.n_removed == 0 and "too many" in str(stood_down.metrics[0].value)
    assert "too many" in stood_down.not_filtered
    # dense_share 0: every scan counts as "many tails", so side-by-side tails are taken too.
    assert remove_mixed(scan, **kw, dense_share=0.0).n_removed > default.n_removed
