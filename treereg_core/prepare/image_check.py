"""Is a projection image usable: filled, and free of stripes?

A projection pixel must be at least one angular step wide in both directions. When it is not (a
wrong step estimate, or a step the user mistyped), every other pixel column or row stays empty
and the image is striped: ORB then finds the stripes' edges, not the tree. A mostly empty image
(a few points spread over a wide view) has nothing to match either. Both are cheap to see.
"""

from __future__ import annotations

import numpy as np

#: More than this share of single-pixel gaps (empty pixels between two occupied ones, relative to
#: the occupied pixels) along one direction: the image is striped.
STRIPED = 0.12
#: Less than this share of the occupied bounding box filled: the image is mostly empty.
MOSTLY_EMPTY = 0.03


def stripe_fraction(occupied: np.ndarray) -> tuple[float, float]:
    """Single-pixel gaps along rows (x) and along columns (y), each relative to the occupied pixels."""
    occ = np.asarray(occupied, dtype=bool)
    n = max(int(occ.sum()), 1)
    gx = (~occ[:, 1:-1] & occ[:, :-2] & occ[:, 2:]).sum() / n
    gy = (~occ[1:-1, :] & occ[:-2, :] & occ[2:, :]).sum() / n
    return float(gx), float(gy)


def fill_rate(occupied: np.ndarray) -> float:
    """Occupied share of the occupied pixels' bounding box."""
    occ = np.asarray(occupied, dtype=bool)
    if not occ.any():
        return 0.0
    rows, cols = np.flatnonzero(occ.any(axis=1)), np.flatnonzero(occ.any(axis=0))
    box = (rows[-1] - rows[0] + 1) * (cols[-1] - cols[0] + 1)
    return float(occ.sum() / box)


def image_warning(occupied: np.ndarray) -> str:
    """A sentence naming what is wrong with the image and what to do, or "" when it looks fine."""
    gx, gy = stripe_fraction(occupied)
    if max(gx, gy) > STRIPED:
        along = "azimuth" if gx >= gy else "elevation"
        return (f"the projection is striped along {along} ({max(gx, gy):.0%} single-pixel gaps): its pixels are "
                "smaller than the scan's angular step there; check the step and give it with --angular-step H V")
    fill = fill_rate(occupied)
    if fill < MOSTLY_EMPTY:
        return (f"the projection is mostly empty ({fill:.1%} of its extent filled): the points are too sparse for "
                "the pixel size; give the instrument's steps with --angular-step H V or raise the pixel factor "
                "(projection.pixel_factor, e.g. --set projection.pixel_factor=4)")
    return ""
