"""A numba kernel against the torch formula it stands in for: values, and gradients by autograd."""

from __future__ import annotations

import torch


def assert_matches_formula(
    kernel: torch.Tensor,
    formula: torch.Tensor,
    inputs: tuple[torch.Tensor, ...],
    seed: int,
    values: dict[str, float],
    gradient_atol: float,
) -> None:
    """``kernel`` and ``formula``, (N,) outputs of the same ``inputs``, agree within ``values``
    (assert_close's rtol and atol), and so do their gradients to ``inputs`` under seeded random
    weights of the rows (within rtol 1e-3 in float32, 1e-8 in float64, and ``gradient_atol``
    times the largest)."""
    torch.testing.assert_close(kernel, formula, **values)
    weights = torch.randn(kernel.shape[0], generator=torch.Generator().manual_seed(seed), dtype=kernel.dtype)
    by_kernel = torch.autograd.grad((kernel * weights).sum(), inputs)
    by_formula = torch.autograd.grad((formula * weights).sum(), inputs)
    rtol = 1e-3 if kernel.dtype == torch.float32 else 1e-8
    for a, b in zip(by_kernel, by_formula):
        torch.testing.assert_close(a, b, rtol=rtol, atol=gradient_atol * b.abs().max())
