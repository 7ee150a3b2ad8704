"""FusedAdam: torch.optim.Adam(fused=True)'s bits and state dict, without importing torch._dynamo."""

import subprocess
import sys

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.numerics import adam as adam_module
from cubecloud_cli.numerics.adam import FusedAdam, adam


def parameters(seed: int) -> list[torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    return [
        torch.randn(40, 3, generator=generator).requires_grad_(),
        torch.randn(40, generator=generator).requires_grad_(),
    ]


def groups(tensors):
    return [{"params": [tensors[0]], "lr": 0.1, "name": "a"}, {"params": [tensors[1]], "lr": 0.01, "name": "b"}]


def train(optimizer, tensors, steps: range, scale: float = 1.0):
    """Gradients from a fixed stream; the second parameter gets none at step 3 and zeros at step 2."""
    for step in steps:
        generator = torch.Generator().manual_seed(100 + step)
        gradients = [scale * torch.randn(t.shape, generator=generator) for t in tensors]
        tensors[0].grad = gradients[0]
        tensors[1].grad = None if step == 3 else gradients[1] * (step != 2)
        optimizer.param_groups[0]["lr"] = 0.1 / (step + 1)  # as the means' schedule changes it
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)


def assert_same_state(ours: dict, theirs: dict):
    assert ours["param_groups"] == theirs["param_groups"]
    assert ours["state"].keys() == theirs["state"].keys()
    for number, values in theirs["state"].items():
        assert values.keys() == ours["state"][number].keys()
        for key, value in values.items():
            assert ours["state"][number][key].dtype == value.dtype
            torch.testing.assert_close(ours["state"][number][key], value, rtol=0, atol=0, equal_nan=True)


def test_steps_give_the_bits_and_state_of_torchs_fused_adam():
    mine, reference = parameters(0), parameters(0)
    ours = FusedAdam(groups(mine), eps=1e-15)
    theirs = torch.optim.Adam(groups(reference), eps=1e-15, fused=True)
    train(ours, mine, range(6))
    train(theirs, reference, range(6))
    assert all(torch.equal(a, b) for a, b in zip(mine, reference))
    assert_same_state(ours.state_dict(), theirs.state_dict())


@pytest.mark.parametrize("direction", ["torch to ours", "ours to torch"])
def test_either_optimizer_resumes_from_the_others_state(direction):
    """A checkpoint written with torch.optim (before FusedAdam) resumes with FusedAdam, and the
    other way round, to the bits of an uninterrupted run."""
    uninterrupted, resumed = parameters(1), parameters(1)
    train(FusedAdam(groups(uninterrupted), eps=1e-15), uninterrupted, range(8))
    first, second = (torch.optim.Adam, FusedAdam) if direction == "torch to ours" else (FusedAdam, torch.optim.Adam)
    options = {"fused": True} if first is torch.optim.Adam else {}
    before = first(groups(resumed), eps=1e-15, **options)
    train(before, resumed, range(4))
    saved = before.state_dict()
    options = {"fused": True} if second is torch.optim.Adam else {}
    after = second(groups(resumed), eps=1e-3, **options)  # the saved eps wins, as in torch.optim
    after.load_state_dict(saved)
    train(after, resumed, range(4, 8))
    assert all(torch.equal(a, b) for a, b in zip(uninterrupted, resumed))


def test_a_state_of_other_groups_is_refused():
    tensors = parameters(2)
    saved = FusedAdam(groups(tensors)).state_dict()
    with pytest.raises(ValueError, match="other parameter groups"):
        FusedAdam([{"params": tensors}]).load_state_dict(saved)


@settings(max_examples=25, deadline=None)
@given(
    gradient=st.sampled_from([0.0, -0.0, 1e-38, 1e-45, -3.0, 1e19, 3e38, float("inf"), float("nan")]),
    eps=st.sampled_from([1e-15, 1e-8, 1e-6]),
    betas=st.sampled_from([(0.9, 0.999), (0.9, 0.99), (0.0, 0.0)]),
)
def test_extreme_gradients_give_torchs_bits(gradient, eps, betas):
    """Underflowing, overflowing and non-finite gradients, zero betas: the same bits as torch's
    kernel, whatever they are (training stops on a non-finite parameter by itself)."""
    mine, reference = [torch.linspace(-2, 2, 16).requires_grad_()], [torch.linspace(-2, 2, 16).requires_grad_()]
    optimizers = (
        FusedAdam(mine, lr=0.5, betas=betas, eps=eps),
        torch.optim.Adam(reference, lr=0.5, betas=betas, eps=eps, fused=True),
    )
    for optimizer, tensors in zip(optimizers, (mine, reference)):
        for step in range(3):
            tensors[0].grad = torch.full((16,), gradient) * (step + 1)
            optimizer.step()
    torch.testing.assert_close(mine[0], reference[0], rtol=0, atol=0, equal_nan=True)
    if gradient in (0.0, -0.0):
        assert torch.equal(mine[0].detach(), torch.linspace(-2, 2, 16))  # 0 / (0 + eps) moves nothing


def test_without_the_fused_kernel_training_gets_torchs_adam(monkeypatch):
    tensors = parameters(3)
    assert isinstance(adam(groups(tensors)), FusedAdam)
    monkeypatch.setattr(adam_module, "fused_adam_runs_on", lambda device, dtype: False)
    fallback = adam(groups(tensors), eps=1e-15)
    assert isinstance(fallback, torch.optim.Adam) and fallback.param_groups[0]["eps"] == 1e-15


def test_a_process_that_trains_imports_no_dynamo():
    """torch.optim imports torch._dynamo on a process's first optimizer (about 2 s); the trainers'
    optimizer does not, after the imports the stages make."""
    probe = (
        "import sys\n"
        "import torch\n"
        "import cubecloud_cli.pipeline.runner\n"  # every stage's module
        "from cubecloud_cli.numerics.adam import adam\n"
        "parameter = torch.zeros(3, requires_grad=True)\n"
        "optimizer = adam([{'params': [parameter], 'lr': 0.1}])\n"
        "parameter.sum().backward()\n"
        "optimizer.step()\n"
        "print(type(optimizer).__name__, 'torch._dynamo' in sys.modules)\n"
    )
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert result.stdout.split() == ["FusedAdam", "False"]
