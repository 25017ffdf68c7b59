"""2-D drawing for the image panel: binary projection images in colour, side by side, with lines.

Pure numpy (the core keeps OpenCV to one module). Projection images follow the paper's eq. 3
(row 0 = lowest elevation, column grows with azimuth), so they are shown flipped both ways: the tree
upright and as seen from the scanner.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def binary_to_rgb(image: np.ndarray, color: tuple[int, int, int], ramp: bool = False) -> np.ndarray:
    """H x W x 3 uint8: occupied pixels (0) in `color`, empty pixels (255) white, shown upright.

    With `ramp`, grey values in between are blended (for the grey distance ramp ORB may see).
    """
    img = np.asarray(image)
    t = (img.astype(np.float32) / 255.0)[..., None] if ramp else (img > 0)[..., None].astype(np.float32)
    rgb = (1.0 - t) * np.asarray(color, np.float32) + t * 255.0
    return np.ascontiguousarray(rgb[::-1, ::-1].astype(np.uint8))


def upscale(image: np.ndarray, factor: int) -> np.ndarray:
    """Nearest-neighbour enlargement by an integer factor (small binary images stay crisp)."""
    if factor <= 1:
        return image
    return np.ascontiguousarray(np.repeat(np.repeat(image, factor, axis=0), factor, axis=1))


def fit_factor(width: int, target: int = 540, most: int = 4) -> int:
    """The integer enlargement that brings `width` closest to `target` without exceeding it."""
    return int(max(1, min(most, target // max(width, 1))))


def display_xy(xy: np.ndarray, shape: tuple[int, int], factor: int = 1) -> np.ndarray:
    """Image (x = column, y = row) coordinates -> coordinates in the flipped (and enlarged) display image."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    rows, cols = shape
    flipped = np.stack([cols - 1 - xy[:, 0], rows - 1 - xy[:, 1]], axis=1)
    return flipped * factor + (factor - 1) / 2.0


@dataclass(frozen=True)
class Layout:
    """Where each tile landed in a composed image: top-left (x, y) offsets."""

    image: np.ndarray
    offsets: tuple[tuple[int, int], ...]


def hstack(tiles: list[np.ndarray], gap: int = 8) -> Layout:
    """Tiles side by side, top-aligned, on white; returns the image and each tile's offset."""
    h = max(t.shape[0] for t in tiles)
    w = sum(t.shape[1] for t in tiles) + gap * (len(tiles) - 1)
    out = np.full((h, w, 3), 255, dtype=np.uint8)
    offsets, x = [], 0
    for t in tiles:
        out[: t.shape[0], x : x + t.shape[1]] = t
        offsets.append((x, 0))
        x += t.shape[1] + gap
    return Layout(out, tuple(offsets))


def vstack(tiles: list[np.ndarray], gap: int = 8) -> Layout:
    """Tiles one above the other, centred, on white."""
    w = max(t.shape[1] for t in tiles)
    h = sum(t.shape[0] for t in tiles) + gap * (len(tiles) - 1)
    out = np.full((h, w, 3), 255, dtype=np.uint8)
    offsets, y = [], 0
    for t in tiles:
        x = (w - t.shape[1]) // 2
        out[y : y + t.shape[0], x : x + t.shape[1]] = t
        offsets.append((x, y))
        y += t.shape[0] + gap
    return Layout(out, tuple(offsets))


def draw_lines(
    image: np.ndarray, p0: np.ndarray, p1: np.ndarray, colors: np.ndarray, thickness: int = 1
) -> None:
    """Draw segments p0[i] -> p1[i] (x, y pixel coordinates) in place, colour per segment."""
    p0 = np.asarray(p0, np.float64).reshape(-1, 2)
    p1 = np.asarray(p1, np.float64).reshape(-1, 2)
    if len(p0) == 0:
        return
    colors = np.broadcast_to(np.asarray(colors, np.uint8).reshape(-1, 3), (len(p0), 3))
    n = int(np.ceil(np.abs(p1 - p0).max())) + 2  # samples per segment: no gaps along the longest
    t = np.linspace(0.0, 1.0, n)
    pts = p0[:, None, :] + (p1 - p0)[:, None, :] * t[None, :, None]  # (segments, n, 2)
    cols = np.repeat(colors, n, axis=0)
    _stamp(image, pts.reshape(-1, 2), cols, thickness)


def draw_markers(image: np.ndarray, xy: np.ndarray, colors: np.ndarray, radius: int = 2) -> None:
    """Filled square markers at (x, y), in place."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    if len(xy) == 0:
        return
    colors = np.broadcast_to(np.asarray(colors, np.uint8).reshape(-1, 3), (len(xy), 3))
    _stamp(image, xy, colors, 2 * radius + 1)


def _stamp(image: np.ndarray, xy: np.ndarray, colors: np.ndarray, size: int) -> None:
    h, w = image.shape[:2]
    r = np.arange(size) - size // 2
    dx, dy = np.meshgrid(r, r)
    x = (np.rint(xy[:, 0])[:, None] + dx.ravel()[None, :]).astype(np.int64)
    y = (np.rint(xy[:, 1])[:, None] + dy.ravel()[None, :]).astype(np.int64)
    c = np.repeat(colors[:, None, :], dx.size, axis=1)
    keep = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    image[y[keep], x[keep]] = c[keep]


def fit_width(image: np.ndarray, max_width: int = 1400) -> np.ndarray:
    """Shrink an image wider than `max_width` by an integer factor, so it travels quickly.

    Min-pooling (per channel): on a white background, thin dark or coloured structure survives.
    """
    k = int(np.ceil(image.shape[1] / max_width))
    if k <= 1:
        return image
    h, w = (image.shape[0] // k) * k, (image.shape[1] // k) * k
    blocks = image[:h, :w].reshape(h // k, k, w // k, k, -1)
    return np.ascontiguousarray(blocks.min(axis=(1, 3)))
