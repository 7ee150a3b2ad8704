"""Pixel-area renders: the fused march over interleaved sub-pixel rays against k² images."""

import numpy as np
import pytest
import torch

from cubecloud_cli.cameras.novel import NovelViewSet
from cubecloud_cli.render import GridField, ImageModel, pixel_area, render_view
from cubecloud_cli.render.pixel_area import pixel_area_render, pixel_area_renders, subpixel_points
from cubecloud_cli.render.rays import tiled_order
from cubecloud_cli.transfer.function import TransferFunction


@pytest.mark.parametrize(("height", "width", "tile"), [(8, 8, 4), (7, 10, 4), (5, 3, 8), (6, 6, 1)])
def test_the_tiled_order_lists_every_pixel_once_tile_by_tile(height, width, tile):
    order = tiled_order(height, width, tile)
    assert sorted(order.tolist()) == list(range(height * width))
    v, u = np.divmod(order, width)
    tile_of = (v // tile) * (-(-width // tile)) + u // tile
    assert (np.diff(tile_of) >= 0).all()  # a tile's pixels come together, tiles in order


def k_images(field, cameras, index, model, factor):
    total = np.zeros((cameras.height, cameras.width), dtype=np.float64)
    for point in subpixel_points(factor):
        total += render_view(field, cameras, index, model, subpixel=point).numpy()
    return (total / factor**2).astype(np.float32)


@pytest.mark.parametrize("factor", [2, 3])
def test_the_fused_pixel_area_render_is_the_k_images_to_the_bit(factor):
    rng = np.random.default_rng(3)
    volume = rng.uniform(size=(20, 20, 20)).astype(np.float32) ** 3
    field = GridField(volume)
    model = ImageModel("dvr", TransferFunction(0.1, 0.7, 30.0), step=2 / 20)
    cameras = NovelViewSet.build(3, 4.0, 13).cameras(1.33)  # 13 pixels: tiles cut at the edge
    fused = pixel_area_render(field, cameras, 2, model, None, torch.device("cpu"), factor)
    assert float(fused.std()) > 0.01
    np.testing.assert_array_equal(fused, k_images(field, cameras, 2, model, factor))


def test_pixel_area_renders_under_several_transfer_functions_are_each_render_alone():
    rng = np.random.default_rng(4)
    field = GridField(rng.uniform(size=(20, 20, 20)).astype(np.float32) ** 3)
    models = [ImageModel("dvr", TransferFunction(low, low + 0.3, 30.0), step=2 / 20) for low in (0.05, 0.2, 0.6)]
    cameras = NovelViewSet.build(3, 4.0, 13).cameras(0.75)
    together = pixel_area_renders(field, cameras, 1, models, None, torch.device("cpu"), 2)
    for image, model in zip(together, models):
        np.testing.assert_array_equal(image, pixel_area_render(field, cameras, 1, model, None, torch.device("cpu"), 2))
    assert together.shape == (3, 13, 13) and float(together.std(axis=(1, 2)).min()) > 0.001


def test_other_models_take_the_image_by_image_path(monkeypatch):
    calls = []
    monkeypatch.setattr(pixel_area, "march_grid_view", lambda *args: calls.append(args))
    field = GridField(np.ones((8, 8, 8), dtype=np.float32) * 0.5)
    cameras = NovelViewSet.build(2, 4.0, 8).cameras(1.0)
    mip = pixel_area_render(field, cameras, 0, ImageModel("mip", step=0.25), None, torch.device("cpu"), 2)
    assert calls == [] and mip.shape == (8, 8) and float(mip.max()) == pytest.approx(0.5)
