"""Neural fields of the scan: world point (x, y, z) in [−1, 1]³ → (intensity, density).

Both fields share one interface, so the cube sampler, the renderer and everything downstream
(export's point cloud and images) never ask which one trained:

* :class:`CuNeRFField`, the paper's network (docs/cunerf.md §1): positional encoding with
  11 frequencies of coordinates scaled to [−π, π], and an MLP of 7 applied layers of width 256
  with the encoded input concatenated before the 5th (the official code builds an 8th layer
  that it never applies; we do not build it).
* :class:`GridField`, for CPUs: a multiresolution dense feature grid, trilinearly interpolated
  (on the CPU by the fused kernels of ``grid_kernels.py``), and a small MLP. The finest level has one vertex per voxel, so the field
  can hold every voxel's value, and the coarser levels fill in between.

Intensity goes through a sigmoid, so it lies in [0, 1]; density through softplus (default) or
ReLU (the official code; it can die and render black, official issue #18).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from cubecloud_cli.cunerf import grid_kernels
from cubecloud_cli.cunerf.config import DENSITY_ACTIVATIONS, FieldConfig
from cubecloud_cli.cunerf.precision import hidden_layers_autocast, matmul_scope

POINT_LIMIT = 16.0


class NeuralField(nn.Module):
    """Base class: ``forward(points) -> (intensity, density)``, each shaped like points[..., 0]."""

    config: FieldConfig

    def raw(self, points: torch.Tensor) -> torch.Tensor:  # (P, 3) -> (P, 2)
        raise NotImplementedError

    def forward(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        shape = points.shape[:-1]
        # Far outside the cube ([−1, 1]³) the field has nothing to say, and sin(2¹⁰·huge) is
        # noise or NaN: points are held within ±POINT_LIMIT world units.
        points = torch.nan_to_num(points.reshape(-1, 3).float(), nan=0.0).clamp(-POINT_LIMIT, POINT_LIMIT)
        raw = self.raw(points)
        intensity = torch.sigmoid(raw[:, 0])
        if self.config.density_activation == "relu":
            density = F.relu(raw[:, 1])
        else:
            density = F.softplus(raw[:, 1])
        return intensity.reshape(shape), density.reshape(shape)


class PositionalEncoding(nn.Module):
    """γ(p) = [p, sin(2⁰p), cos(2⁰p), …, sin(2^(L−1)p), cos(2^(L−1)p)] per coordinate."""

    def __init__(self, frequencies: int):
        super().__init__()
        self.frequencies = frequencies
        for name, value in self.derived_buffers().items():
            self.register_buffer(name, value, persistent=False)
        self.out_features = 3 * (1 + 2 * frequencies)

    def derived_buffers(self) -> dict[str, torch.Tensor]:
        """The buffers made from the configuration, not saved with the weights."""
        return {"scales": 2.0 ** torch.arange(self.frequencies, dtype=torch.float32)}

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        scaled = points[..., None, :] * self.scales[:, None]  # (P, L, 3)
        waves = torch.stack((torch.sin(scaled), torch.cos(scaled)), dim=-2)  # (P, L, 2, 3)
        return torch.cat((points, waves.flatten(-3)), dim=-1)


class CuNeRFField(NeuralField):
    def __init__(self, config: FieldConfig):
        super().__init__()
        self.config = config
        # How the hidden layers compute (cunerf/precision.py): a way of running, not a weight.
        self.precision = "float32"
        self.encoding = PositionalEncoding(config.frequencies)
        encoded = self.encoding.out_features
        layers = []
        for index in range(config.depth):
            inputs = encoded if index == 0 else config.width
            if index == config.skip_at:
                inputs += encoded
            layers.append(nn.Linear(inputs, config.width))
        self.layers = nn.ModuleList(layers)
        self.head = nn.Linear(config.width, 2)

    def raw(self, points: torch.Tensor) -> torch.Tensor:
        # The official code scales each axis to [−π, π] (docs/cunerf.md §3.3).
        encoded = self.encoding(points * math.pi)
        hidden = encoded
        with matmul_scope(self.precision, points.device), hidden_layers_autocast(self.precision, points.device):
            for index, layer in enumerate(self.layers):
                if index == self.config.skip_at:
                    hidden = torch.cat((encoded, hidden), dim=-1)
                hidden = F.relu(layer(hidden))
        return self.head(hidden.float())


class GridField(NeuralField):
    def __init__(self, config: FieldConfig):
        super().__init__()
        if min(config.resolutions) < 2:
            raise ValueError("every grid level needs at least 2 vertices per axis")
        self.config = config
        rows = sum(r**3 for r in config.resolutions)
        # One table for all levels (rows of level l start at offsets[l]), so a single lookup
        # serves every level; tiny random values break the symmetry between features.
        self.table = nn.Parameter(torch.randn(rows, config.features).mul_(1e-4))  # in place: 1 GB at 512³
        for name, value in self.derived_buffers().items():
            self.register_buffer(name, value, persistent=False)
        inputs = config.features * len(config.resolutions)
        self.mlp = nn.Sequential(nn.Linear(inputs, config.hidden), nn.ReLU(), nn.Linear(config.hidden, 2))

    def derived_buffers(self) -> dict[str, torch.Tensor]:
        """The buffers made from the configuration, not saved with the weights."""
        return {"offsets": torch.tensor([0] + [r**3 for r in self.config.resolutions[:-1]]).cumsum(0)}

    def _on_cpu_kernels(self, points: torch.Tensor) -> bool:
        """Whether the numba kernels apply: float32 on the CPU (the torch path serves the rest)."""
        return points.device.type == "cpu" and self.table.dtype == torch.float32

    def encode(self, points: torch.Tensor) -> torch.Tensor:
        """(P, 3) -> (P, levels · features): each level's features, trilinearly interpolated."""
        if self._on_cpu_kernels(points):
            return FusedGridLookup.apply(self.table, points, self.config.resolutions, self.offsets)
        indices, weights = [], []
        for level, resolution in enumerate(self.config.resolutions):
            index, weight = trilinear_corners(points, resolution)
            indices.append(index + self.offsets[level])
            weights.append(weight)
        index = torch.stack(indices, dim=1).reshape(-1, 8)
        weight = torch.stack(weights, dim=1).reshape(-1, 8)
        features = TrilinearLookup.apply(self.table, index, weight)
        return features.reshape(points.shape[0], -1)

    def raw(self, points: torch.Tensor) -> torch.Tensor:
        if self._on_cpu_kernels(points):
            first, last = self.mlp[0], self.mlp[2]
            return FusedMLP.apply(self.encode(points), first.weight, first.bias, last.weight, last.bias)
        return self.mlp(self.encode(points))


_CORNERS = torch.tensor([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)])


def trilinear_corners(points: torch.Tensor, resolution: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Row indices (P, 8) into an r³ table (x-major) and trilinear weights (P, 8) summing to 1.

    Vertex v of a level sits at world (2v + 1)/r − 1, the centre of voxel v of an r³ volume over
    [−1, 1]³ (docs/design.md §2). Points outside the outermost vertices take the border value.
    """
    r = resolution
    continuous = ((points.detach() + 1.0) * (0.5 * r) - 0.5).clamp(0.0, r - 1.0)
    continuous = torch.nan_to_num(continuous, nan=0.0)
    low = continuous.floor().clamp(max=r - 2)
    fraction = continuous - low
    low = low.long()
    base = (low[:, 0] * r + low[:, 1]) * r + low[:, 2]
    steps = (_CORNERS.to(points.device) * torch.tensor([r * r, r, 1], device=points.device)).sum(-1)
    index = base[:, None] + steps[None, :]
    fx, fy, fz = fraction.unbind(-1)
    wx = torch.stack((1 - fx, fx), -1)
    wy = torch.stack((1 - fy, fy), -1)
    wz = torch.stack((1 - fz, fz), -1)
    weight = (wx[:, :, None, None] * wy[:, None, :, None] * wz[:, None, None, :]).reshape(-1, 8)
    return index, weight


class TrilinearLookup(torch.autograd.Function):
    """Σ_corners weight · table[row], the lookup off the CPU (and in float64). ``embedding_bag``
    does the forward in one pass; the backward scatters into a dense gradient with
    ``index_add_``, faster than either ``grid_sample``'s or ``embedding_bag``'s own backward.
    Points get no gradient."""

    @staticmethod
    def forward(ctx, table: torch.Tensor, index: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(index, weight)
        ctx.rows = table.shape[0]
        return F.embedding_bag(index, table, per_sample_weights=weight, mode="sum")

    @staticmethod
    def backward(ctx, grad_output: torch.Tensor):
        index, weight = ctx.saved_tensors
        contributions = (weight[:, :, None] * grad_output[:, None, :]).reshape(-1, grad_output.shape[1])
        grad_table = torch.zeros(ctx.rows, grad_output.shape[1], dtype=grad_output.dtype, device=grad_output.device)
        grad_table.index_add_(0, index.reshape(-1), contributions)
        return grad_table, None, None


class FusedGridLookup(torch.autograd.Function):
    """:meth:`GridField.encode` on the CPU in two numba kernels (``grid_kernels``): the same
    corners and weights as :func:`trilinear_corners`, without its (P, 8) tensors per level. Points
    get no gradient."""

    @staticmethod
    def forward(ctx, table: torch.Tensor, points: torch.Tensor, resolutions: tuple[int, ...], offsets: torch.Tensor):
        points_np = points.detach().contiguous().float().numpy()
        levels = np.asarray(resolutions, dtype=np.int64)
        starts = offsets.numpy().astype(np.int64)
        # Each point's corners and fractions, kept for the backward when the table wants a gradient.
        kept = points_np.shape[0] if ctx.needs_input_grad[0] else 0
        cells = np.empty((kept, levels.size, 2), dtype=np.int64)
        fractions = np.empty((kept, levels.size, 3), dtype=np.float32)
        ctx.saved = (cells, fractions, levels, starts, table.shape)
        features = grid_kernels.encode_forward(points_np, table.detach().numpy(), levels, starts, cells, fractions)
        return torch.from_numpy(features)

    @staticmethod
    def backward(ctx, grad_output: torch.Tensor):
        cells, fractions, levels, starts, (rows, features) = ctx.saved
        grad = grid_kernels.encode_backward(
            cells,
            fractions,
            grad_output.detach().contiguous().float().numpy(),
            levels,
            starts,
            rows,
            features,
            numba.get_num_threads(),
        )
        return torch.from_numpy(grad), None, None, None


class FusedMLP(torch.autograd.Function):
    """The grid field's Linear → ReLU → Linear on the CPU in two numba kernels
    (``grid_kernels.mlp_forward``/``mlp_backward``): at 32 768 points of 6 features per iteration
    torch's matrix products for these thin shapes cost more than the arithmetic. The weight
    gradients are summed per block of points and the blocks in order, so they are the same bits
    on any thread count."""

    @staticmethod
    def forward(ctx, features, w1, b1, w2, b2):
        arrays = [t.detach().contiguous().float().numpy() for t in (features, w1.t(), b1, w2, b2)]
        ctx.arrays = arrays
        return torch.from_numpy(grid_kernels.mlp_forward(*arrays))

    @staticmethod
    def backward(ctx, grad_output):
        features, w1t, b1, w2, _ = ctx.arrays
        grads = grid_kernels.mlp_backward(features, grad_output.detach().contiguous().float().numpy(), w1t, b1, w2)
        grad_features, *blocks = grads
        # The blocks' partial sums added one after another: the same bits whatever the threads.
        grad_w1t, grad_b1, grad_w2, grad_b2 = (_sum_in_order(block) for block in blocks)
        return torch.from_numpy(grad_features), grad_w1t.t().contiguous(), grad_b1, grad_w2, grad_b2


def _sum_in_order(blocks: np.ndarray) -> torch.Tensor:
    total = blocks[0].copy()
    for block in blocks[1:]:
        total += block
    return torch.from_numpy(total)


def build_field(config: FieldConfig) -> NeuralField:
    if config.density_activation not in DENSITY_ACTIVATIONS:
        raise ValueError(f"unknown density activation {config.density_activation!r}")
    if config.kind == "cunerf":
        return CuNeRFField(config)
    if config.kind == "grid":
        return GridField(config)
    raise ValueError(f"unknown field kind {config.kind!r}")
