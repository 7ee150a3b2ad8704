"""Density control on constructed cases (clone, split, prune, budget, reset), and the strategies the
trainer is given: the reference's on its schedule, and none."""

import math

import pytest
import torch

from cubecloud_cli.splat.densify import (
    DensifySettings,
    GradientStats,
    apply_plan,
    plan_densification,
)
from cubecloud_cli.splat.gaussians import reset_opacity

EXTENT = 2.0  # percent_dense 0.01 → clone below a largest scale of 0.02, split above


def model(scales, opacities):
    count = len(scales)
    means = torch.arange(count, dtype=torch.float32)[:, None].repeat(1, 3)
    log_scales = torch.log(torch.tensor(scales, dtype=torch.float32))[:, None].repeat(1, 3)
    quaternions = torch.tensor([[1.0, 0, 0, 0]]).repeat(count, 1)
    logits = torch.logit(torch.tensor(opacities, dtype=torch.float32))
    return means, log_scales, quaternions, logits


def test_gradients_are_averaged_in_ndc_units():
    stats = GradientStats(3)
    grad = torch.tensor([[1.0, 1.0], [0.0, 2.0], [5.0, 5.0]])
    stats.add(grad, torch.tensor([3, 3, 0]), width=100, height=60)
    stats.add(grad * 0, torch.tensor([3, 0, 0]), width=100, height=60)
    mean = stats.mean()
    assert mean[0] == pytest.approx(math.hypot(50, 30) / 2)  # two views, one with zero gradient
    assert mean[1] == pytest.approx(60.0) and mean[2] == 0.0  # never visible: no statistics


def test_clone_split_prune_and_keep():
    means, log_scales, quaternions, logits = model([0.01, 0.05, 0.01, 0.05, 0.01], [0.5, 0.5, 0.5, 0.5, 0.001])
    gradients = torch.tensor([1e-3, 1e-3, 1e-5, 1e-5, 1e-3])
    plan = plan_densification(
        means,
        log_scales,
        quaternions,
        torch.sigmoid(logits),
        gradients,
        DensifySettings(),
        EXTENT,
        False,
        torch.Generator().manual_seed(0),
    )
    assert plan.clone.tolist() == [0] and plan.split.tolist() == [1]
    assert plan.keep.tolist() == [True, False, True, True, False]  # split parent and transparent one go
    assert plan.new_count == 3 + 1 + 2
    assert torch.allclose(torch.exp(plan.child_log_scales), torch.full((2, 3), 0.05 / 1.6))
    new_means = apply_plan(plan, means, plan.child_means)
    assert new_means.shape == (6, 3) and torch.equal(new_means[3], means[0])  # the clone, unchanged
    moments = apply_plan(plan, torch.ones(5, 3), new_rows_zero=True)
    assert moments[:3].eq(1).all() and moments[3:].eq(0).all()
    assert apply_plan(plan, logits)[4:].eq(logits[1]).all()  # children inherit the opacity


def test_a_large_gaussian_with_a_high_gradient_is_split_before_the_size_rule():
    # max scale 0.3: above 0.1 × extent (0.2) but its children (0.1875) are not: they survive.
    means, log_scales, quaternions, logits = model([0.3, 0.5], [0.5, 0.5])
    plan = plan_densification(
        means,
        log_scales,
        quaternions,
        torch.sigmoid(logits),
        torch.tensor([1e-3, 1e-3]),
        DensifySettings(),
        EXTENT,
        True,
        torch.Generator().manual_seed(0),
    )
    assert plan.split.tolist() == [0, 1] and plan.keep.tolist() == [False, False]
    assert plan.child_keep.tolist() == [True, True, False, False]  # 0.5 / 1.6 is still too large
    assert plan.new_count == 2 and apply_plan(plan, logits).shape == (2,)


def test_large_gaussians_are_pruned_only_after_the_first_reset():
    means, log_scales, quaternions, logits = model([0.5, 0.01], [0.5, 0.5])
    gradients = torch.zeros(2)
    early = plan_densification(
        means, log_scales, quaternions, torch.sigmoid(logits), gradients, DensifySettings(), EXTENT, False
    )
    late = plan_densification(
        means, log_scales, quaternions, torch.sigmoid(logits), gradients, DensifySettings(), EXTENT, True
    )
    assert early.keep.tolist() == [True, True] and late.keep.tolist() == [False, True]


def test_split_children_are_drawn_from_the_parent():
    count = 4000
    means = torch.zeros(count, 3)
    log_scales = torch.log(torch.tensor([[0.3, 0.1, 0.05]])).repeat(count, 1)
    angle = math.pi / 6  # a rotation about z
    quaternions = torch.tensor([[math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)]]).repeat(count, 1)
    logits = torch.zeros(count)
    plan = plan_densification(
        means,
        log_scales,
        quaternions,
        torch.sigmoid(logits),
        torch.ones(count),
        DensifySettings(),
        EXTENT,
        False,
        torch.Generator().manual_seed(1),
    )
    assert plan.split.numel() == count and plan.child_means.shape == (2 * count, 3)
    covariance = torch.cov(plan.child_means.T)
    rotation = torch.tensor(
        [[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0], [0, 0, 1.0]]
    )
    expected = rotation @ torch.diag(torch.tensor([0.09, 0.01, 0.0025])) @ rotation.T
    assert torch.allclose(covariance, expected, atol=4e-3)


def test_the_budget_takes_the_largest_gradients_and_prunes_down():
    means, log_scales, quaternions, logits = model([0.01] * 6, [0.5, 0.6, 0.7, 0.4, 0.2, 0.9])
    gradients = torch.tensor([1e-3, 5e-3, 2e-3, 0.0, 0.0, 0.0])
    plan = plan_densification(
        means,
        log_scales,
        quaternions,
        torch.sigmoid(logits),
        gradients,
        DensifySettings(max_gaussians=7),
        EXTENT,
        False,
    )
    assert plan.clone.tolist() == [1] and plan.new_count == 7  # room for one: the largest gradient
    over = plan_densification(
        means,
        log_scales,
        quaternions,
        torch.sigmoid(logits),
        gradients,
        DensifySettings(max_gaussians=4),
        EXTENT,
        False,
    )
    assert over.keep.tolist() == [True, True, True, False, False, True]  # the two least opaque go
    assert over.clone.numel() == 0 and over.new_count == 4


def test_opacity_reset_caps_at_one_percent():
    logits = torch.logit(torch.tensor([0.9, 0.005, 1e-9]).clamp_min(1e-7))
    reset = torch.sigmoid(reset_opacity(logits))
    assert torch.allclose(reset, torch.tensor([0.01, 0.005, 1e-7]), rtol=1e-4)
    assert torch.isfinite(reset_opacity(torch.tensor([100.0, -100.0]))).all()


def test_the_reference_schedule_scales_to_the_run_length():
    from cubecloud_cli.splat.settings import SplatSettings

    assert SplatSettings(iterations=30_000).schedule() == {
        "densify_from": 500,
        "densify_until": 15_000,
        "densify_every": 100,
        "reset_every": 3000,
        "sh_up_every": 1000,
    }
    assert SplatSettings(iterations=2000).schedule() == {
        "densify_from": 33,
        "densify_until": 1000,
        "densify_every": 10,
        "reset_every": 200,
        "sh_up_every": 67,
    }


def tiny_trainer(settings, strategy=None, count=50):
    """A trainer of ``count`` random Gaussians on four 16² views of noise."""
    from pathlib import Path

    import numpy as np

    from cubecloud_cli.cameras import OrbitSpec, orbit_cameras
    from cubecloud_cli.splat import gaussians_from_points
    from cubecloud_cli.splat.densify import strategy_for
    from cubecloud_cli.splat.trainer import SplatTrainer
    from cubecloud_cli.splat.training_views import TrainingScene

    cameras = orbit_cameras(OrbitSpec(views=4, resolution=16))
    images = torch.rand(4, 16, 16, 1, generator=torch.Generator().manual_seed(0))
    scene = TrainingScene(Path("."), cameras, list("abcd"), images, [1, 2, 3], [0], None)
    rng = np.random.default_rng(0)
    start = gaussians_from_points(rng.uniform(-1, 1, (count, 3)), rng.uniform(0, 1, (count, 1)))
    strategy = strategy if strategy is not None else strategy_for(settings, scene.extent)
    return SplatTrainer(start, scene, settings, torch.device("cpu"), strategy)


def test_no_reset_or_densification_at_or_after_densify_until(monkeypatch):
    from cubecloud_cli.splat.settings import SplatSettings

    trainer = tiny_trainer(SplatSettings(iterations=200))
    strategy = trainer.strategy
    events = []
    monkeypatch.setattr(strategy, "_reset_opacity", lambda trainable: events.append(("reset", trainer.iteration)))
    original = strategy._densify
    monkeypatch.setattr(
        strategy,
        "_densify",
        lambda trainable, prune_large: (
            events.append(("densify", trainer.iteration)),
            original(trainable, prune_large),
        ),
    )
    for _ in range(200):
        trainer.step()
    resets = [it for kind, it in events if kind == "reset"]
    densified = [it for kind, it in events if kind == "densify"]
    assert resets == [20, 40, 60, 80] and densified == list(range(10, 100, 10))


def test_optimizer_moments_follow_their_rows_when_parameters_are_replaced():
    from cubecloud_cli.splat.optimizer import replace_parameters

    means = torch.arange(12, dtype=torch.float32).reshape(4, 3).requires_grad_(True)
    other = torch.zeros(4, 1, requires_grad=True)
    optimizer = torch.optim.Adam([{"params": [means], "name": "means"}, {"params": [other], "name": "other"}], lr=0.1)
    (means.square().sum() + other.sum()).backward()
    optimizer.step()
    before = {key: optimizer.state[means][key].clone() for key in ("exp_avg", "exp_avg_sq")}
    keep = torch.tensor([True, False, True, True])
    rows = torch.cat((torch.arange(4)[keep], torch.tensor([2])))  # prune row 1, duplicate row 2

    replaced = replace_parameters(optimizer, ["means"], lambda name, old: old[rows], lambda name, moment: moment[rows])

    new = replaced["means"]
    assert new.requires_grad and new.is_leaf and torch.equal(new.detach(), means.detach()[rows])
    assert optimizer.param_groups[0]["params"][0] is new and means not in optimizer.state
    for key, moment in before.items():
        assert torch.equal(optimizer.state[new][key], moment[rows])
    assert optimizer.param_groups[1]["params"][0] is other  # groups not named are untouched
    (new.square().sum() + other.sum()).backward()
    optimizer.step()  # Adam steps with the rewritten state


def test_the_schedule_says_when_to_densify_and_reset():
    from cubecloud_cli.splat.densify import DensifySchedule
    from cubecloud_cli.splat.settings import SplatSettings

    strategy = DensifySchedule.from_settings(SplatSettings(iterations=30_000))
    assert strategy.thresholds.grad_threshold == SplatSettings().grad_threshold
    assert not strategy.densify_due(500) and strategy.densify_due(600) and not strategy.densify_due(650)
    assert strategy.reset_due(3000) and not strategy.reset_due(15_000)  # no reset once refining stops
    assert not strategy.prunes_large(3000) and strategy.prunes_large(3001)
    assert not DensifySchedule.from_settings(SplatSettings(iterations=30_000, refine=False)).densify_due(600)


def test_a_trainer_given_no_density_control_trains_the_gaussians_it_started_with():
    from cubecloud_cli.splat.densify import NoDensification, ReferenceStrategy, strategy_for
    from cubecloud_cli.splat.settings import SplatSettings

    settings = SplatSettings(iterations=100)
    still = tiny_trainer(settings, NoDensification())
    start = still.gaussians.means.detach().clone()
    before = still.evaluate([1, 2, 3])["psnr"]
    for _ in range(100):
        still.step()
    assert len(still.gaussians) == 50 and still.evaluate([1, 2, 3])["psnr"] > before + 1.0
    assert not torch.equal(still.gaussians.means.detach(), start)  # trained, only not densified
    assert still.strategy.state_dict() == {}
    assert isinstance(strategy_for(SplatSettings(refine=False), 1.0), NoDensification)

    growing = tiny_trainer(settings)
    assert isinstance(growing.strategy, ReferenceStrategy)
    for _ in range(100):
        growing.step()
    assert len(growing.gaussians) != 50  # the reference's strategy, on the same start, changed the set
