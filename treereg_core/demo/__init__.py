"""The bundled demo case: three stations of a simulated 8 m tree on ground (0.06 deg steps), with
their true transforms. Made by our own simulator; `assets/README.md` gives the command."""

from __future__ import annotations

from pathlib import Path

from ..io.cases import Case, read_case

#: The folder holding scan1.ply, scan2.ply, scan3.ply and truth.json (inside the installed package).
DEMO_DIR = Path(__file__).resolve().parent


def demo_case(angular_step_deg: tuple[float, float] | None = None) -> Case:
    """The demo's scans and truth."""
    return read_case(DEMO_DIR, angular_step_deg)
