"""Adam through torch's fused kernel, without torch.optim.

torch.optim's optimizers import torch._dynamo when a process builds its first one (their methods
are wrapped to keep dynamo out of them): about 2 s on this 2-core host, paid by every process
that trains (a cunerf or splat command, each of `run`'s side-by-side splat runs, a cohort job),
for nothing it uses. ``FusedAdam`` makes the update the way ``torch.optim.Adam(fused=True)``
does: per parameter group, the step counts go up by one and one call of the fused kernel updates
parameters and moments with the same arguments, so a step gives the same bits. Its state dict
has torch.optim's layout, so checkpoints written with torch.optim load, and the other way round.

Only what training here uses: no weight decay, AMSGrad, maximisation, gradient scaling or
closure; ``zero_grad`` sets gradients to None. Where the fused kernel is missing or refuses the
parameters' device or dtype, ``adam`` returns torch.optim.Adam instead, as before.
"""

from __future__ import annotations

import functools
from typing import Any, Iterable, Union

import torch

# torch.optim.Adam's own group entries, kept so that either optimizer loads the other's state.
TORCH_GROUP_DEFAULTS = {
    "weight_decay": 0.0,
    "amsgrad": False,
    "maximize": False,
    "foreach": None,
    "capturable": False,
    "differentiable": False,
    "fused": True,
    "decoupled_weight_decay": False,
}


class FusedAdam:
    """Adam with torch.optim's interface where training touches it: ``param_groups`` (each a dict
    with ``params`` and ``lr``, free to change between steps), ``state`` keyed by parameter,
    ``step``, ``zero_grad``, ``state_dict`` and ``load_state_dict``."""

    def __init__(
        self,
        params: Iterable[torch.Tensor] | Iterable[dict[str, Any]],
        lr: float = 1e-3,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
    ):
        defaults = {"lr": lr, "betas": tuple(betas), "eps": eps, **TORCH_GROUP_DEFAULTS}
        groups = list(params)
        if groups and not isinstance(groups[0], dict):
            groups = [{"params": groups}]
        self.param_groups: list[dict[str, Any]] = [
            {**defaults, **group, "params": list(group["params"])} for group in groups
        ]
        self.state: dict[torch.Tensor, dict[str, torch.Tensor]] = {}

    def _moments(self, parameter: torch.Tensor) -> dict[str, torch.Tensor]:
        state = self.state.get(parameter)
        if not state:
            # The step count lives beside the parameter in float32, as the fused kernel reads it.
            state = {
                "step": torch.zeros((), dtype=torch.float32, device=parameter.device),
                "exp_avg": torch.zeros_like(parameter, memory_format=torch.preserve_format),
                "exp_avg_sq": torch.zeros_like(parameter, memory_format=torch.preserve_format),
            }
            self.state[parameter] = state
        return state

    @torch.no_grad()
    def step(self) -> None:
        for group in self.param_groups:
            by_kind: dict[tuple[torch.device, torch.dtype], list[torch.Tensor]] = {}
            for parameter in group["params"]:
                if parameter.grad is not None:
                    by_kind.setdefault((parameter.device, parameter.dtype), []).append(parameter)
            beta1, beta2 = group["betas"]
            for parameters in by_kind.values():
                states = [self._moments(p) for p in parameters]
                steps = [s["step"] for s in states]
                torch._foreach_add_(steps, 1)
                torch._fused_adam_(
                    parameters,
                    [p.grad for p in parameters],
                    [s["exp_avg"] for s in states],
                    [s["exp_avg_sq"] for s in states],
                    [],
                    steps,
                    amsgrad=False,
                    lr=float(group["lr"]),
                    beta1=float(beta1),
                    beta2=float(beta2),
                    weight_decay=0.0,
                    eps=float(group["eps"]),
                    maximize=False,
                    grad_scale=None,
                    found_inf=None,
                )

    def zero_grad(self, set_to_none: bool = True) -> None:
        if not set_to_none:
            raise ValueError("FusedAdam only sets gradients to None")
        for group in self.param_groups:
            for parameter in group["params"]:
                parameter.grad = None

    def state_dict(self) -> dict[str, Any]:
        """torch.optim's layout: parameters numbered in group order, state by number."""
        numbers: dict[int, int] = {}
        groups = []
        for group in self.param_groups:
            ids = [numbers.setdefault(id(p), len(numbers)) for p in group["params"]]
            groups.append({**{k: v for k, v in group.items() if k != "params"}, "params": ids})
        state = {numbers[id(p)]: dict(s) for p, s in self.state.items() if id(p) in numbers}
        return {"state": state, "param_groups": groups}

    def load_state_dict(self, saved: dict[str, Any]) -> None:
        """Take moments and hyperparameters from ``saved`` (this class's or torch.optim.Adam's),
        onto the parameters' device and dtype; the parameters themselves stay."""
        saved_groups = saved["param_groups"]
        if len(saved_groups) != len(self.param_groups) or any(
            len(s["params"]) != len(g["params"]) for s, g in zip(saved_groups, self.param_groups)
        ):
            raise ValueError("the saved optimizer state has other parameter groups than this optimizer")
        parameters = {
            number: parameter
            for saved_group, group in zip(saved_groups, self.param_groups)
            for number, parameter in zip(saved_group["params"], group["params"])
        }
        self.state = {}
        for number, values in saved["state"].items():
            parameter = parameters[int(number)]
            self.state[parameter] = {
                key: value.to(device=parameter.device, dtype=torch.float32 if key == "step" else parameter.dtype)
                for key, value in values.items()
            }
        for saved_group, group in zip(saved_groups, self.param_groups):
            group.update({k: v for k, v in saved_group.items() if k != "params"}, betas=tuple(saved_group["betas"]))


Optimizer = Union[FusedAdam, torch.optim.Optimizer]


@functools.lru_cache(maxsize=None)
def fused_adam_runs_on(device: torch.device, dtype: torch.dtype = torch.float32) -> bool:
    """Whether torch's fused Adam kernel exists here and takes tensors of this device and dtype
    (probed once per process and kind)."""
    try:
        probe = torch.zeros(1, dtype=dtype, device=device, requires_grad=True)
        probe.grad = torch.ones_like(probe)
        FusedAdam([probe]).step()
    except (AttributeError, RuntimeError, TypeError, NotImplementedError):
        return False
    return True


def adam(
    groups: list[dict[str, Any]], lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8
) -> Optimizer:
    """``FusedAdam`` over ``groups`` where the fused kernel runs on their parameters, else
    torch.optim.Adam (fused where it can be)."""
    parameters = [p for group in groups for p in group["params"]]
    kinds = {(p.device, p.dtype) for p in parameters}
    if all(fused_adam_runs_on(device, dtype) for device, dtype in kinds):
        return FusedAdam(groups, lr=lr, betas=betas, eps=eps)
    try:
        return torch.optim.Adam(groups, lr=lr, betas=betas, eps=eps, fused=True)
    except (RuntimeError, TypeError):
        return torch.optim.Adam(groups, lr=lr, betas=betas, eps=eps)
