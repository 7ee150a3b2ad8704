"""Writing rendered views: 8-bit PNGs for other tools, float stacks for training and eval, and a
contact sheet for people."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from cubecloud_cli.core.pictures import to_uint8
from cubecloud_cli.core.writes import save_picture

THUMBNAIL = 128  # pixels per view on the contact sheet


def view_names(count: int) -> list[str]:
    """view_000.png …: zero-padded so that name order is view order (3DGS sorts by name)."""
    digits = max(3, len(str(count - 1)))
    return [f"view_{index:0{digits}d}.png" for index in range(count)]


def write_views(images: np.ndarray, folder: Path, names: list[str]) -> None:
    """One 8-bit PNG per view, grey in three equal channels: the reference 3DGS code and gsplat
    assume RGB and fail on single-channel images."""
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    for image, name in zip(images, names):
        grey = to_uint8(image)
        save_picture(Image.fromarray(np.repeat(grey[..., None], 3, axis=2), mode="RGB"), folder / name)


def write_contact_sheet(
    images: np.ndarray, path: Path, held_out: set[int], title: str, columns: int | None = None
) -> None:
    """All views on one PNG, numbered in order; held-out (test) views are marked "test". Without
    ``columns`` the sheet is about square."""
    from PIL import Image, ImageDraw

    count, height, width = images.shape
    scale = min(1.0, THUMBNAIL / max(height, width))
    thumb_h, thumb_w = max(1, round(height * scale)), max(1, round(width * scale))
    columns = min(count, max(1, columns or math.ceil(math.sqrt(count * thumb_h / thumb_w))))
    rows = math.ceil(count / columns)
    gap, band = 2, 14
    sheet = Image.new("L", (columns * (thumb_w + gap) - gap, band + rows * (thumb_h + gap) - gap), 0)
    draw = ImageDraw.Draw(sheet)
    draw.text((2, 1), title, fill=255)
    for index, image in enumerate(images):
        row, column = divmod(index, columns)
        x, y = column * (thumb_w + gap), band + row * (thumb_h + gap)
        thumb = Image.fromarray(to_uint8(image)).resize((thumb_w, thumb_h), Image.BILINEAR)
        sheet.paste(thumb, (x, y))
        label = f"{index}{' test' if index in held_out else ''}"
        draw.text((x + 2, y + 1), label, fill=255)
    save_picture(sheet, path)
