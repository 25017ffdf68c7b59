"""Shared test helpers. `SHARED` is the `shared/` folder beside the project checkout (CI puts it there)."""

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
REAL_TREES = SHARED / "data" / "real_trees"
