"""Colours of the app: one per scan (as in the paper's figures) and a categorical set for arcs."""

from __future__ import annotations

import colorsys

import numpy as np

#: Scan 1 green, scan 2 red, scan 3 blue (paper Figs. 7, 9, 10), then more for extra scans.
SCAN_COLORS: tuple[tuple[int, int, int], ...] = (
    (30, 170, 60),
    (215, 40, 40),
    (40, 80, 230),
    (235, 150, 20),
    (150, 60, 200),
    (20, 180, 190),
)

#: Points that a stage removed (ground, crop) or that are only context.
GREY = (150, 150, 150)
#: Kept vs rejected matches and tie lines. No line or arc colour is a scan's colour (nor close to one:
#: `distinct_from_scans`), so a line never reads as part of a scan and two scans' arcs stay apart.
KEPT = (230, 0, 200)
REJECTED = (170, 170, 170)
HIGHLIGHT = (255, 215, 0)
#: Where the fine stage moved the target's tie points from (its starting pose) to (the fine pose).
OFFSET = (20, 20, 20)

#: Categorical colours for arcs, chosen away from every scan colour and from grey ('not in an arc').
CATEGORICAL = np.array(
    [
        (255, 215, 0), (230, 0, 200), (120, 60, 20), (20, 30, 110), (125, 140, 0),
        (0, 95, 95), (255, 140, 170), (110, 0, 40), (150, 200, 255), (40, 40, 40),
    ],
    dtype=np.uint8,
)


#: Two colours closer than this in every channel read as the same colour on screen (shading moves a
#: point's colour by about as much).
MIN_CHANNEL_GAP = 60


def distinct_from_scans(rgb: tuple[int, int, int] | np.ndarray) -> bool:
    """Whether `rgb` differs from every scan colour by at least MIN_CHANNEL_GAP in some channel."""
    c = np.asarray(rgb, dtype=int)
    return all(int(np.abs(c - np.asarray(s)).max()) >= MIN_CHANNEL_GAP for s in SCAN_COLORS)


#: A survey's stations after the scan colours: six more, each apart from the others and from every scan
#: colour (`MIN_CHANNEL_GAP`), none yellow (a stem's ring) or grey (left out); then hues by the golden angle.
MORE_STATION_COLORS: tuple[tuple[int, int, int], ...] = (
    (140, 86, 75), (230, 110, 190), (150, 150, 20), (20, 30, 110), (0, 110, 100), (120, 0, 40),
)
_GOLDEN = 0.618033988749895


def station_color(index: int) -> tuple[int, int, int]:
    """The colour of survey station `index`: the scan colours, then `MORE_STATION_COLORS`, then hues
    spread by the golden angle (a 6 x 6 grid has 36 stations; neighbours in the list stay apart)."""
    fixed = SCAN_COLORS + MORE_STATION_COLORS
    if index < len(fixed):
        return fixed[index]
    h = (0.11 + index * _GOLDEN) % 1.0
    r, g, b = colorsys.hsv_to_rgb(h, 0.75, 0.85 if index % 2 else 0.6)
    return int(r * 255), int(g * 255), int(b * 255)


#: A survey's links, as the survey report colours them: used by the placement, verified but dropped by
#: a loop that did not close, unverified, failed.
LINK_COLORS: dict[str, tuple[int, int, int]] = {"used": (26, 127, 55), "dropped": (142, 68, 173),
                                                "unverified": (179, 89, 0), "failed": (198, 40, 40)}


def scan_color(index: int) -> tuple[int, int, int]:
    """The colour of scan number `index` (0 = reference)."""
    return SCAN_COLORS[index % len(SCAN_COLORS)]


def categorical(labels: np.ndarray) -> np.ndarray:
    """N x 3 uint8 colours, one per integer label (negative labels grey)."""
    labels = np.asarray(labels, dtype=np.int64)
    out = CATEGORICAL[np.mod(labels, len(CATEGORICAL))]
    out[labels < 0] = GREY
    return out


def hex_color(rgb: tuple[int, int, int]) -> str:
    return "#{:02x}{:02x}{:02x}".format(*rgb)


#: Points without a residual (seen by their scan alone, or not registered under the pose shown).
NO_RESIDUAL = (215, 215, 215)
#: Points that moved with the wind: off the other scans' surface as registered, on it once the
#: crown's measured motion is taken out (never a scan's colour, nor one of the residual ramp's).
MOVED = (255, 80, 180)
#: Mixed pixels the preparation removed (the Scans stage, on request).
MIXED = (25, 25, 25)
#: The residual colour map, from 0 to its top: dark blue, teal, green, yellow, red (a perceptually
#: ordered ramp, as viridis ends in yellow; red marks the top and beyond).
_RAMP = np.array([(40, 30, 120), (30, 120, 160), (40, 170, 90), (240, 210, 30), (215, 40, 40)], dtype=float)


def residual_colors(distances_m: np.ndarray, max_m: float) -> np.ndarray:
    """N x 3 uint8: each distance on the ramp from 0 to `max_m` (beyond: the top colour), NaN grey."""
    d = np.asarray(distances_m, dtype=float)
    t = np.clip(np.nan_to_num(d / max(max_m, 1e-9), nan=0.0), 0.0, 1.0) * (len(_RAMP) - 1)
    lo = np.minimum(np.floor(t).astype(int), len(_RAMP) - 2)
    f = (t - lo)[:, None]
    out = (_RAMP[lo] * (1 - f) + _RAMP[lo + 1] * f).astype(np.uint8)
    out[~np.isfinite(d)] = NO_RESIDUAL
    return out


def residual_legend(max_m: float, width: int = 360, height: int = 14) -> np.ndarray:
    """The colour bar of `residual_colors` from 0 to `max_m`, as an image for the panel."""
    bar = residual_colors(np.linspace(0.0, max_m, width), max_m)
    return np.ascontiguousarray(np.repeat(bar[None, :, :], height, axis=0))
