"""A PNG of the three orthogonal mid-slices, in the radiological display convention."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def mid_slices(volume: np.ndarray) -> dict[str, np.ndarray]:
    """Axial, coronal and sagittal mid-slices of a RAS volume as display images (row, column).

    Radiological convention: the patient's right on the viewer's left, anterior and superior at
    the top; sagittal with anterior on the left.
    """
    i, j, k = (n // 2 for n in volume.shape)
    return {
        "axial": volume[::-1, ::-1, k].T,
        "coronal": volume[::-1, j, ::-1].T,
        "sagittal": volume[i, ::-1, ::-1].T,
    }


def write_preview(volume: np.ndarray, path: Path) -> None:
    """Write the three mid-slices side by side with labels, 8-bit grey."""
    from PIL import Image, ImageDraw

    panels = mid_slices(volume)
    height = max(p.shape[0] for p in panels.values())
    label_band = 14
    gap = 4
    width = sum(p.shape[1] for p in panels.values()) + gap * (len(panels) - 1)
    canvas = np.zeros((height + label_band, width), dtype=np.uint8)
    x = 0
    positions = []
    for name, panel in panels.items():
        pixels = np.clip(np.nan_to_num(panel) * 255.0 + 0.5, 0, 255).astype(np.uint8)
        canvas[label_band : label_band + panel.shape[0], x : x + panel.shape[1]] = pixels
        positions.append((name, x))
        x += panel.shape[1] + gap
    image = Image.fromarray(canvas)
    draw = ImageDraw.Draw(image)
    for name, left in positions:
        draw.text((left + 2, 1), name, fill=255)
    image.save(path)
