"""Colours of the app: one per scan (as in the paper's figures) and a categorical set for arcs."""

from __future__ import annotations

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
#: Kept vs rejected matches and tie lines.
KEPT = (20, 200, 60)
REJECTED = (170, 170, 170)
HIGHLIGHT = (250, 200, 0)

#: Categorical colours for arcs (Tableau 10, its grey swapped for indigo: grey means 'not in an arc').
CATEGORICAL = np.array(
    [
        (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
        (140, 86, 75), (227, 119, 194), (57, 59, 121), (188, 189, 34), (23, 190, 207),
    ],
    dtype=np.uint8,
)


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
