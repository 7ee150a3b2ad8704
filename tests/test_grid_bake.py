"""The fused bake of a grid field (cunerf/grid_bake.py) against the torch cube renders it replaces."""

import numpy as np
import pytest
import torch

from cubecloud_cli.cunerf import grid_bake
from cubecloud_cli.cunerf.api import CunerfField, grid_centres
from cubecloud_cli.cunerf.config import FieldConfig, RenderConfig
from cubecloud_cli.cunerf.model import CubeModel, render_many
from cubecloud_cli.cunerf.supervision import Occupancy

original = grid_bake.bake_lattice


def model_with_structure(activation="softplus", samples=2, importance=0, seed=0) -> CubeModel:
    """A grid model whose features and MLP are large enough that intensity and density vary."""
    torch.manual_seed(seed)
    field = FieldConfig(kind="grid", density_activation=activation, resolutions=(4, 9, 16), features=2, hidden=8)
    render = RenderConfig(cube_half_size=1 / 16, samples_per_axis=samples, importance=importance, separate_fine=False)
    model = CubeModel(field, render)
    with torch.no_grad():
        model.coarse.table.normal_(0.0, 1.5)
        for layer in (model.coarse.mlp[0], model.coarse.mlp[2]):
            layer.weight.normal_(0.0, 1.0)
            layer.bias.normal_(0.0, 0.5)
    return model


def torch_bake(model: CubeModel, size: int, occupancy) -> np.ndarray:
    keep = None if occupancy is None else occupancy.occupied
    centres = grid_centres(size, torch.device("cpu"))
    values = render_many(model, centres, None, keep, torch.Generator().manual_seed(0))
    return values.clamp(0.0, 1.0).reshape(size, size, size).numpy()


def occupancy_of(size: int, seed: int = 1) -> Occupancy:
    blocks = torch.from_numpy(np.random.default_rng(seed).uniform(size=(4, 4, 4)) < 0.5)
    return Occupancy(blocks, size // 4, size)


@pytest.mark.parametrize(
    ("activation", "samples", "with_occupancy"),
    [("softplus", 2, True), ("relu", 2, False), ("softplus", 3, False), ("relu", 3, True)],
)
def test_the_fused_bake_renders_what_the_torch_cubes_render(activation, samples, with_occupancy):
    """Lattices of one shell (2³) and of four (3³: centre, faces, edges, corners)."""
    size = 16
    model = model_with_structure(activation, samples)
    occupancy = occupancy_of(size) if with_occupancy else None
    assert grid_bake.applies(model, torch.device("cpu"))
    fused = np.empty((size,) * 3, dtype=np.float32)
    grid_bake.bake_lattice(model, size, occupancy, fused)
    expected = torch_bake(model, size, occupancy)
    assert float(expected.std()) > 0.05  # the test field has structure to get wrong
    np.testing.assert_allclose(fused, expected, rtol=0, atol=2e-6)
    if with_occupancy:
        assert (fused == 0).sum() >= (expected == 0).sum() > 0  # the air blocks read 0


def test_a_bake_at_another_size_than_the_occupancy_skips_the_same_cubes():
    model = model_with_structure()
    occupancy = occupancy_of(16)
    fused = np.empty((24,) * 3, dtype=np.float32)
    grid_bake.bake_lattice(model, 24, occupancy, fused)
    np.testing.assert_allclose(fused, torch_bake(model, 24, occupancy), rtol=0, atol=2e-6)


def test_extreme_raw_values_stay_finite():
    """Raw outputs far past exp's float32 range: sigmoid and softplus must not overflow to NaN."""
    model = model_with_structure()
    with torch.no_grad():
        model.coarse.mlp[2].bias.copy_(torch.tensor([-1e4, 1e4]))
    fused = np.empty((8,) * 3, dtype=np.float32)
    grid_bake.bake_lattice(model, 8, None, fused)
    assert np.isfinite(fused).all()
    np.testing.assert_allclose(fused, torch_bake(model, 8, None), rtol=0, atol=2e-6)


def test_models_the_kernel_does_not_cover_go_through_torch():
    cpu = torch.device("cpu")
    assert not grid_bake.applies(model_with_structure(importance=8), cpu)  # a fine pass
    mlp = CubeModel(FieldConfig(kind="cunerf", width=8, depth=2, skip_at=1), RenderConfig(1 / 16, 2, 0))
    assert not grid_bake.applies(mlp, cpu)
    official = CubeModel(FieldConfig(kind="grid", resolutions=(4,)), RenderConfig(1 / 16, 2, 0, official=True))
    assert not grid_bake.applies(official, cpu)


def test_the_field_bake_takes_the_kernel_from_its_size_on(monkeypatch):
    model = model_with_structure()
    field = CunerfField(model, 16, np.eye(4), occupancy_of(16))
    through_torch = field.bake(16)  # below MIN_SIZE: the kernel's compilation would cost more
    calls = []
    monkeypatch.setattr(grid_bake, "MIN_SIZE", 16)
    monkeypatch.setattr(grid_bake, "bake_lattice", lambda *args: calls.append(args) or original(*args))
    fused = field.bake(16)
    assert len(calls) == 1
    np.testing.assert_allclose(fused, through_torch, rtol=0, atol=2e-6)
