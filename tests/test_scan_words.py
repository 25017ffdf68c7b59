"""Misleading words of issue 29 item 9 about what a scan holds: a scan of only ground among good ones
is that scan's failure (the others registered and written), a scan whose vertical is not its z says
so, and a stem without crown is not said to have a crown that moved."""

from __future__ import annotations

import json
import re

import numpy as np

from hostile import cli
from treereg_core.demo import demo_case
from treereg_core.io.scans import write_scan
from treereg_core.io.transforms import read_transforms


def test_a_scan_of_only_ground_fails_alone_and_the_others_are_written(tmp_path, capsys):
    case = demo_case()
    paths = []
    for s in case.scans:
        pts = s.points
        if s.name == "scan3.ply":  # a crop that missed the tree: its lowest 0.2 m, ground only
            pts = pts[pts[:, 2] < pts[:, 2].min() + 0.2]
        paths.append(write_scan(tmp_path / s.name, pts))
    out = tmp_path / "out" / "transforms.json"
    rc, err = cli(capsys, "register", *paths, "--angular-step", "0.06", "0.06", "--out", out)
    assert rc == 1, err  # a scan is not verified: exit 1, the others written
    tf = read_transforms(out)
    assert sorted(tf.transforms) == ["scan1.ply", "scan2.ply"]
    why = tf.extra["unregistered"]["scan3.ply"]
    assert why.startswith("it holds only ground: ") and "shows no stem to register" in why, why
    lines = [ln for ln in err.splitlines() if ln.startswith("treereg: ")]
    assert len(lines) == 1, err  # once, not once per pair it was in
    assert re.match(r"treereg: scan3\.ply: failed: it holds only ground: \d+ of its \d+ points lie on its ground plane "
                    r"\(within prepare\.ground_band_m = 0\.3 m of it\) and 0 above it, so it shows no stem to register "
                    r"\(try: leave it out, or give the scan of the tree .*--set prepare\.ground_band_m=0\.1\)\)$",
                    lines[0]), lines[0]
    assert "widen the crop" not in err and "same tree" not in err
    assert "scan3.ply" in json.dumps(tf.extra["quality"])
