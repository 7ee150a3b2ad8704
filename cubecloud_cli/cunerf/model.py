"""A cube renderer around one or two neural fields: CuNeRF's coarse-to-fine pipeline
(docs/cunerf.md §2): sample the cube → coarse field → render → resample radii from the
coarse weights → fine field on all points → render.

The official behaviour, quirks included, is one switch (``RenderConfig.official``): the
low-corner-biased training sampler and the asymmetric test lattice, polar angles drawn
uniformly (crowding the poles) and random even at test, ties broken by the sort, unbounded
weights clipped only in test renders.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import nn

from cubecloud_cli.cunerf.config import FieldConfig, RenderConfig, render_chunk
from cubecloud_cli.cunerf.fields import NeuralField, build_field
from cubecloud_cli.cunerf.rendering import render_cubes, shell_edges
from cubecloud_cli.cunerf.sampling import cube_offsets, sample_radii_from_weights, sphere_directions


@dataclass
class CubeOutput:
    value: torch.Tensor  # (B,) the prediction: fine when there is a fine pass, else coarse
    coarse: torch.Tensor  # (B,) the coarse pass (the adaptive loss uses it)
    has_fine: bool


class CubeModel(nn.Module):
    def __init__(self, field_config: FieldConfig, render_config: RenderConfig):
        super().__init__()
        self.field_config = field_config
        self.render_config = render_config
        self.coarse = build_field(field_config)
        wants_fine = render_config.importance > 0 and render_config.separate_fine
        self.fine: NeuralField | None = build_field(field_config) if wants_fine else None

    @classmethod
    def holding(cls, field_config: FieldConfig, render_config: RenderConfig, state: dict) -> "CubeModel":
        """A model whose weights are ``state``'s tensors themselves (memory-mapped ones stay on
        disk until read), never allocating and initialising weights of its own first: a
        512³ grid's table is 1 GB."""
        with torch.device("meta"):
            model = cls(field_config, render_config)
        model.load_state_dict(state, assign=True)
        device = next(iter(state.values())).device if state else torch.device("cpu")
        for module in model.modules():
            derived = getattr(module, "derived_buffers", None)
            if derived is not None:
                for name, value in derived().items():
                    module.register_buffer(name, value.to(device), persistent=False)
        return model

    def set_precision(self, precision: str) -> None:
        """How the paper's MLP computes from now on (cunerf/precision.py); the grid field
        always computes in float32."""
        for field in (self.coarse, self.fine):
            if field is not None and hasattr(field, "precision"):
                field.precision = precision

    @property
    def final_field(self) -> NeuralField:
        """The field whose values the prediction is made of (fine when there is one)."""
        return self.fine if self.fine is not None else self.coarse

    def render(self, centres: torch.Tensor, train: bool, generator: torch.Generator | None = None) -> CubeOutput:
        """Render cubes centred at ``centres`` (B, 3) world points."""
        config = self.render_config
        official = config.official
        if train:
            layout = "official-train" if official else config.train_layout
        else:
            layout = "official-lattice" if official else "lattice"
        offsets = cube_offsets(
            centres.shape[0], config.samples_per_axis, layout, config.cube_half_size, generator, centres.device
        )
        intensity, density = self.coarse(centres[:, None, :] + offsets)
        coarse = render_cubes(
            offsets, intensity, density, config.half_diagonal, tie_aware=not official, bounded=not official
        )
        coarse_value = coarse.value
        if config.importance <= 0 or offsets.shape[1] < 3:
            value = self._finish(coarse_value, train)
            return CubeOutput(value, value, False)

        edges = shell_edges(coarse.radii)
        radii = sample_radii_from_weights(
            edges, coarse.weights[:, 1:-1], config.importance, deterministic=not train, generator=generator
        )
        mode = "official" if official else ("uniform" if train else "fibonacci")
        directions = sphere_directions(radii.shape, mode, generator, centres.device)  # type: ignore[arg-type]
        extra = (radii * config.half_diagonal)[..., None] * directions
        all_offsets = torch.cat((offsets.expand(centres.shape[0], -1, -1), extra.detach()), dim=1)
        intensity, density = self.final_field(centres[:, None, :] + all_offsets)
        fine = render_cubes(
            all_offsets, intensity, density, config.half_diagonal, tie_aware=not official, bounded=not official
        )
        return CubeOutput(self._finish(fine.value, train), self._finish(coarse_value, train), True)

    def _finish(self, value: torch.Tensor, train: bool) -> torch.Tensor:
        # Official renders exceed 1 and are clipped only at test (docs/cunerf.md §2.3).
        if self.render_config.official and not train:
            return value.clamp(0.0, 1.0)
        return value


@torch.no_grad()
def render_many(
    model: CubeModel,
    centres: torch.Tensor,
    chunk: int | None = None,
    keep: Callable[[torch.Tensor], torch.Tensor] | None = None,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Test renders of any number of cubes, ``chunk`` at a time. Cubes for which ``keep``
    is False (air, by the occupancy grid) are not rendered and read 0."""
    chunk = chunk or render_chunk(model.render_config, centres.device.type)
    values = torch.zeros(centres.shape[0], device=centres.device)
    was_training = model.training
    model.eval()
    try:
        for start in range(0, centres.shape[0], chunk):
            block = centres[start : start + chunk]
            if keep is None:
                values[start : start + chunk] = model.render(block, train=False, generator=generator).value
                continue
            wanted = keep(block)
            if bool(wanted.any()):
                rendered = model.render(block[wanted], train=False, generator=generator).value
                values[start : start + chunk][wanted] = rendered
    finally:
        model.train(was_training)
    return values
