"""Memory a raster needs, computed before it is allocated.

The size of the projection images and of the arcs' slice raster follows from the data's angular
span and the parameters (angular step, pixel factor, image size cap). A combination that would need
more than `MAX_RASTER_BYTES` is refused with a sentence naming what to change, instead of a
MemoryError (or a swapping machine) minutes later. `RasterTooLarge` is a `ConfigError`: the command
line prints it as one line and exits with status 2.
"""

from __future__ import annotations

from .errors import ConfigError

#: The most memory one stage may spend on rasters of one scan (2 GB of the 24 GB we plan for:
#: a stage holds a few, and two scans are in memory at once).
MAX_RASTER_BYTES = 2_000_000_000
#: The most points a scan uploaded to the app may hold unless `treereg view --max-upload-points`
#: says otherwise: about 64 bytes each while the app reads and prepares it (20 M: ~1.3 GB), and a
#: compressed file's size says nothing of it (190 kB of LAZ held 20 M points).
MAX_UPLOAD_POINTS = 20_000_000


class RasterTooLarge(ConfigError):
    """A raster the parameters ask for would not fit in memory; the message says what to change."""


def format_bytes(n: float) -> str:
    """1536 -> '1.5 kB', 3.2e9 -> '3.2 GB' (decimal units, as a person reads them)."""
    for unit in ("B", "kB", "MB", "GB", "TB"):
        if n < 1000 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000.0
    raise AssertionError  # unreachable


def check_raster(what: str, rows: float, cols: float, bytes_per_cell: float, advice: str, count: int = 1) -> None:
    """Raise `RasterTooLarge` when `count` rasters of `rows` x `cols` cells would exceed the budget.

    `what` names the raster and whose it is ("scan2.ply: the projection images"); `advice` says which
    parameter to change.
    """
    need = float(rows) * float(cols) * bytes_per_cell * count
    if need <= MAX_RASTER_BYTES:
        return
    many = f" each, {count} of them" if count > 1 else ""
    raise RasterTooLarge(
        f"{what} would need {format_bytes(need)} of memory ({cols:,.0f} x {rows:,.0f} cells{many}), "
        f"more than the {format_bytes(MAX_RASTER_BYTES)} treereg allows: {advice}")
