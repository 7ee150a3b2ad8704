"""Pictures for people that several stages make: values in [0, 1] as 8-bit grey, and a PNG of a
volume's three orthogonal mid-slices in the radiological display convention."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cubecloud_cli.core.writes import save_picture


def to_uint8(image: np.ndarray) -> np.ndarray:
    """[0, 1] (NaN as 0) to 0..255, rounded to the nearest level."""
    return np.clip(np.rint(np.nan_to_num(image) * 255.0), 0, 255).astype(np.uint8)


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
    write_preview_rows([("", volume)], path)


def write_preview_rows(rows: list[tuple[str, np.ndarray]], path: Path) -> None:
    """One row of mid-slices per labelled volume (all S³ alike), values in [0, 1]."""
    from PIL import Image, ImageDraw

    label_band, gap, margin = 14, 4, 2
    all_panels = [mid_slices(volume) for _, volume in rows]
    names = list(all_panels[0])
    panel_width = [max(p[name].shape[1] for p in all_panels) for name in names]
    row_height = max(p[name].shape[0] for p in all_panels for name in names)
    width = sum(panel_width) + gap * (len(names) - 1)
    height = label_band + len(rows) * (row_height + margin) - margin
    canvas = np.zeros((height, width), dtype=np.uint8)
    top = label_band
    for panels in all_panels:
        x = 0
        for name, panel_w in zip(names, panel_width):
            panel = panels[name]
            pixels = np.clip(np.nan_to_num(panel) * 255.0 + 0.5, 0, 255).astype(np.uint8)
            canvas[top : top + panel.shape[0], x : x + panel.shape[1]] = pixels
            x += panel_w + gap
        top += row_height + margin
    image = Image.fromarray(canvas)
    draw = ImageDraw.Draw(image)
    x = 0
    for name, panel_w in zip(names, panel_width):
        draw.text((x + 2, 1), name, fill=255)
        x += panel_w + gap
    top = label_band
    for label, _ in rows:
        if label:
            draw.text((2, top + 2), label, fill=255)
        top += row_height + margin
    save_picture(image, path)
