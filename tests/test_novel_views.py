"""The novel-view test: pixel-area references, and the cells and headline that eval reports."""

import math

import numpy as np
import pytest
import torch

from cubecloud_cli.cameras import OrbitSpec, orbit_cameras
from cubecloud_cli.cameras.novel import HEADLINE_MAGNIFICATIONS, NovelViewSet
from cubecloud_cli.eval.novel_scores import NovelTest, angle_bin, annotate, pictured_views, summarize_novel
from cubecloud_cli.eval.outputs import cell_table
from cubecloud_cli.render import GridField, ImageModel, render_view
from cubecloud_cli.render.pixel_area import pixel_area_render, subpixel_points
from cubecloud_cli.transfer.function import TransferFunction


def blob_volume(size=24, seed=0):
    rng = np.random.default_rng(seed)
    grid = np.linspace(-1, 1, size)
    x, y, z = np.meshgrid(grid, grid, grid, indexing="ij")
    volume = np.exp(-((x - 0.2) ** 2 + y**2 + (z + 0.1) ** 2) / 0.2) + 0.3 * rng.uniform(size=(size,) * 3) * (
        x * x + y * y < 0.5
    )
    return np.clip(volume, 0, 1).astype(np.float32)


@pytest.mark.parametrize("kind", ["dvr", "mip"])
def test_a_pixel_area_render_is_the_mean_of_a_finer_image(kind):
    """k² images through sub-pixel points are the same rays as one image k times finer."""
    field = GridField(blob_volume())
    model = ImageModel(kind, TransferFunction(0.2, 0.8, 6.0), step=2 / 24)
    cameras = orbit_cameras(OrbitSpec(views=2, resolution=16, elevation=30.0))
    fine = type(cameras)(cameras.rotations, cameras.translations, 32, 32, 2 * cameras.focal)
    expected = render_view(field, fine, 1, model).numpy().reshape(16, 2, 16, 2).mean(axis=(1, 3))
    area = pixel_area_render(field, cameras, 1, model, field.support(model.support_threshold), torch.device("cpu"), 2)
    np.testing.assert_allclose(area, expected, atol=2e-6)
    assert sorted(subpixel_points(2)) == [(0.25, 0.25), (0.25, 0.75), (0.75, 0.25), (0.75, 0.75)]


def test_zooming_out_makes_point_samples_alias_and_area_samples_not():
    """A fine stripe pattern seen at 0.5×: sampling pixel centres picks stripes at random, the
    pixel-area mean is close to the pattern's mean grey, as a camera would record it."""
    size = 64
    stripes = (np.indices((size,) * 3)[0] % 2).astype(np.float32)  # one-voxel stripes across x
    field = GridField(stripes)
    model = ImageModel("slice", step=2 / size)
    novel = NovelViewSet.build(3, 4.0, 24)
    cameras = novel.cameras(0.5)
    centre = slice(9, 15)  # inside the cube's silhouette
    point = render_view(field, cameras, 2, model).numpy()[centre, centre]
    area = pixel_area_render(field, cameras, 2, model, None, torch.device("cpu"), 4)[centre, centre]
    assert float(point.std()) > 0.25  # the stripes come through as noise of nearly full contrast
    assert abs(float(area.mean()) - 0.5) < 0.05 and float(area.std()) < 0.1


def rows_for(test: NovelTest, psnr_of) -> list[dict]:
    rows = []
    for name, direction, magnification in test.views.entries():
        value = psnr_of(direction, magnification)
        rows.append(
            {
                "psnr": value,
                "ssim": 0.99,
                "mse": 10 ** (-value / 10),
                "psnr_foreground": value - 5,
                "ssim_foreground": 0.98,
                "mse_foreground": 1e-4,
            }
        )
    return rows


def test_cells_and_headline():
    views = NovelViewSet.build(4, 4.0, 16)
    test = NovelTest(views, np.zeros((len(views), 16, 16), dtype=np.float32))
    angles = np.array([5.0, 15.0, 50.0, 90.0])
    rows = annotate(rows_for(test, lambda d, m: 30.0 + d + 10 * m), test, angles)
    assert [r["angle_bin"] for r in rows[:4]] == ["0–10°", "10–20°", "≥ 45°", "≥ 45°"]
    summary = summarize_novel(rows)
    headline = [30.0 + d + 10 * m for m in HEADLINE_MAGNIFICATIONS for d in range(4)]
    assert summary["headline"]["views"] == 12 and summary["headline"]["psnr"] == pytest.approx(np.mean(headline))
    assert summary["by_magnification"]["2"]["psnr"] == pytest.approx(30 + 1.5 + 20)
    assert summary["angle_bins"] == ["0–10°", "10–20°", "≥ 45°"]  # the empty 20–45° bin is left out
    cell = next(c for c in summary["cells"] if c["angle"] == "≥ 45°" and c["magnification"] == 0.5)
    assert cell["views"] == 2 and cell["psnr"] == pytest.approx(30 + 2.5 + 5)
    table = cell_table(summary)
    assert table[0].startswith("| angle from nearest training camera | 0.5× | 0.75× | 1× | 1.33× | 2× |")
    assert "| ≥ 45° | 37.50 (2) |" in table[4] and table[-1].startswith("| all | 36.50 (4) |")


def test_angle_bins_at_their_edges():
    assert [angle_bin(a) for a in (0.0, 9.999, 10.0, 20.0, 44.9, 45.0, 180.0)] == [
        "0–10°",
        "0–10°",
        "10–20°",
        "20–45°",
        "20–45°",
        "≥ 45°",
        "≥ 45°",
    ]
    assert angle_bin(math.nan) == "unknown" and angle_bin(-1.0) == "unknown"


def test_the_pictured_views_are_above_below_zoomed_in_and_out():
    views = NovelViewSet.build(16, 4.0, 16)
    test = NovelTest(views, np.zeros((len(views), 16, 16), dtype=np.float32))
    names = [views.entries()[index][0] for _, index in pictured_views(test)]
    assert names == ["novel_m1_d00", "novel_m1_d01", "novel_m2_d02", "novel_m0.5_d02"]
    tiny = NovelViewSet.build(1, 4.0, 16)
    assert [label for label, _ in pictured_views(NovelTest(tiny, np.zeros((5, 16, 16))))] == ["from above (the head)"]
