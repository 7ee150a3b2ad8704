"""Optimizer-state surgery: swapping a parameter in its Adam group while keeping the moments of
the rows that survive, as gsplat's strategies do when Gaussians are added, removed or reset."""

from __future__ import annotations

from typing import Callable, Iterable

import torch

from cubecloud_cli.numerics.adam import Optimizer

MOMENTS = ("exp_avg", "exp_avg_sq")


def replace_parameters(
    optimizer: Optimizer,
    names: Iterable[str],
    new_value: Callable[[str, torch.Tensor], torch.Tensor],
    new_moment: Callable[[str, torch.Tensor], torch.Tensor],
) -> dict[str, torch.Tensor]:
    """Replace each named group's parameter by ``new_value(name, old)`` and each of its Adam moments
    by ``new_moment(name, moment)``; returns the new parameters (leaves that require grad).

    Adam keys its state by the parameter object, so the state moves to the new one; the step
    count stays, as in the reference."""
    wanted = set(names)
    replaced = {}
    for group in optimizer.param_groups:
        name = group["name"]
        if name not in wanted:
            continue
        old = group["params"][0]
        new = new_value(name, old.detach()).requires_grad_(True)
        state = optimizer.state.pop(old, {})
        for key in MOMENTS:
            if key in state:
                state[key] = new_moment(name, state[key])
        group["params"][0] = new
        if state:
            optimizer.state[new] = state
        replaced[name] = new
    return replaced
