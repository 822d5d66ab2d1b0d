"""Pictures: the rendered pose over the photo (estimate magenta, ground truth green)."""

from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw

ESTIMATE_COLOR = (255, 0, 255)
TRUTH_COLOR = (0, 255, 0)


def mask_contour(mask: np.ndarray, width: int = 2) -> np.ndarray:
    """Pixels of `mask` within `width` px of its boundary."""
    mask = np.asarray(mask, dtype=bool)
    inner = mask.copy()
    for _ in range(width):
        shrunk = inner.copy()
        shrunk[1:, :] &= inner[:-1, :]
        shrunk[:-1, :] &= inner[1:, :]
        shrunk[:, 1:] &= inner[:, :-1]
        shrunk[:, :-1] &= inner[:, 1:]
        inner = shrunk
    return mask & ~inner


def overlay_mask(image_rgb: np.ndarray, mask: np.ndarray, color=ESTIMATE_COLOR, tint: float = 0.25) -> np.ndarray:
    """The photo with `mask` tinted and outlined in `color` (uint8 H x W x 3)."""
    out = np.asarray(image_rgb, dtype=np.float32).copy()
    mask = np.asarray(mask, dtype=bool)
    col = np.asarray(color, dtype=np.float32)
    out[mask] = (1 - tint) * out[mask] + tint * col
    out[mask_contour(mask)] = col
    return np.clip(out, 0, 255).astype(np.uint8)


def overlay_rendering(
    image_rgb: np.ndarray, rgb: np.ndarray, mask: np.ndarray, color=ESTIMATE_COLOR, opacity: float = 0.6
) -> np.ndarray:
    """The rendered object (float RGB in [0, 1]) blended over the photo, outlined in `color`."""
    out = np.asarray(image_rgb, dtype=np.float32).copy()
    mask = np.asarray(mask, dtype=bool)
    out[mask] = (1 - opacity) * out[mask] + opacity * 255.0 * rgb[mask]
    out[mask_contour(mask)] = np.asarray(color, dtype=np.float32)
    return np.clip(out, 0, 255).astype(np.uint8)


def caption(image_rgb: np.ndarray, lines: list[str]) -> np.ndarray:
    """The picture with a strip of text below it (what a person wants to read next to it)."""
    h, w = image_rgb.shape[:2]
    strip = 14 * len(lines) + 8
    canvas = Image.new("RGB", (w, h + strip), (20, 20, 20))
    canvas.paste(Image.fromarray(np.asarray(image_rgb, dtype=np.uint8)), (0, 0))
    draw = ImageDraw.Draw(canvas)
    for i, line in enumerate(lines):
        draw.text((6, h + 4 + 14 * i), line, fill=(235, 235, 235))
    return np.asarray(canvas)
