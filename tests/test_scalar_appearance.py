"""What a scalar Gaussian hands the rasterizer on a CPU (splat/scalar_appearance.py): the numba
kernel against the torch map it stands in for (ScalarGaussians' scales, opacities and colours),
finite differences, and the extremes of its clamps."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.splat.gaussians import LOG_SCALE_LIMIT
from cubecloud_cli.splat.scalar_appearance import LOG_LENGTH_LIMIT, scalar_appearance
from cubecloud_cli.splat.scalar_gaussians import ScalarGaussians
from cubecloud_cli.transfer.function import TransferFunction

TRAINED = ("quaternions", "log_scales", "value_logits", "log_lengths")
TRANSFERS = {
    "ramp": TransferFunction(0.3, 0.6, 4.0),
    "band": TransferFunction(0.55, 0.6, 10.0, 0.7, 0.8),
    "step": TransferFunction(0.5, 0.5, 30.0),  # a window of zero width
    "zero-width band": TransferFunction(0.4, 0.4, 8.0, 0.6, 0.6),
    "clear": TransferFunction(0.2, 0.9, 0.0),
    "dense": TransferFunction(0.1, 0.2, 9.9e5),
}


def _gaussians(seed: int, count: int, dtype, transfer: TransferFunction, chord: bool, smoothing: bool, spread=1.0):
    generator = torch.Generator().manual_seed(seed)

    def normal(*shape):
        return torch.randn(*shape, generator=generator, dtype=dtype)

    return ScalarGaussians(
        normal(count, 3),
        normal(count, 3) * spread - 3.0,
        normal(count, 4),
        normal(count) * 2.0 * spread,
        normal(count) * spread - 1.0,
        transfer,
        smoothing=torch.rand(count, generator=generator, dtype=dtype) * 0.01 if smoothing else None,
        chord_lengths=chord,
    )


def _torch_map(gaussians: ScalarGaussians, centre: torch.Tensor) -> torch.Tensor:
    scales = gaussians.scales()
    opacities = gaussians.opacities(centre, scales)
    return torch.cat((scales.reshape(-1), opacities, gaussians.colours(centre)[:, 0]))


def _kernel(gaussians: ScalarGaussians, centre: torch.Tensor) -> torch.Tensor:
    g = gaussians
    scales, opacities, colours = scalar_appearance(
        g.means, g.quaternions, g.log_scales, g.value_logits, g.log_lengths, g.smoothing, g.transfer, centre,
        g.chord_lengths,
    )  # fmt: skip
    return torch.cat((scales.reshape(-1), opacities, colours[:, 0]))


def _trained(gaussians: ScalarGaussians) -> tuple[torch.Tensor, ...]:
    for name in TRAINED:
        getattr(gaussians, name).requires_grad_(True)
    return tuple(getattr(gaussians, name) for name in TRAINED)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    transfer=st.sampled_from(sorted(TRANSFERS)),
    chord=st.booleans(),
    smoothing=st.booleans(),
    spread=st.sampled_from([0.1, 1.0, 4.0]),
    dtype=st.sampled_from(["32", "64"]),
)
def test_the_kernel_matches_the_torch_map_and_its_gradients(seed, transfer, chord, smoothing, spread, dtype):
    """Against the torch map in float64 on the same parameters: the kernel computes in float64, and
    torch in float32 would put a window's edge elsewhere by its rounding of v − low (with a window
    of zero width, a slope of 1e6, any gradient at all)."""
    dtype = torch.float32 if dtype == "32" else torch.float64
    gaussians = _gaussians(seed, 48, dtype, TRANSFERS[transfer], chord, smoothing, spread)
    centre = torch.tensor([0.3, -0.2, 4.0], dtype=dtype)
    oracle = ScalarGaussians(
        **{name: getattr(gaussians, name).detach().double() for name in ("means", *TRAINED)},
        transfer=gaussians.transfer,
        smoothing=None if gaussians.smoothing is None else gaussians.smoothing.double(),
        chord_lengths=chord,
    )
    used = TRAINED if chord else TRAINED[1:]  # without chord lengths the rotation changes nothing here
    for g in (gaussians, oracle):
        _trained(g)
    kernel, formula = _kernel(gaussians, centre), _torch_map(oracle, centre.double())
    tolerance = {"rtol": 1e-5, "atol": 1e-6} if dtype == torch.float32 else {"rtol": 1e-9, "atol": 1e-12}
    torch.testing.assert_close(kernel, formula.to(dtype), **tolerance)
    weights = torch.randn(kernel.shape[0], generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    by_kernel = torch.autograd.grad((kernel.double() * weights).sum(), [getattr(gaussians, n) for n in used])
    by_formula = torch.autograd.grad((formula * weights).sum(), [getattr(oracle, n) for n in used])
    rtol = 1e-4 if dtype == torch.float32 else 1e-8
    for a, b in zip(by_kernel, by_formula):
        torch.testing.assert_close(a.double(), b, rtol=rtol, atol=rtol * max(float(b.abs().max()), 1e-6))


@pytest.mark.parametrize("transfer", ["ramp", "band"])
@pytest.mark.parametrize("chord", [False, True])
def test_the_kernels_gradients_match_finite_differences(transfer, chord):
    gaussians = _gaussians(5, 6, torch.float64, TRANSFERS[transfer], chord, smoothing=True)
    gaussians.value_logits = torch.logit(torch.tensor([0.35, 0.45, 0.57, 0.65, 0.75, 0.5], dtype=torch.float64))
    centre = torch.tensor([0.0, 0.5, 5.0], dtype=torch.float64)

    def drawn(quaternions, log_scales, logits, log_lengths):
        g = gaussians
        return scalar_appearance(
            g.means, quaternions, log_scales, logits, log_lengths, g.smoothing, g.transfer, centre, chord
        )

    assert torch.autograd.gradcheck(drawn, _trained(gaussians))


@settings(max_examples=40, deadline=None)
@given(
    logit=st.sampled_from([-1e4, -90.0, 0.0, 90.0, 1e4]),
    log_length=st.sampled_from([-1e4, -LOG_LENGTH_LIMIT - 1, 0.0, LOG_LENGTH_LIMIT + 1, 1e4]),
    log_scale=st.sampled_from([-1e3, -LOG_SCALE_LIMIT - 1, -3.0, LOG_SCALE_LIMIT + 1, 1e3]),
    transfer=st.sampled_from(sorted(TRANSFERS)),
)
def test_at_the_extremes_every_output_and_gradient_stays_finite(logit, log_length, log_scale, transfer):
    gaussians = _gaussians(1, 4, torch.float32, TRANSFERS[transfer], chord=True, smoothing=True)
    gaussians.value_logits = torch.full((4,), logit)
    gaussians.log_lengths = torch.full((4,), log_length)
    gaussians.log_scales = torch.full((4, 3), log_scale)
    inputs = _trained(gaussians)
    scales, opacities, colours = scalar_appearance(
        *(gaussians.means, *inputs[:1], inputs[1], inputs[2], inputs[3]),
        gaussians.smoothing, gaussians.transfer, torch.tensor([0.0, 0.0, 4.0]), True,
    )  # fmt: skip
    for output in (scales, opacities, colours):
        assert torch.isfinite(output).all()
    assert ((opacities >= 0) & (opacities <= 1)).all() and ((colours >= 0) & (colours <= 1)).all()
    (scales.sum() + opacities.sum() + colours.sum()).backward()
    for tensor in inputs:
        assert torch.isfinite(tensor.grad).all()
    if abs(log_scale) > LOG_SCALE_LIMIT:  # clamped: no gradient through the scales
        assert (inputs[1].grad == 0).all()
    if abs(log_length) > LOG_LENGTH_LIMIT + 12:  # clamped past any chord ratio
        assert (inputs[3].grad == 0).all()


def test_a_row_with_no_gradient_stays_zero_under_a_non_finite_upstream_gradient():
    gaussians = _gaussians(2, 3, torch.float32, TRANSFERS["band"], chord=True, smoothing=True)
    gaussians.value_logits = torch.tensor([-30.0, 0.62, 30.0])  # far below, inside (0.65), far above the band
    inputs = _trained(gaussians)
    _, opacities, _ = scalar_appearance(
        gaussians.means, *inputs[:2], inputs[2], inputs[3], gaussians.smoothing, gaussians.transfer,
        torch.tensor([0.0, 0.0, 4.0]), True,
    )  # fmt: skip
    opacities.backward(torch.tensor([math.nan, 1.0, math.inf]))
    by_length = inputs[3].grad
    assert by_length[0] == 0 and by_length[2] == 0 and torch.isfinite(by_length[1]) and by_length[1] != 0


def test_the_model_draws_through_the_kernel_on_a_cpu_and_through_torch_for_a_scene_read_from_its_ply():
    gaussians = _gaussians(4, 32, torch.float32, TRANSFERS["band"], chord=True, smoothing=True)
    centre = torch.tensor([0.0, 1.0, 4.0])
    scales, opacities, colours = gaussians.drawn(centre)
    torch.testing.assert_close(torch.cat((scales.reshape(-1), opacities, colours[:, 0])), _torch_map(gaussians, centre))
    from_ply = ScalarGaussians(**{**vars(gaussians), "opacity_scale": torch.full((32,), 0.5)})
    torch.testing.assert_close(from_ply.drawn(centre)[1], from_ply.opacities(centre))
