"""The two fields: the paper's MLP and the CPU grid; shapes, ranges and the grid lookup."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.cunerf import grid_kernels
from cubecloud_cli.cunerf.fields import (
    CuNeRFField,
    FieldConfig,
    FusedGridLookup,
    FusedMLP,
    GridField,
    PositionalEncoding,
    TrilinearLookup,
    build_field,
    trilinear_corners,
)
from cubecloud_cli.cunerf.settings import grid_resolutions


def test_positional_encoding_matches_the_paper():
    encoding = PositionalEncoding(11)
    assert encoding.out_features == 69
    p = torch.tensor([[0.3, -1.2, 2.0]])
    out = encoding(p)[0]
    assert torch.equal(out[:3], p[0])
    # Frequency 2^k: sin block then cos block, each over (x, y, z).
    k = 3
    np.testing.assert_allclose(out[3 + 6 * k : 6 + 6 * k].numpy(), torch.sin(p[0] * 2**k).numpy(), rtol=1e-6)
    np.testing.assert_allclose(out[6 + 6 * k : 9 + 6 * k].numpy(), torch.cos(p[0] * 2**k).numpy(), rtol=1e-6)


def test_cunerf_network_has_the_papers_shape():
    field = CuNeRFField(FieldConfig(kind="cunerf"))
    widths = [(layer.in_features, layer.out_features) for layer in field.layers]
    assert widths == [(69, 256)] + [(256, 256)] * 3 + [(325, 256)] + [(256, 256)] * 2
    assert (field.head.in_features, field.head.out_features) == (256, 2)
    parameters = sum(p.numel() for p in field.parameters())
    assert 425_000 < parameters < 435_000  # ~431k effective (docs/cunerf.md §1.2)


@pytest.mark.parametrize("kind", ["cunerf", "grid"])
@pytest.mark.parametrize("activation", ["softplus", "relu"])
def test_outputs_are_in_range_even_far_outside_the_volume(kind, activation):
    torch.manual_seed(0)
    field = build_field(FieldConfig(kind=kind, density_activation=activation, resolutions=(4, 8)))
    points = torch.tensor([[0.0, 0.0, 0.0], [1e6, -1e6, 3.0], [-1.0, 1.0, -1.0], [1e-30, 0, 0]])
    intensity, density = field(points)
    assert intensity.shape == density.shape == (4,)
    assert torch.isfinite(intensity).all() and torch.isfinite(density).all()
    assert (intensity >= 0).all() and (intensity <= 1).all() and (density >= 0).all()
    half = field(points.half().float())
    assert torch.isfinite(half[0]).all()


def test_grid_lookup_equals_grid_sample_with_border_padding():
    torch.manual_seed(1)
    field = GridField(FieldConfig(kind="grid", resolutions=(4, 7), features=3)).double()
    points = torch.rand(300, 3, dtype=torch.float64) * 2.6 - 1.3
    for level, r in enumerate((4, 7)):
        rows = field.table[field.offsets[level] : field.offsets[level] + r**3].reshape(r, r, r, 3)
        grid = rows.permute(3, 2, 1, 0)[None]  # (1, F, z, y, x) for grid_sample's (x, y, z)
        expected = F.grid_sample(
            grid, points.reshape(1, -1, 1, 1, 3), mode="bilinear", padding_mode="border", align_corners=False
        )
        ours = field.encode(points)[:, 3 * level : 3 * level + 3]
        np.testing.assert_allclose(ours.detach().numpy(), expected.reshape(3, -1).t().detach().numpy(), atol=1e-12)


def test_grid_vertices_sit_at_voxel_centres():
    index, weight = trilinear_corners(
        torch.tensor([[(2 * 2 + 1) / 8 - 1, (2 * 0 + 1) / 8 - 1, (2 * 7 + 1) / 8 - 1]]), 8
    )
    hit = index[0, weight[0].argmax()].item()
    assert hit == (2 * 8 + 0) * 8 + 7 and weight.max().item() == pytest.approx(1.0)


def test_grid_lookup_gradient():
    points = torch.rand(40, 3, dtype=torch.float64) * 2 - 1
    index, weight = trilinear_corners(points, 4)
    table = torch.randn(64, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: TrilinearLookup.apply(t, index, weight), (table,))


def test_grid_resolutions_end_at_one_vertex_per_voxel():
    assert grid_resolutions(16, 128, 3) == (16, 45, 128)
    assert grid_resolutions(16, 8, 3) == (8,)
    assert grid_resolutions(16, 128, 1) == (128,)
    assert all(r >= 2 for r in grid_resolutions(2, 3, 4))


def test_grid_rejects_a_single_vertex_level():
    with pytest.raises(ValueError):
        GridField(FieldConfig(kind="grid", resolutions=(1, 4)))


def test_nan_points_do_not_poison_the_grid_lookup():
    index, weight = trilinear_corners(torch.tensor([[math.nan, 0.0, 0.0]]), 4)
    assert (index >= 0).all() and (index < 64).all() and torch.isfinite(weight).all()


def _torch_lookup(field: GridField, table: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """The (P, 8)-tensor path, the reference for the fused CPU kernels."""
    indices, weights = [], []
    for level, resolution in enumerate(field.config.resolutions):
        index, weight = trilinear_corners(points, resolution)
        indices.append(index + field.offsets[level])
        weights.append(weight)
    index, weight = torch.stack(indices, 1).reshape(-1, 8), torch.stack(weights, 1).reshape(-1, 8)
    return TrilinearLookup.apply(table, index, weight).reshape(points.shape[0], -1)


def _edge_points(count: int) -> torch.Tensor:
    """Random points inside and beyond the cube, plus vertices, borders, NaN and ±inf."""
    generator = torch.Generator().manual_seed(3)
    points = torch.rand(count, 3, generator=generator) * 2.6 - 1.3
    special = torch.tensor(
        [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [math.nan, 0.2, -0.2], [math.inf, -math.inf, 0.5]]
    )
    return torch.cat((points, special))


@pytest.mark.parametrize("resolutions", [(2,), (4, 9, 16)])
def test_fused_cpu_lookup_matches_the_tensor_path(resolutions):
    torch.manual_seed(2)
    field = GridField(FieldConfig(kind="grid", resolutions=resolutions, features=3))
    with torch.no_grad():
        field.table.normal_()
    points = _edge_points(500)
    fused_table = field.table.detach().clone().requires_grad_(True)
    reference_table = field.table.detach().clone().requires_grad_(True)
    fused = FusedGridLookup.apply(fused_table, points, resolutions, field.offsets)
    reference = _torch_lookup(field, reference_table, points)
    assert torch.isfinite(fused).all()
    torch.testing.assert_close(fused, reference, rtol=1e-6, atol=1e-6)
    upstream = torch.randn_like(fused)
    fused.backward(upstream)
    reference.backward(upstream)
    torch.testing.assert_close(fused_table.grad, reference_table.grad, rtol=1e-5, atol=1e-5)
    assert torch.equal(field.encode(points), fused.detach())  # encode takes the fused path on the CPU


def test_fused_cpu_lookup_gradient_is_the_same_bits_on_any_thread_count():
    field = GridField(FieldConfig(kind="grid", resolutions=(3, 8, 32), features=2))
    points = _edge_points(3000).numpy()
    upstream = np.random.default_rng(0).standard_normal((points.shape[0], 6)).astype(np.float32)
    levels, starts = np.array([3, 8, 32]), field.offsets.numpy()
    cells = np.empty((points.shape[0], 3, 2), dtype=np.int64)
    fractions = np.empty((points.shape[0], 3, 3), dtype=np.float32)
    grid_kernels.encode_forward(points, field.table.detach().numpy(), levels, starts, cells, fractions)
    grads = [
        grid_kernels.encode_backward(cells, fractions, upstream, levels, starts, field.table.shape[0], 2, bands)
        for bands in (1, 2, 3, 7)
    ]
    for grad in grads[1:]:
        assert np.array_equal(grad, grads[0])


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.floats(allow_nan=True, allow_infinity=True, width=32),
        min_size=3,
        max_size=3,
    )
)
def test_fused_cpu_lookup_stays_finite_at_any_point(coordinates):
    field = GridField(FieldConfig(kind="grid", resolutions=(2, 5), features=2))
    point = torch.tensor([coordinates], dtype=torch.float32)
    table = field.table.detach().clone().requires_grad_(True)
    out = FusedGridLookup.apply(table, point, (2, 5), field.offsets)
    out.sum().backward()
    assert torch.isfinite(out).all() and torch.isfinite(table.grad).all()
    # Trilinear weights are convex: the gradient of the sum puts weight 1 on each level.
    assert table.grad.sum().item() == pytest.approx(2 * 2, abs=1e-4)


def test_fused_cpu_mlp_matches_torch_forward_and_backward():
    torch.manual_seed(4)
    mlp = torch.nn.Sequential(torch.nn.Linear(6, 32), torch.nn.ReLU(), torch.nn.Linear(32, 2))
    features = torch.randn(3000, 6) * 3.0
    features[:5] = 0.0  # every hidden unit at its bias: some exactly at ReLU's kink when biased to 0
    with torch.no_grad():
        mlp[0].bias[:4] = 0.0
    reference_input = features.clone().requires_grad_(True)
    fused_input = features.clone().requires_grad_(True)
    reference = mlp(reference_input)
    upstream = torch.randn_like(reference)
    reference.backward(upstream)
    expected = [reference_input.grad] + [p.grad.clone() for p in mlp.parameters()]
    mlp.zero_grad()
    fused = FusedMLP.apply(fused_input, mlp[0].weight, mlp[0].bias, mlp[2].weight, mlp[2].bias)
    fused.backward(upstream)
    torch.testing.assert_close(fused, reference, rtol=1e-5, atol=1e-5)
    for ours, theirs in zip([fused_input.grad] + [p.grad for p in mlp.parameters()], expected):
        torch.testing.assert_close(ours, theirs, rtol=1e-4, atol=1e-4)


def test_fused_cpu_mlp_gradients_are_the_same_bits_on_any_thread_count():
    import numba

    torch.manual_seed(5)
    mlp = torch.nn.Sequential(torch.nn.Linear(6, 32), torch.nn.ReLU(), torch.nn.Linear(32, 2))
    features = torch.randn(5000, 6)
    upstream = torch.randn(5000, 2)
    results = []
    threads = numba.get_num_threads()
    try:
        for count in sorted({1, threads}):
            numba.set_num_threads(count)
            weights = [p.detach().clone().requires_grad_(True) for p in mlp.parameters()]
            FusedMLP.apply(features, *weights).backward(upstream)
            results.append([w.grad for w in weights])
    finally:
        numba.set_num_threads(threads)
    for grads in results[1:]:
        assert all(torch.equal(a, b) for a, b in zip(grads, results[0]))
