"""The layout promises of ARCHITECTURE.md, checked: the core never imports the app, no module
imports itself back through others, the core is split by concern, every stage is registered once."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import ROOT

PACKAGES = ("treereg_core", "treereg_viewer", "treereg_cli")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")}


def _imports(name: str, path: Path, known: set[str]) -> set[str]:
    """Project modules `name` imports (anywhere in the file, function bodies included)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            targets = [f"{base}.{a.name}" for a in node.names]
        else:
            continue
        for t in targets:
            # the longest known module the import names (a name imported from a module counts as the module)
            while t and t not in known:
                t = t.rpartition(".")[0]
            if t and t != name:
                out.add(t)
    return out


def test_importing_the_core_never_imports_the_app():
    code = "import treereg_core, treereg_core.stages, treereg_core.pipeline, sys; " \
           "print([m for m in sys.modules if 'viser' in m or 'treereg_viewer' in m])"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_no_import_cycles_among_the_projects_modules():
    mods = _modules()
    known = set(mods)
    graph = {m: _imports(m, p, known) for m, p in mods.items()}
    # Package __init__ files are entered on the way to any submodule; an edge into a package means
    # "its __init__", which must not lead back.
    state: dict[str, int] = {}
    cycles: list[list[str]] = []

    def visit(m: str, stack: list[str]) -> None:
        state[m] = 1
        for n in sorted(graph.get(m, ())):
            if state.get(n) == 1:
                cycles.append(stack[stack.index(n):] + [n])
            elif n not in state:
                visit(n, stack + [n])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def test_the_core_is_split_by_concern_and_only_the_cli_knows_both():
    core = ROOT / "treereg_core"
    subpackages = {p.name for p in core.iterdir() if (p / "__init__.py").is_file()}
    assert {"io", "geometry", "prepare", "coarse", "fine", "evaluate", "simulate", "demo"} <= subpackages
    mods = _modules()
    known = set(mods)
    for m, p in mods.items():
        deps = _imports(m, p, known)
        if m.startswith("treereg_core"):
            assert not any(d.startswith(("treereg_viewer", "treereg_cli")) for d in deps), (m, deps)
        if m.startswith("treereg_viewer"):
            assert not any(d.startswith("treereg_cli") for d in deps), (m, deps)
    # Only one module runs OpenCV (ORB).
    cv2_users = [m for m, p in mods.items() if "import cv2" in p.read_text()]
    assert cv2_users == ["treereg_core.coarse.features"], cv2_users


def test_every_stage_is_registered_once_with_its_sections_and_upstream():
    from treereg_core.params import SECTIONS, SURVEY_SECTIONS
    from treereg_core.stages import STAGE_NAMES, STAGES, downstream

    assert len(set(STAGE_NAMES)) == len(STAGE_NAMES)
    for i, s in enumerate(STAGES):
        assert set(s.sections) <= set(SECTIONS), s.name
        assert all(STAGE_NAMES.index(u) < i for u in s.upstream), s.name
    # Each parameter section is read by at least one stage (no orphan settings), but the survey's,
    # which the survey registration reads (treereg_core/survey, not a stage of the one-tree pipeline).
    read = {sec for s in STAGES for sec in s.sections}
    assert read == set(SECTIONS) - set(SURVEY_SECTIONS)
    survey_code = "".join(p.read_text() for p in (ROOT / "treereg_core" / "survey").glob("*.py"))
    assert all(f"params.{sec}" in survey_code or f".{sec}\n" in survey_code for sec in SURVEY_SECTIONS)
    assert downstream("arcs") == ("arcs", "sections", "fine", "verify", "graph", "evaluation")
    assert "slices" not in downstream("arcs") and "icp" not in downstream("fine")


def test_the_public_api_is_one_import():
    import treereg_core as T

    from treereg_core import params, pipeline, scan, stages
    from treereg_core.coarse import estimate
    from treereg_core.fine import pose
    from treereg_core.io import scans

    homes = {"register": pipeline.register, "Pipeline": pipeline.Pipeline, "Params": params.Params, "Scan": scan.Scan,
             "read_scan": scans.read_scan, "FineResult": pose.FineResult,
             "CoarseResult": estimate.CoarseResult, "STAGES": stages.STAGES}
    for name, obj in homes.items():
        assert getattr(T, name) is obj, name  # the object itself, not a copy or a stand-in
    assert set(T.__all__) >= {"register", "Pipeline", "Params", "Scan", "read_scan"}


#: What `mypy --strict` must pass on: the stage model, the registry and its stage modules, the pipeline and its workers,
#: and the app's registry with the types of its stages' entry points (AppStage, RenderFn, the controls), the snapshot
#: and its typed accessors (controller: `Snapshot.pair`, `Snapshot.scan_item`), and every stage and drawing module
#: that draws results through them.
TYPED = ("treereg_core/stage.py", "treereg_core/stages", "treereg_core/pipeline.py", "treereg_core/parallel.py",
         "treereg_viewer/stages/__init__.py", "treereg_viewer/stages/base.py", "treereg_viewer/controller.py",
         "treereg_viewer/align.py", "treereg_core/geometry/point_pairs.py", "treereg_core/verify/summary.py",
         "treereg_core/survey/inspect.py", "treereg_viewer/survey_view.py",
         *(f"treereg_viewer/draw/{name}.py" for name in (
             "__init__", "common", "fits", "motion", "images", "cross_section", "scan_layer", "before")),
         *(f"treereg_viewer/stages/{name}.py" for name in (
             "prepare", "projection", "matching", "coarse", "hypotheses", "slices", "arcs", "sections", "fine", "verify",
             "icp", "graph", "evaluation")))


def test_every_app_stage_and_drawing_module_is_typed():
    """A new stage or drawing module of the app joins TYPED (issue 29: under mypy as the core's are)."""
    app = {str(p.relative_to(ROOT)) for d in ("stages", "draw") for p in (ROOT / "treereg_viewer" / d).glob("*.py")}
    assert app <= set(TYPED), sorted(app - set(TYPED))


@pytest.mark.slow
def test_the_stage_model_registry_and_pipeline_pass_mypy_strict(tmp_path):
    pytest.importorskip("mypy", reason="mypy is not installed (pip install -e '.[test]')")
    # Imported modules are read for their types, their own errors not reported (--follow-imports=silent).
    done = subprocess.run([sys.executable, "-m", "mypy", "--strict", "--follow-imports=silent", "--no-incremental",
                           "--cache-dir", str(tmp_path), *TYPED], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr


def test_every_stages_result_is_a_keyword_only_dataclass_with_ok_message_metrics():
    import dataclasses

    from treereg_core.stages import STAGES

    for s in STAGES:
        assert dataclasses.is_dataclass(s.result), s.name
        fs = {f.name: f for f in dataclasses.fields(s.result)}
        # ok, message and metrics: fields, or properties derived from the fields (ImageSequence's)
        assert all(n in fs or isinstance(getattr(s.result, n, None), property) for n in ("ok", "message", "metrics")), s.name
        assert all(f.kw_only for f in fs.values()), (s.name, [n for n, f in fs.items() if not f.kw_only])
        assert s.result.__dataclass_params__.frozen, s.name
        with pytest.raises(TypeError):  # built by keyword only
            s.result(True, "", ())


def test_a_stages_name_is_its_modules_its_sections_and_its_views():
    """One name, one place per stage: `treereg_core/stages/<name>.py`, the parameter section <name>
    (every stage has parameters of its own), the viewer's `treereg_viewer/stages/<name>.py` and an
    entry keyed by <name> in the viewer's registry."""
    import importlib

    from treereg_core.params import SECTIONS
    from treereg_core.stages import STAGE_NAMES, STAGES

    core = {p.stem for p in (ROOT / "treereg_core" / "stages").glob("*.py")} - {"__init__", "common"}
    assert core == set(STAGE_NAMES)
    for s in STAGES:
        assert importlib.import_module(f"treereg_core.stages.{s.name}").STAGE is s
        assert s.name in SECTIONS and s.name in s.sections, f"{s.name}: no parameter section {s.name!r} it reads"
    viewer = ROOT / "treereg_viewer" / "stages"
    assert viewer.is_dir(), "the viewer's side of each stage: treereg_viewer/stages/<name>.py"
    assert {p.stem for p in viewer.glob("*.py")} >= set(STAGE_NAMES)
    registry = importlib.import_module("treereg_viewer.stages").STAGES  # the app's side, keyed by the core's names
    assert tuple(registry) == STAGE_NAMES
    assert all(app.name == name for name, app in registry.items())
