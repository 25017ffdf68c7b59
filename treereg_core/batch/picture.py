"""A small picture of a registered tree for the campaign report: top and side view, a colour per scan.

Points are drawn as pixels into a numpy image and encoded as PNG with zlib (no imaging library):
a misregistered scan shows as a second trunk or a shifted crown in its own colour.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

from ..geometry.rigid import apply_transform

#: Scan colours (RGB), reference first; the same order as the app's.
PALETTE = np.array([(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
                    (140, 86, 75), (227, 119, 194), (127, 127, 127)], dtype=np.uint8)
#: Points drawn per scan.
_POINTS = 20_000


def png_bytes(image: np.ndarray) -> bytes:
    """An H x W x 3 uint8 image as PNG bytes."""
    h, w, _ = image.shape
    raw = b"".join(b"\x00" + image[r].tobytes() for r in range(h))  # filter 0 per row

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))


def tree_picture(points: list[np.ndarray], transforms: list[np.ndarray | None], size_px: int = 180) -> bytes | None:
    """Top view (x, y) and side view (x, z) of the registered scans, side by side, as PNG bytes.

    `transforms[i]` maps scan i into the reference frame; scans without one are left out. None when
    nothing is registered.
    """
    placed = []
    for i, (pts, T) in enumerate(zip(points, transforms)):
        if T is None or len(pts) == 0:
            continue
        sub = pts[:: max(1, len(pts) // _POINTS)]
        placed.append((i, apply_transform(np.asarray(T, dtype=float), sub)))
    if not placed:
        return None
    allp = np.vstack([p for _, p in placed])
    lo = np.quantile(allp, 0.002, axis=0)
    hi = np.quantile(allp, 0.998, axis=0)
    span = float(max((hi - lo).max(), 1e-6)) * 1.04
    centre = (lo + hi) / 2.0
    image = np.full((size_px, 2 * size_px + 4, 3), 255, dtype=np.uint8)
    for i, p in placed:
        color = PALETTE[i % len(PALETTE)]
        for panel, (a, b) in enumerate(((0, 1), (0, 2))):
            u = ((p[:, a] - centre[a]) / span + 0.5) * (size_px - 1)
            v = (0.5 - (p[:, b] - centre[b]) / span) * (size_px - 1)
            ok = (u >= 0) & (u < size_px) & (v >= 0) & (v < size_px)
            image[v[ok].astype(int), u[ok].astype(int) + panel * (size_px + 4)] = color
    image[:, size_px:size_px + 4] = 200  # a grey gap between the views
    return png_bytes(image)
