"""The arithmetic of the paper's MLP on a CUDA GPU (issue 54).

The paper's network is eight 256-wide layers applied to 192 points per cube, 1024 cubes per
iteration: about 0.5 TFLOP per training step, so in float32 an H100/H200 runs at its plain
float32 rate (~60 TFLOP/s) and a 200 000-iteration run takes half an hour. Tensor cores take
the same matrix products in TF32 (inputs rounded to 10 mantissa bits, sums in float32) or in
bfloat16 (8 bits; products of the hidden layers only) at several times that rate.

* ``float32``: as written; the only choice on the CPU and for the grid field.
* ``tf32``: TF32 tensor cores in every float32 matrix product of the scope (forward and
  backward).
* ``bf16``: the hidden layers run under bfloat16 autocast. The positional encoding (sin of up
  to 2¹⁰·π·x, where bfloat16 would round away the position) and the 256 → 2 head (the output
  the loss and the renders see) stay float32, and so do the cube renderer and the optimizer.
"""

from __future__ import annotations

import contextlib
from typing import TYPE_CHECKING, ContextManager, Iterator, Literal, get_args

if TYPE_CHECKING:  # the options are read where no stage runs: torch is imported in the scopes
    import torch

Precision = Literal["float32", "tf32", "bf16"]
PRECISIONS: tuple[str, ...] = get_args(Precision)


def precision_problem(precision: str, model: str, device_type: str) -> str | None:
    """Why ``precision`` cannot run here (a one-line message naming the fix), or None."""
    if precision not in PRECISIONS:
        return f"--precision {precision!r} must be one of {', '.join(PRECISIONS)}"
    if precision == "float32":
        return None
    if model != "cunerf":
        return f"--precision {precision} is for --model cunerf (the paper's MLP): the grid field computes in float32"
    if device_type != "cuda":
        return f"--precision {precision} needs a CUDA GPU (--device cuda): on the {device_type} use --precision float32"
    return None


@contextlib.contextmanager
def matmul_scope(precision: str, device: torch.device) -> Iterator[None]:
    """Within the scope, float32 matrix products on ``device`` may use TF32 tensor cores when
    ``precision`` is tf32. torch keeps that choice process-wide, so the scope restores it on
    the way out; a training step holds the scope over its backward pass too."""
    if precision != "tf32" or device.type != "cuda":
        yield
        return
    import torch

    previous = torch.get_float32_matmul_precision()
    torch.set_float32_matmul_precision("high")
    try:
        yield
    finally:
        torch.set_float32_matmul_precision(previous)


def hidden_layers_autocast(precision: str, device: torch.device) -> ContextManager[object]:
    """bfloat16 autocast for the MLP's hidden layers when ``precision`` is bf16; its backward
    pass follows the forward's casts wherever it runs. On a CPU only tests ask for it."""
    if precision != "bf16":
        return contextlib.nullcontext()
    import torch

    return torch.autocast(device.type, dtype=torch.bfloat16)
