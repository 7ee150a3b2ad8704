"""The paper MLP's arithmetic choices (cunerf/precision.py): float32 keeps its bits, bfloat16's
hidden layers stay close to float32 with a float32 output, the TF32 scope restores torch's
process-wide setting, and losses read in groups give the running mean and the failure point
that reading each step gives."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.cunerf.config import FieldConfig, RenderConfig, render_chunk
from cubecloud_cli.cunerf.fields import CuNeRFField
from cubecloud_cli.cunerf.model import CubeModel
from cubecloud_cli.cunerf.precision import PRECISIONS, matmul_scope, precision_problem
from cubecloud_cli.cunerf.settings import CunerfSettings
from cubecloud_cli.cunerf.supervision import TrainingVoxels
from cubecloud_cli.cunerf.training import Trainer


def _field(seed: int = 0) -> CuNeRFField:
    torch.manual_seed(seed)
    return CuNeRFField(FieldConfig(kind="cunerf"))


def test_float32_is_the_field_as_written():
    field = _field()
    points = torch.rand(257, 3) * 2 - 1
    encoded = field.encoding(points * math.pi)
    hidden = encoded
    for index, layer in enumerate(field.layers):
        if index == field.config.skip_at:
            hidden = torch.cat((encoded, hidden), dim=-1)
        hidden = torch.relu(layer(hidden))
    assert torch.equal(field.raw(points), field.head(hidden))


@given(scale=st.sampled_from([1e-6, 1.0, 15.9]), seed=st.integers(0, 3))
@settings(max_examples=8, deadline=None)
def test_bf16_hidden_layers_stay_near_float32_and_give_float32(scale, seed):
    # Points from the centre to the field's clamp (±16): the encoding's sin(2¹⁰·π·x) is float32
    # in both, so bfloat16 rounds the products (8 mantissa bits) and not the positions.
    field = _field(seed)
    points = (torch.rand(512, 3, generator=torch.Generator().manual_seed(seed)) * 2 - 1) * scale
    exact = field.raw(points)
    field.precision = "bf16"
    rounded = field.raw(points)
    assert rounded.dtype == torch.float32
    assert torch.isfinite(rounded).all()
    error = (rounded - exact).abs().max() / exact.abs().max().clamp_min(1e-6)
    assert error < 0.05, float(error)
    intensity, density = field(points)
    assert intensity.dtype == density.dtype == torch.float32


def test_bf16_gradients_reach_every_layer_in_float32():
    field = _field()
    field.precision = "bf16"
    field.raw(torch.rand(64, 3)).square().sum().backward()
    for parameter in field.parameters():
        assert parameter.grad is not None and parameter.grad.dtype == torch.float32
        assert torch.isfinite(parameter.grad).all()


def test_the_model_sets_both_fields_and_leaves_the_grid_alone():
    render = RenderConfig(cube_half_size=0.05, samples_per_axis=2, importance=4)
    model = CubeModel(FieldConfig(kind="cunerf", width=16, depth=3, skip_at=1), render)
    model.set_precision("bf16")
    assert model.coarse.precision == model.fine.precision == "bf16"
    grid = CubeModel(FieldConfig(kind="grid", resolutions=(4,), features=2, hidden=4), render)
    grid.set_precision("bf16")  # nothing to set: the grid computes in float32
    assert not hasattr(grid.coarse, "precision")


def test_the_tf32_scope_restores_the_process_setting_even_on_error():
    before = torch.get_float32_matmul_precision()
    with matmul_scope("tf32", torch.device("cpu")):  # the CPU is left alone
        assert torch.get_float32_matmul_precision() == before
    cuda = torch.device("cuda")
    with pytest.raises(KeyError):
        with matmul_scope("tf32", cuda):
            assert torch.get_float32_matmul_precision() == "high"
            raise KeyError
    assert torch.get_float32_matmul_precision() == before


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("model", ["fast", "cunerf"])
@pytest.mark.parametrize("device", ["cpu", "cuda"])
def test_precision_is_refused_only_where_it_cannot_run(precision, model, device):
    problem = precision_problem(precision, model, device)
    runs = precision == "float32" or (model == "cunerf" and device == "cuda")
    assert (problem is None) == runs, problem
    assert precision_problem("fp8", "cunerf", "cuda").startswith("--precision 'fp8' must be one of")


def test_a_gpu_renders_four_times_the_cpus_chunk():
    config = RenderConfig(cube_half_size=0.01, samples_per_axis=4, importance=64)
    assert render_chunk(config) == 2048
    assert render_chunk(config, "cuda") == 8192
    tiny = RenderConfig(cube_half_size=0.01, samples_per_axis=2, importance=0)
    assert render_chunk(tiny) == 32768  # the CPU's cap, as before


def _trainer(volume: np.ndarray, read_every: int, lr: float = 2e-3) -> Trainer:
    run = CunerfSettings(
        model="cunerf", iterations=30, batch_size=32, lr=lr, lr_final=lr, warmup=0, samples_per_axis=2, importance=4
    )
    torch.manual_seed(0)
    model = CubeModel(FieldConfig(kind="cunerf", width=16, depth=3, skip_at=1), run.render_config(volume.shape[0]))
    voxels = TrainingVoxels(torch.from_numpy(volume), 1, [], 0.8)
    return Trainer(model, voxels, run, torch.Generator().manual_seed(0), loss_read_every=read_every)


def test_losses_read_in_groups_give_the_same_running_mean_and_weights():
    volume = np.random.default_rng(0).random((8, 8, 8), dtype=np.float32)
    each, grouped = _trainer(volume, 1), _trainer(volume, 7)
    means = []
    for _ in range(20):
        each.step()
        grouped.step()
        means.append(each.smoothed_loss)
    assert grouped.smoothed_loss == means[13]  # read after steps 7 and 14, not yet after 20
    grouped.flush_losses()
    assert grouped.smoothed_loss == means[-1]
    for a, b in zip(each.model.state_dict().values(), grouped.model.state_dict().values()):
        assert torch.equal(a, b)
    assert grouped.state()["smoothed_loss"] == means[-1]


def test_a_loss_that_is_not_finite_names_its_own_iteration_when_read_late():
    trainer = _trainer(np.full((8, 8, 8), 0.5, np.float32), 5)
    for _ in range(6):
        trainer.step()
    with torch.no_grad():
        trainer.model.coarse.head.bias.fill_(float("nan"))  # iteration 7's loss is NaN
    for _ in range(3):
        trainer.step()
    with pytest.raises(FloatingPointError, match="at iteration 7"):
        trainer.flush_losses()
