"""The training loop: batches of voxels → cube renders → adaptive MSE → Adam (docs/cunerf.md §3).

Everything random draws from one ``torch.Generator`` whose state goes into the checkpoint with
the model, the optimizer and the iteration, so a resumed run continues exactly as an
uninterrupted one would. Validation renders use their own generator and leave training's alone.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from cubecloud_cli.core.writes import write_atomically
from cubecloud_cli.cunerf.model import CubeModel, CubeOutput, render_many
from cubecloud_cli.cunerf.precision import matmul_scope
from cubecloud_cli.cunerf.settings import CunerfSettings
from cubecloud_cli.cunerf.supervision import TrainingVoxels, voxel_centres
from cubecloud_cli.numerics.adam import Optimizer, adam
from cubecloud_cli.numerics.metrics import psnr, ssim_and_masked
from cubecloud_cli.numerics.readback import GroupedReads

CHECKPOINT_FORMAT = 1
VALIDATION_SEED = 1234


def learning_rate(step: int, settings: CunerfSettings) -> float:
    """Sine warm-up from 1% over ``warmup`` steps, then log-linear decay lr → lr_final over the
    run (the official mip-NeRF-style schedule, docs/cunerf.md §3.2)."""
    warm = 1.0
    if settings.warmup > 0:
        warm = 0.01 + 0.99 * math.sin(0.5 * math.pi * min(max(step / settings.warmup, 0.0), 1.0))
    tau = min(max(step / max(settings.iterations, 1), 0.0), 1.0)
    return warm * math.exp((1.0 - tau) * math.log(settings.lr) + tau * math.log(settings.lr_final))


def adaptive_mse(output: CubeOutput, target: torch.Tensor) -> torch.Tensor:
    """CuNeRF's 𝓛_A: MSE(fine) + mean(√|fine − C| · (coarse − C)²), the weight gradient-stopped.
    Plain MSE when there is no fine pass."""
    fine_error = output.value - target
    loss = (fine_error * fine_error).mean()
    if output.has_fine:
        weight = torch.sqrt(fine_error.detach().abs())
        loss = loss + (weight * (output.coarse - target) ** 2).mean()
    return loss


def make_optimizer(model: CubeModel, settings: CunerfSettings) -> Optimizer:
    if settings.model == "cunerf":
        options: dict[str, Any] = {"betas": (0.9, 0.999), "eps": 1e-6}  # the official values
    else:
        options = {"betas": (0.9, 0.99), "eps": 1e-15}  # instant-NGP's, for feature grids
    return adam([{"params": list(model.parameters())}], lr=settings.lr, **options)


@dataclass
class Trainer:
    model: CubeModel
    voxels: TrainingVoxels
    settings: CunerfSettings
    generator: torch.Generator
    iteration: int = 0
    elapsed_s: float = 0.0
    history: list[dict[str, float]] = field(default_factory=list)
    smoothed_loss: float | None = None  # running mean shown in the bar and log.csv, as of the last read
    context: dict[str, Any] = field(default_factory=dict)  # saved as is, e.g. the input's sha256
    loss_read_every: int | None = None  # steps between reads of the losses (numerics/readback.py); None: the device's

    def __post_init__(self) -> None:
        self.optimizer = make_optimizer(self.model, self.settings)
        device = self.voxels.volume.device
        self._losses = GroupedReads(self.loss_read_every) if self.loss_read_every else GroupedReads.for_device(device)

    def step(self) -> torch.Tensor:
        """One iteration; returns its loss as a 0-d tensor (reading it waits for the step)."""
        started = time.perf_counter()
        for group in self.optimizer.param_groups:
            group["lr"] = learning_rate(self.iteration, self.settings)
        device = self.voxels.volume.device
        with matmul_scope(self.settings.precision, device):
            centres, targets = self.voxels.batch(self.settings.batch_size, self.generator)
            output = self.model.render(centres, train=True, generator=self.generator)
            loss = adaptive_mse(output, targets)
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
        self.optimizer.step()
        self.iteration += 1
        self.elapsed_s += time.perf_counter() - started
        if self._losses.push(self.iteration, loss.detach().reshape(1)):
            self.flush_losses()
        return loss.detach()

    def flush_losses(self) -> None:
        """Read the losses of the steps not yet read: raise on the first that is not finite,
        and update the running mean. The wait for the device counts as training time."""
        started = time.perf_counter()
        read = self._losses.read()
        self.elapsed_s += time.perf_counter() - started
        for iteration, (value,) in read:
            if not math.isfinite(value):
                raise FloatingPointError(f"the loss became {value} at iteration {iteration}")
            self.smoothed_loss = value if self.smoothed_loss is None else 0.9 * self.smoothed_loss + 0.1 * value

    def held_out_scores(self, chunk: int | None = None) -> dict[str, float]:
        """PSNR/SSIM on the held-out slices (whole image and body only)."""
        slices = self.voxels.held_out
        if not slices:
            return {}
        size = self.voxels.size
        device = self.voxels.volume.device
        grid = torch.arange(size, device=device)
        i, j = torch.meshgrid(grid, grid, indexing="ij")
        predictions, references = [], []
        generator = torch.Generator(device=device).manual_seed(VALIDATION_SEED)
        for k in slices:
            indices = torch.stack((i, j, torch.full_like(i, k)), dim=-1).reshape(-1, 3)
            rendered = render_many(self.model, voxel_centres(indices, size), chunk, generator=generator)
            predictions.append(rendered.reshape(size, size).cpu().numpy())
            references.append(self.voxels.volume[:, :, k].cpu().numpy())
        prediction, reference = np.stack(predictions), np.stack(references)
        body = reference > 0
        result = {"val_psnr": psnr(reference, prediction), "val_psnr_body": psnr(reference, prediction, body)}
        if size >= 11:
            result["val_ssim"], result["val_ssim_body"] = ssim_and_masked(reference, prediction, body)
        return result

    # -- checkpoints -------------------------------------------------------------------------

    def state(self) -> dict[str, Any]:
        self.flush_losses()  # a checkpoint never holds weights past a loss that was not finite
        return {
            "format": CHECKPOINT_FORMAT,
            "settings": self.settings.as_dict(),
            "volume_size": self.voxels.size,
            "field": self.model.field_config.as_dict(),
            "render": self.model.render_config.as_dict(),
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "generator": self.generator.get_state(),
            "iteration": self.iteration,
            "elapsed_s": self.elapsed_s,
            "history": self.history,
            "smoothed_loss": self.smoothed_loss,
            "context": self.context,
        }

    def save(self, path: Path) -> None:
        """Write atomically: a checkpoint is either the old one or the new one, never half."""
        state = self.state()
        write_atomically(path, lambda temporary: torch.save(state, temporary))

    def restore(self, state: dict[str, Any]) -> None:
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.generator.set_state(state["generator"])
        self.iteration = int(state["iteration"])
        self.elapsed_s = float(state["elapsed_s"])
        self.history = list(state["history"])
        self.smoothed_loss = state.get("smoothed_loss")
