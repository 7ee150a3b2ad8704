"""Density control: what changes the set of Gaussians during training, passed to the trainer as a
strategy, as gsplat's ``Strategy`` is (``strategy/base.py``: ``step_pre_backward``,
``step_post_backward``), so that a run can swap the reference's rules for another's or for none.

:class:`DensityStrategy` is what the trainer calls; :class:`ReferenceStrategy` is adaptive density
control of the reference 3DGS (docs/references.md §1.3–1.4) and :class:`NoDensification` keeps the
Gaussians the run started with (``--no-refine``). The reference's rules are pure functions: every
``densify_every`` iterations :func:`plan_densification` says what to change, and :func:`apply_plan`
applies the plan to every per-Gaussian tensor (parameters and optimizer moments alike):

* clone Gaussians whose mean view-space gradient (in NDC units) reaches the threshold and whose
  largest scale is at most ``percent_dense`` × the scene extent (copies, unchanged);
* split the large ones among them into two, drawn from the Gaussian itself, scales ÷ 1.6;
* prune those with opacity below ``min_opacity`` (and, after the first opacity reset, those
  larger than ``max_world_size`` × extent, judged after splitting as the reference does; the
  reference's screen-size rule never fires, see §1.3, and is not reproduced);
* hold the count to ``max_gaussians``: growth goes to the largest gradients first, and a model
  above the budget loses its least opaque Gaussians.

:class:`DensifySchedule` says when, on the reference schedule scaled to the run.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch

from cubecloud_cli.numerics.adam import Optimizer
from cubecloud_cli.raster.backends import Rasterized
from cubecloud_cli.raster.projection import quaternion_to_rotation
from cubecloud_cli.splat.optimizer import replace_parameters
from cubecloud_cli.splat.scalar_gaussians import GaussianModel
from cubecloud_cli.splat.settings import SplatSettings

SPLIT_SCALE_DIVISOR = 1.6  # 0.8 · 2 children, as in the reference


@dataclass(frozen=True)
class DensifySettings:
    grad_threshold: float = SplatSettings.grad_threshold
    percent_dense: float = SplatSettings.percent_dense
    min_opacity: float = 0.005
    max_world_size: float = 0.1
    max_gaussians: int | None = None


@dataclass(frozen=True)
class DensifySchedule:
    """When the reference gathers gradient statistics, densifies, prunes large Gaussians and resets
    opacity: its schedule scaled to the run (``SplatSettings.schedule``)."""

    thresholds: DensifySettings
    schedule: dict[str, int]
    refine: bool = True

    @classmethod
    def from_settings(cls, settings: SplatSettings) -> "DensifySchedule":
        thresholds = DensifySettings(
            settings.grad_threshold, settings.percent_dense, max_gaussians=settings.max_gaussians
        )
        return cls(thresholds, settings.schedule(), settings.refine)

    def refining(self, iteration: int) -> bool:
        """Statistics, densification and resets happen only before densify_until, as in the reference."""
        return self.refine and iteration < self.schedule["densify_until"]

    def densify_due(self, iteration: int) -> bool:
        return (
            self.refining(iteration)
            and iteration > self.schedule["densify_from"]
            and iteration % self.schedule["densify_every"] == 0
        )

    def prunes_large(self, iteration: int) -> bool:
        """The world-size rule applies once the first opacity reset has passed."""
        return iteration > self.schedule["reset_every"]

    def reset_due(self, iteration: int) -> bool:
        return self.refining(iteration) and iteration % self.schedule["reset_every"] == 0


class GradientStats:
    """Running mean of each Gaussian's view-space mean gradient, in NDC units."""

    def __init__(self, count: int, device: torch.device | str = "cpu"):
        self.total = torch.zeros(count, device=device)
        self.views = torch.zeros(count, device=device)

    def add(self, means2d_grad: torch.Tensor, radii: torch.Tensor, width: int, height: int) -> None:
        # Pixel-space gradients × (W/2, H/2) are the NDC gradients the reference thresholds.
        grad = means2d_grad.detach()
        ndc_norm = torch.sqrt((grad[:, 0] * (width / 2.0)) ** 2 + (grad[:, 1] * (height / 2.0)) ** 2)
        visible = (radii > 0).to(self.total.dtype)  # masks by product: boolean indexing costs more
        self.total += ndc_norm * visible
        self.views += visible

    def mean(self) -> torch.Tensor:
        return torch.where(self.views > 0, self.total / self.views.clamp_min(1.0), torch.zeros_like(self.total))


@dataclass
class DensifyPlan:
    keep: torch.Tensor  # (N,) bool: originals that stay
    clone: torch.Tensor  # (C,) indices of Gaussians copied unchanged
    split: torch.Tensor  # (S,) indices of Gaussians replaced by two children each
    child_means: torch.Tensor  # (K, 3), the kept children
    child_log_scales: torch.Tensor  # (K, 3)
    child_keep: torch.Tensor  # (2S,) bool: which of the 2 children per split survive the size rule

    @property
    def new_count(self) -> int:
        return int(self.keep.sum()) + self.clone.numel() + int(self.child_keep.sum())


def plan_densification(
    means: torch.Tensor,
    log_scales: torch.Tensor,
    quaternions: torch.Tensor,
    opacities: torch.Tensor,
    mean_gradients: torch.Tensor,
    settings: DensifySettings,
    extent: float,
    prune_large: bool,
    generator: torch.Generator | None = None,
) -> DensifyPlan:
    with torch.no_grad():
        count = means.shape[0]
        scales = torch.exp(log_scales)
        largest = scales.max(dim=1).values
        opacity = opacities
        transparent = opacity < settings.min_opacity
        too_large = (largest > settings.max_world_size * extent) if prune_large else torch.zeros_like(transparent)
        grow = (mean_gradients >= settings.grad_threshold) & ~transparent
        big = largest > settings.percent_dense * extent
        # As the reference: a Gaussian chosen for splitting is split before the world-size rule
        # looks at it, and then only its children are judged by their own size.
        prune = transparent | (too_large & ~(grow & big))
        if settings.max_gaussians is not None:
            surviving = count - int(prune.sum())
            if surviving > settings.max_gaussians:  # over budget already: drop the least opaque
                excess = surviving - settings.max_gaussians
                ranked = torch.where(prune, torch.full_like(opacity, float("inf")), opacity)
                prune[torch.topk(ranked, excess, largest=False).indices] = True
                grow &= ~prune
                surviving = settings.max_gaussians
            room = max(0, settings.max_gaussians - surviving)  # each clone or split adds one
            candidates = grow.nonzero().squeeze(1)
            if candidates.numel() > room:
                best = torch.topk(mean_gradients[candidates], room).indices
                grow = torch.zeros_like(grow)
                grow[candidates[best]] = True
        prune |= too_large & ~(grow & big)  # large ones that lost their split to the budget
        clone = (grow & ~big).nonzero().squeeze(1)
        split = (grow & big).nonzero().squeeze(1)

        # Children: two samples of N(μ, R diag(s²) Rᵀ), scales ÷ 1.6.
        parent_scales = scales[split].repeat_interleave(2, dim=0)
        noise = torch.randn(
            parent_scales.shape, generator=generator, device=means.device if generator is None else "cpu"
        )
        noise = noise.to(means.device) * parent_scales
        rotations = quaternion_to_rotation(quaternions[split]).repeat_interleave(2, dim=0)
        child_means = means[split].repeat_interleave(2, dim=0) + (rotations @ noise[:, :, None])[:, :, 0]
        child_log_scales = torch.log(parent_scales / SPLIT_SCALE_DIVISOR)
        child_keep = torch.ones(child_means.shape[0], dtype=torch.bool, device=means.device)
        if prune_large:
            child_keep = torch.exp(child_log_scales).max(dim=1).values <= settings.max_world_size * extent
        keep = ~prune
        keep[split] = False
        return DensifyPlan(keep, clone, split, child_means[child_keep], child_log_scales[child_keep], child_keep)


def apply_plan(
    plan: DensifyPlan, values: torch.Tensor, children: torch.Tensor | None = None, new_rows_zero: bool = False
) -> torch.Tensor:
    """The per-Gaussian tensor after the plan: kept originals, then clones, then split children
    (``children`` when given, else copies of their parents). ``new_rows_zero`` gives new rows
    zeros instead (optimizer moments start afresh for new Gaussians)."""
    kept = values[plan.keep]
    if new_rows_zero:
        added = values.new_zeros((plan.clone.numel() + int(plan.child_keep.sum()), *values.shape[1:]))
        return torch.cat((kept, added))
    split_rows = children if children is not None else values[plan.split].repeat_interleave(2, dim=0)[plan.child_keep]
    return torch.cat((kept, values[plan.clone], split_rows))


@dataclass
class Trainable:
    """What a strategy may change: the Gaussians, the optimizer that holds them (parameters and
    moments are replaced together) and the run's generator (the split children's draws)."""

    gaussians: GaussianModel
    optimizer: Optimizer
    generator: torch.Generator


class DensityStrategy(Protocol):
    """What the trainer asks at each iteration about the set of Gaussians. It keeps its own state
    (``state_dict`` goes into the run's checkpoints)."""

    def initialize(self, count: int, device: torch.device) -> None:
        """Start for ``count`` Gaussians on ``device``."""
        ...

    def gathers_statistics(self, iteration: int) -> bool:
        """Whether ``iteration`` (counted from 1, after its backward) may still change the set:
        the trainer recomputes the 3D filter on its own schedule only once it does not."""
        ...

    def step_post_backward(self, iteration: int, rendered: Rasterized, width: int, height: int) -> None:
        """After the iteration's backward, before the optimizer's step: gather statistics."""
        ...

    def changes_at(self, iteration: int) -> bool:
        """Whether ``step_post_optimizer`` densifies, prunes or resets at ``iteration`` (the
        trainer first reads its pending values back, numerics/readback.py)."""
        ...

    def step_post_optimizer(self, iteration: int, trainable: Trainable) -> bool:
        """After the optimizer's step: densify, prune or reset; True when Gaussians were added or
        removed."""
        ...

    def state_dict(self) -> dict:
        """What a checkpoint keeps of the strategy."""
        ...

    def load_state_dict(self, state: dict, count: int, device: torch.device) -> None:
        """Continue from a checkpoint's state for its ``count`` Gaussians."""
        ...


class ReferenceStrategy:
    """The reference 3DGS's adaptive density control: view-space gradient statistics, clone, split
    and prune on :class:`DensifySchedule`, and periodic opacity resets, within the scene's
    ``extent``."""

    def __init__(self, schedule: DensifySchedule, extent: float):
        self.schedule = schedule
        self.extent = extent
        self.stats = GradientStats(0)

    def initialize(self, count: int, device: torch.device) -> None:
        self.stats = GradientStats(count, device)

    def gathers_statistics(self, iteration: int) -> bool:
        return self.schedule.refining(iteration)

    def step_post_backward(self, iteration: int, rendered: Rasterized, width: int, height: int) -> None:
        screen_gradient = rendered.screen_gradient() if self.gathers_statistics(iteration) else None
        if screen_gradient is not None:
            self.stats.add(screen_gradient, rendered.radii, width, height)

    def changes_at(self, iteration: int) -> bool:
        return self.schedule.densify_due(iteration) or self.schedule.reset_due(iteration)

    def step_post_optimizer(self, iteration: int, trainable: Trainable) -> bool:
        densified = self.schedule.densify_due(iteration)
        if densified:
            self._densify(trainable, prune_large=self.schedule.prunes_large(iteration))
        if self.schedule.reset_due(iteration):
            self._reset_opacity(trainable)
        return densified

    def _densify(self, trainable: Trainable, prune_large: bool) -> None:
        g = trainable.gaussians
        device = g.means.device
        plan = plan_densification(
            g.means,
            g.log_scales,
            g.quaternions,
            g.pruning_opacities(),
            self.stats.mean(),
            self.schedule.thresholds,
            self.extent,
            prune_large,
            trainable.generator,
        )
        children = {"means": plan.child_means.to(device), "log_scales": plan.child_log_scales.to(device)}
        replaced = replace_parameters(
            trainable.optimizer,
            g.TRAINED,
            lambda name, old: apply_plan(plan, old, children.get(name)),
            lambda name, moment: apply_plan(plan, moment, new_rows_zero=True),
        )
        for name, new in replaced.items():
            setattr(g, name, new)
        self.stats = GradientStats(len(g), device)

    @staticmethod
    def _reset_opacity(trainable: Trainable) -> None:
        g = trainable.gaussians
        name = g.OPACITY_PARAMETER
        replaced = replace_parameters(
            trainable.optimizer,
            [name],
            lambda name, old: g.reset_transparency(old),
            lambda name, moment: torch.zeros_like(moment),
        )
        setattr(g, name, replaced[name])

    def state_dict(self) -> dict:
        return {"stats": (self.stats.total.cpu(), self.stats.views.cpu())}

    def load_state_dict(self, state: dict, count: int, device: torch.device) -> None:
        self.stats = GradientStats(count, device)
        self.stats.total, self.stats.views = (t.to(device) for t in state["stats"])


class NoDensification:
    """The Gaussians the run started with, none added, removed or reset (``--no-refine``)."""

    def initialize(self, count: int, device: torch.device) -> None:
        pass

    def gathers_statistics(self, iteration: int) -> bool:
        return False

    def step_post_backward(self, iteration: int, rendered: Rasterized, width: int, height: int) -> None:
        pass

    def changes_at(self, iteration: int) -> bool:
        return False

    def step_post_optimizer(self, iteration: int, trainable: Trainable) -> bool:
        return False

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict, count: int, device: torch.device) -> None:
        pass


def strategy_for(settings: SplatSettings, extent: float) -> DensityStrategy:
    """The strategy ``settings`` ask for, for a scene of ``extent``: the reference's, or none."""
    if not settings.refine:
        return NoDensification()
    return ReferenceStrategy(DensifySchedule.from_settings(settings), extent)
