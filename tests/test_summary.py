"""`treereg register`'s summary (issue 32, item 8): one row per scan — its verdict and the checks it
rests on, each beside its threshold; the reference as "reference"; never "nan" or "inf" — and every
pair's numbers only behind `--details` (a nine-station run printed about 1300 lines)."""

from __future__ import annotations

import contextlib
import io
import re

import pytest

from treereg_cli.main import main
from treereg_core.io.scans import write_scan
from treereg_core.simulate.cases import CaseSpec, benchmark_cases, write_case


@pytest.fixture(scope="module")
def printed(tmp_path_factory):
    """A small tree's three stations and a scan of another tree, registered twice (with and without
    --details): what each printed."""
    d = tmp_path_factory.mktemp("summary")
    write_case(benchmark_cases(3, seed=0, small=True)[1].build(), d)
    other = CaseSpec(seed=4242, height_m=8.0, angular_step_deg=(0.07, 0.07)).build().scans[1]
    write_scan(d / "other.ply", other.points)
    files = [str(d / n) for n in ("scan1.ply", "scan2.ply", "scan3.ply", "other.ply")]
    out = {}
    for flag in ((), ("--details",)):
        buf = io.StringIO()  # (capsys is function-scoped: captured by hand for the module)
        with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(io.StringIO()):
            rc = main(["register", *files, "--out", str(d / f"t{len(flag)}.json"), *flag])
        out[bool(flag)] = (rc, buf.getvalue())
    return out


def _rows(text: str) -> dict[str, str]:
    lines = text.splitlines()
    start = next(k for k, ln in enumerate(lines) if re.match(r"^\s+scan\s+verdict\s+consistency\s+residual\s+margin", ln))
    rows = {}
    for ln in lines[start + 1:]:
        if not ln.strip():
            break
        rows[ln.split()[0]] = ln
    return rows


def test_one_row_per_scan_each_check_beside_its_threshold(printed):
    rc, text = printed[False]
    assert rc == 1  # the other tree is not verified
    rows = _rows(text)
    assert list(rows) == ["scan1.ply", "scan2.ply", "scan3.ply", "other.ply"]
    assert re.fullmatch(r"\s+scan1\.ply\s+reference", rows["scan1.ply"])
    for name in ("scan2.ply", "scan3.ply"):
        assert re.search(r"verified\s+[01]\.\d{3} ✓ ≥ 0\.95\s+\d+\.\d mm ✓ ≤ \d+\.\d mm\s+-?\d\.\d{3} ✓ ≥ 0\.03\s+\d+\.\d mm\s+scan1\.ply",
                         rows[name]), rows[name]
    assert re.search(r"(failed|unverified)\s", rows["other.ply"]) and "✗" in rows["other.ply"], rows["other.ply"]
    assert not re.search(r"\b(nan|inf)\b", text, re.IGNORECASE), text


def test_every_pairs_numbers_only_with_details(printed):
    _, short = printed[False]
    _, long = printed[True]
    assert "scan2.ply -> scan1.ply" not in short and "inliers by chance" not in short
    assert "scan2.ply -> scan1.ply" in long and "inliers by chance" in long
    assert _rows(long) == _rows(short)  # the same summary either way
    assert len(short.splitlines()) < 20 < len(long.splitlines())
    assert not re.search(r"\b(nan|inf)\b", long, re.IGNORECASE)
