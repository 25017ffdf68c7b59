"""The campaign's summary: `summary.csv` (a row per tree), `scans.csv` (a row per scan) and a
self-contained `report.html` (verdicts, errors against truth when known, times and a picture per tree,
the pictures inlined as data URIs, so the one file can be mailed or archived)."""

from __future__ import annotations

import base64
import csv
import html
import io
import re
from pathlib import Path

from ..io.atomic import write_text_atomic
from .jobs import SUMMARY_NAMES
from .tree import TreeOutcome

TREE_COLUMNS = ("tree", "status", "exit_code", "scans", "verified", "unverified", "failed", "points", "read_s", "register_s",
                "total_s", "max_rot_err_deg", "max_disp_err_m", "message")
SCAN_COLUMNS = ("tree", "scan", "verdict", "points", "rot_err_deg", "disp_err_m", "message", "started_from")


#: Colour class of a scan's verdict in the report.
VERDICT_CLASS = {"failed": "failed", "unverified": "partial"}


def _num(v: float | None, digits: int) -> str:
    return "" if v is None else f"{v:.{digits}f}"


def tree_row(o: TreeOutcome) -> dict[str, str]:
    rot = [s.rot_err_deg for s in o.scans if s.rot_err_deg is not None]
    disp = [s.disp_err_m for s in o.scans if s.disp_err_m is not None]
    return {
        "tree": o.tree, "status": o.status, "exit_code": str(o.exit_code), "scans": str(len(o.scans)),
        "verified": str(sum(s.verdict in ("reference", "verified") for s in o.scans)),  # the reference counts
        "unverified": str(sum(s.verdict == "unverified" for s in o.scans)),
        "failed": str(sum(s.verdict == "failed" for s in o.scans)),
        "points": str(sum(s.points for s in o.scans)),
        "read_s": _num(o.seconds.get("read"), 2), "register_s": _num(o.seconds.get("register"), 2),
        "total_s": _num(o.seconds.get("total"), 2),
        "max_rot_err_deg": _num(max(rot), 4) if rot else "", "max_disp_err_m": _num(max(disp), 5) if disp else "",
        "message": o.message,
    }


#: What a spreadsheet takes for the start of a formula (OWASP, CSV injection): a tree or scan name
#: such as `=HYPERLINK(...)` would run as one when the summary is opened.
_FORMULA_START = ("=", "+", "-", "@", "\t", "\r")
_NUMBER = re.compile(r"[-+]?\d+(\.\d*)?([eE][-+]?\d+)?")


def csv_cell(text: str) -> str:
    """`text` as a CSV cell no spreadsheet runs: a cell starting as a formula does is prefixed with
    a single quote (OWASP), unless it is a plain number (ours: a negative error stays a number)."""
    if text.startswith(_FORMULA_START) and not _NUMBER.fullmatch(text):
        return "'" + text
    return text


def _csv(columns: tuple[str, ...], rows: list[dict[str, str]]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=columns, lineterminator="\n")
    w.writeheader()
    w.writerows({k: csv_cell(v) for k, v in row.items()} for row in rows)
    return buf.getvalue()


def write_summary(outcomes: list[TreeOutcome], out_dir: Path, pictures: dict[str, bytes | None],
                  title: str = "treereg batch") -> list[Path]:
    """Write summary.csv, scans.csv and report.html into `out_dir`; returns their paths."""
    out_dir = Path(out_dir)
    rows = [tree_row(o) for o in outcomes]
    scan_rows = [{"tree": o.tree, "scan": s.name, "verdict": s.verdict, "points": str(s.points),
                  "rot_err_deg": _num(s.rot_err_deg, 4), "disp_err_m": _num(s.disp_err_m, 5), "message": s.message,
                  "started_from": s.started_from}
                 for o in outcomes for s in o.scans]
    texts = (_csv(TREE_COLUMNS, rows), _csv(SCAN_COLUMNS, scan_rows), report_html(outcomes, pictures, title))
    paths = [write_text_atomic(out_dir / name, text) for name, text in zip(SUMMARY_NAMES, texts)]
    return paths


STYLE = """
body{font-family:system-ui,sans-serif;margin:24px;color:#222}
table{border-collapse:collapse}td,th{border-bottom:1px solid #ddd;padding:6px 10px;text-align:left;vertical-align:top}
th{background:#f4f4f4}.ok{color:#1a7f37}.partial,.unverified{color:#b35900}.failed,.error{color:#c62828}
.scan{white-space:nowrap}.msg{max-width:420px;font-size:90%;color:#555}
"""


def report_html(outcomes: list[TreeOutcome], pictures: dict[str, bytes | None], title: str) -> str:
    """The HTML report: one row per tree."""
    counts = {s: sum(o.status == s for o in outcomes) for s in ("ok", "partial", "unverified", "failed", "error")}
    e = html.escape
    head = (f"<h1>{e(title)}</h1><p>{len(outcomes)} trees: " +
            ", ".join(f'<span class="{k}">{v} {k}</span>' for k, v in counts.items() if v) + "</p>")
    rows = []
    for o in outcomes:
        png = pictures.get(o.tree)
        img = (f'<img alt="top and side view of {e(o.tree)}" src="data:image/png;base64,'
               f'{base64.b64encode(png).decode()}">' if png else "")
        scans = "<br>".join(
            f'<span class="scan">{e(s.name)}: <b class="{VERDICT_CLASS.get(s.verdict, "ok")}">{e(s.verdict)}</b>'
            + (f", {s.rot_err_deg:.3f}&deg; / {1000 * s.disp_err_m:.1f} mm" if s.disp_err_m is not None else "")
            + (f", started from {e(s.started_from)}" if s.started_from else "") + "</span>" for s in o.scans)
        times = ", ".join(f"{k} {v:.1f} s" for k, v in o.seconds.items())
        rows.append(f'<tr><td>{e(o.tree)}</td><td>{img}</td><td class="{o.status}">{o.status}</td><td>{scans}</td>'
                    f'<td>{times}</td><td class="msg">{e(o.message)}</td></tr>')
    table = ("<table><tr><th>tree</th><th>verified scans (top, side)</th><th>status</th>"
             "<th>scans: verdict, error against truth</th><th>times</th><th>message</th></tr>" + "".join(rows) + "</table>")
    return (f"<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>{e(title)}</title>"
            f"<style>{STYLE}</style></head><body>{head}{table}</body></html>\n")
