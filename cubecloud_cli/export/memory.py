"""Refuse an export that cannot fit in memory, before allocating any of it."""

from __future__ import annotations

import os

from cubecloud_cli.cameras.novel import MAGNIFICATIONS, SUPERSAMPLING
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.export.settings import ExportSettings

# Per pixel of one view while it renders: ray directions in float64 and float32, the ray
# intervals, the accumulator and the chunked march's working set (measured ≈ 120 B).
BYTES_PER_RENDERED_PIXEL = 160


def export_bytes(settings: ExportSettings, volume_size: int) -> int:
    """An upper estimate of the stage's peak memory in bytes."""
    pixels = settings.pixels() ** 2
    novel_views = settings.novel_directions * len(MAGNIFICATIONS)
    stacks = (2 * settings.views + novel_views) * pixels * 4  # images, reference and novel stacks, float32
    # Counted as if a novel reference's k × k sub-pixel renders were held at once (they go one at
    # a time): an upper estimate, as the refusal wants.
    largest = SUPERSAMPLING if novel_views else 1
    rendering = pixels * largest * largest * BYTES_PER_RENDERED_PIXEL
    bake = settings.bake_resolution(volume_size)
    grids = 3 * 4 * (volume_size**3 + (bake**3 if settings.render_from == "grid" else 0))
    cubes = -((-volume_size // settings.cube) ** 3)
    points = cubes * settings.points_per_cube * 4 * 12  # positions, values, masks, gradients
    return stacks + rendering + grids + points


def available_bytes() -> int | None:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def check_export_memory(settings: ExportSettings, volume_size: int) -> None:
    needed = export_bytes(settings, volume_size)
    available = available_bytes()
    if available is not None and needed > 0.8 * available:
        raise CubecloudError(
            f"export needs about {needed / 2**30:.1f} GiB and this machine has {available / 2**30:.1f} GiB: "
            f"lower --resolution (now {settings.resolution}), --views (now {settings.views}) "
            f"or --points-per-cube (now {settings.points_per_cube}), or raise --cube (now {settings.cube})"
        )
