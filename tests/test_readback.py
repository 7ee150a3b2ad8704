"""Values a trainer reads back from its device in groups (numerics/readback.py): the same
training, running mean, history and failure point as reading each step, on the CPU where the
grouping can be forced; and the splat trainer reads everything before it changes its Gaussians."""

from __future__ import annotations

import pytest
import torch
from test_densify import tiny_trainer

from cubecloud_cli.numerics.readback import READ_EVERY_ON_GPU, GroupedReads
from cubecloud_cli.splat.gaussians import TRAINED_PARAMETERS
from cubecloud_cli.splat.settings import SplatSettings


def test_reads_come_back_in_order_once_and_when_due():
    reads = GroupedReads(3)
    assert not reads.push(1, torch.tensor([1.5, 1.0]))
    assert not reads.push(2, torch.tensor([2.5, 0.0]))
    assert reads.push(3, torch.tensor([float("nan"), 1.0]))
    read = reads.read()
    assert [i for i, _ in read] == [1, 2, 3] and read[0][1] == [1.5, 1.0] and read[1][1] == [2.5, 0.0]
    assert read[2][1][0] != read[2][1][0]  # NaN comes back as NaN
    assert reads.read() == []
    assert GroupedReads.for_device(torch.device("cpu")).every == 1
    assert GroupedReads.for_device(torch.device("cuda")).every == READ_EVERY_ON_GPU


def _parameters(trainer):
    return [getattr(trainer.gaussians, name).detach().clone() for name in TRAINED_PARAMETERS]


def test_a_splat_run_read_in_groups_trains_as_one_read_each_step(monkeypatch):
    settings = SplatSettings(iterations=120)
    each, grouped = tiny_trainer(settings), tiny_trainer(settings)
    grouped._reads.every = 7
    changes = []
    original = grouped.strategy.step_post_optimizer

    def checked(iteration, trainable):
        if grouped.strategy.changes_at(iteration):
            changes.append(iteration)
            assert not grouped._reads._pending  # every step before a change was read first
        return original(iteration, trainable)

    monkeypatch.setattr(grouped.strategy, "step_post_optimizer", checked)
    for _ in range(120):
        each.step()
        grouped.step()
    assert changes and len(grouped.gaussians) != 50  # the set changed, after reads
    grouped.read_back()
    assert grouped.last_loss == each.last_loss
    for a, b in zip(_parameters(each), _parameters(grouped)):
        assert torch.equal(a, b)


def test_a_parameter_that_is_not_finite_is_named_at_its_own_iteration_when_read_late():
    trainer = tiny_trainer(SplatSettings(iterations=30))  # densification starts at 33: none here
    trainer._reads.every = 10
    for _ in range(4):
        trainer.step()
    with torch.no_grad():
        trainer.gaussians.opacity_logits[0] = float("nan")  # iteration 5's parameters
    for _ in range(3):
        trainer.step()
    with pytest.raises(FloatingPointError, match="became NaN or Inf at iteration 5"):
        trainer.read_back()
