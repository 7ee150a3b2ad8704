"""What a scalar Gaussian hands the rasterizer, in one numba pass each way on a CPU.

``ScalarGaussians`` (``scalar_gaussians.py``) defines the map in torch, which stays the GPU's
path and this kernel's oracle: the rendered scales sⱼ = sqrt(e^{2 log sⱼ} + filter variance), the
3D filter's attenuation, the value v = sigmoid(logit), the transfer function's extinction σ(v),
the chord ratio r seen from the camera (``chord.py``), and

    α = attenuation · (1 − exp(−σ(v) · exp(clamp(log ℓ + log r)))),    colour = v.

In torch that was some forty elementwise operations on (N,) and (N, 3) tensors each way, each
with its temporary: 9.6 ms of a 26 ms training step at 50,000 Gaussians on the 2-core VM. Past
the scales' exps and the sigmoid (torch's, vectorised, in float64), the kernel computes every
output and its derivatives by the raw parameters in one float64 pass, and the backward pass is
one product per parameter.

The clamps are torch's: a clamped log scale, optical length or chord ratio passes no gradient
(torch's clamp passes it at the bounds themselves, as here), and neither do the transfer
function's flat parts. A row whose partial derivative is 0 gets 0, even from a non-finite
upstream gradient.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange

from cubecloud_cli.numerics.jit import PRANGE_ONLY
from cubecloud_cli.splat.chord import chord_terms
from cubecloud_cli.splat.gaussians import LOG_SCALE_LIMIT
from cubecloud_cli.transfer.function import TransferFunction

# exp(±LOG_LENGTH_LIMIT) world units: with densities below 1e6 the optical depth σ·ℓ stays
# below 2.3e10, finite in float32, and so does its gradient.
LOG_LENGTH_LIMIT = 10.0
# Columns of the partial derivatives the forward pass keeps for the backward one.
BY_LOGIT, BY_LENGTH = 0, 1  # ∂α/∂logit, ∂α/∂log ℓ
BY_LOG_SCALES = 2  # three: ∂α/∂log sⱼ
BY_QUATERNION = 5  # four: ∂α/∂u for the raw quaternion u
COLOUR_BY_LOGIT = 9  # ∂colour/∂logit = v(1 − v)
SCALES_BY_LOG_SCALES = 10  # three: ∂sⱼ/∂log sⱼ
PARTIALS = 13


@njit(inline="always")
def _clip_unit(x):
    """clip(x, 0, 1) and whether torch's clip passes a gradient there (0 <= x <= 1)."""
    if x < 0.0:
        return 0.0, False
    if x > 1.0:
        return 1.0, False
    return x, True


@njit(inline="always")
def _axis(raw, own, variance, with_filter):
    """One axis of log scale ``raw`` and scale ``own`` (its clamped exp): the rendered scale s,
    ∂s/∂log s, the share of its smoothed variance that is the Gaussian's own (the 3D filter's
    attenuation is the square root of the three shares' product) and that log share's derivative
    by log s."""
    passes = -LOG_SCALE_LIMIT <= raw <= LOG_SCALE_LIMIT
    if not with_filter:
        return own, own if passes else 0.0, 1.0, 0.0
    square = own * own
    smoothed = square + variance
    s = math.sqrt(smoothed)
    share = square / smoothed
    if not passes:
        return s, 0.0, share, 0.0
    return s, s * share, share, 1.0 - share


@njit(parallel=PRANGE_ONLY, cache=True)
def _appearance_forward(
    means, quaternions, log_scales, own_scales, values, log_lengths, variances, centre, transfer, flags, scales,
    alphas, partials,
) -> None:  # fmt: skip
    """scales and alphas of every Gaussian, and ``partials`` (N, PARTIALS), from the clamped exp of
    the log scales and the values, both float64 (torch's vectorised exp is cheaper than a call per
    element, which bounds this kernel). ``transfer``:
    (low, rise width, fall start, fall width, density) as ``march_parameters`` gives them;
    ``flags``: (with the 3D filter, with chord lengths)."""
    low, rise_width, fall_low, fall_width, density = transfer[0], transfer[1], transfer[2], transfer[3], transfer[4]
    with_filter, with_chord = flags[0], flags[1]
    for i in prange(means.shape[0]):
        variance = float(variances[i]) if with_filter else 0.0
        s0, ds0, share0, by_att0 = _axis(float(log_scales[i, 0]), float(own_scales[i, 0]), variance, with_filter)
        s1, ds1, share1, by_att1 = _axis(float(log_scales[i, 1]), float(own_scales[i, 1]), variance, with_filter)
        s2, ds2, share2, by_att2 = _axis(float(log_scales[i, 2]), float(own_scales[i, 2]), variance, with_filter)
        shares = share0 * share1 * share2
        if not shares <= 1.0:  # torch's clamp_max(0) of the log: no gradient past it
            by_att0 = by_att1 = by_att2 = 0.0
        attenuation = math.sqrt(min(shares, 1.0))

        value = float(values[i])
        by_logit = value * (1.0 - value)
        rise, rise_passes = _clip_unit((value - low) / rise_width)
        fall_in, fall_passes = _clip_unit((value - fall_low) / fall_width)
        fall = 1.0 - fall_in
        slope = (fall / rise_width if rise_passes else 0.0) - (rise / fall_width if fall_passes else 0.0)
        extinction = density * rise * fall

        log_ratio, by_w, by_x, by_y, by_z, by_s0, by_s1, by_s2 = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        if with_chord:
            _, log_ratio, by_w, by_x, by_y, by_z, by_s0, by_s1, by_s2 = chord_terms(
                means, quaternions, centre, i, s0, s1, s2, True
            )
        raw_length = float(log_lengths[i]) + log_ratio
        length_passes = -LOG_LENGTH_LIMIT <= raw_length <= LOG_LENGTH_LIMIT
        length = math.exp(min(max(raw_length, -LOG_LENGTH_LIMIT), LOG_LENGTH_LIMIT))
        depth = extinction * length
        drawn = -math.expm1(-depth)
        alpha = attenuation * drawn
        through = attenuation * (1.0 - drawn)  # ∂α/∂depth, exp(−depth) to an ulp of 1
        by_length = through * depth if length_passes else 0.0

        scales[i, 0], scales[i, 1], scales[i, 2] = s0, s1, s2
        alphas[i] = alpha
        partials[i, BY_LOGIT] = through * length * density * slope * by_logit
        partials[i, BY_LENGTH] = by_length
        partials[i, BY_LOG_SCALES + 0] = alpha * by_att0 + by_length * by_s0 * ds0
        partials[i, BY_LOG_SCALES + 1] = alpha * by_att1 + by_length * by_s1 * ds1
        partials[i, BY_LOG_SCALES + 2] = alpha * by_att2 + by_length * by_s2 * ds2
        partials[i, BY_QUATERNION + 0] = by_length * by_w
        partials[i, BY_QUATERNION + 1] = by_length * by_x
        partials[i, BY_QUATERNION + 2] = by_length * by_y
        partials[i, BY_QUATERNION + 3] = by_length * by_z
        partials[i, COLOUR_BY_LOGIT] = by_logit
        partials[i, SCALES_BY_LOG_SCALES + 0] = ds0
        partials[i, SCALES_BY_LOG_SCALES + 1] = ds1
        partials[i, SCALES_BY_LOG_SCALES + 2] = ds2


@njit(inline="always")
def _times(upstream, partial):
    """upstream · partial, 0 where the partial is (a masked row stays 0 under a NaN upstream)."""
    return upstream * partial if partial != 0.0 else 0.0


@njit(parallel=PRANGE_ONLY, cache=True)
def _appearance_backward(partials, by_scales, by_alphas, by_colours, logits, lengths, log_scales, quaternions) -> None:
    for i in prange(partials.shape[0]):
        by_alpha = float(by_alphas[i])
        logits[i] = _times(by_alpha, partials[i, BY_LOGIT]) + _times(float(by_colours[i]), partials[i, COLOUR_BY_LOGIT])
        lengths[i] = _times(by_alpha, partials[i, BY_LENGTH])
        for j in range(3):
            log_scales[i, j] = _times(by_alpha, partials[i, BY_LOG_SCALES + j]) + _times(
                float(by_scales[i, j]), partials[i, SCALES_BY_LOG_SCALES + j]
            )
        for k in range(4):
            quaternions[i, k] = _times(by_alpha, partials[i, BY_QUATERNION + k])


class _ScalarAppearance(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quaternions, log_scales, value_logits, log_lengths, variances, centre, transfer, flags):
        # In float64, as the kernel computes: a window's edge then falls where float64 arithmetic
        # puts it, whatever the parameters' dtype.
        own_scales = torch.exp(log_scales.detach().double().clamp(-LOG_SCALE_LIMIT, LOG_SCALE_LIMIT))
        values = torch.sigmoid(value_logits.detach().double())
        arrays = [
            np.ascontiguousarray(t.detach().numpy())
            for t in (means, quaternions, log_scales, own_scales, values, log_lengths, variances, centre)
        ]
        count, dtype = means.shape[0], log_scales.dtype
        colours = values.to(dtype)
        scales, alphas = torch.empty((count, 3), dtype=dtype), torch.empty(count, dtype=dtype)
        partials = torch.empty((count, PARTIALS), dtype=dtype)
        _appearance_forward(*arrays, transfer, flags, scales.numpy(), alphas.numpy(), partials.numpy())
        ctx.save_for_backward(partials)
        return scales, alphas, colours[:, None]

    @staticmethod
    def backward(ctx, by_scales, by_alphas, by_colours):
        (partials,) = ctx.saved_tensors
        count, dtype = partials.shape[0], partials.dtype
        grads = [torch.empty(count, dtype=dtype), torch.empty(count, dtype=dtype)]
        grads += [torch.empty((count, 3), dtype=dtype), torch.empty((count, 4), dtype=dtype)]

        def upstream(grad, shape):  # an output nothing depends on gets no gradient from autograd
            grad = torch.zeros(shape, dtype=dtype) if grad is None else grad
            return np.ascontiguousarray(grad.reshape(shape).numpy())

        by_each = (upstream(by_scales, (count, 3)), upstream(by_alphas, (count,)), upstream(by_colours, (count,)))
        _appearance_backward(partials.numpy(), *by_each, *[g.numpy() for g in grads])
        by_logits, by_lengths, by_log_scales, by_quaternions = grads
        return None, by_quaternions, by_log_scales, by_logits, by_lengths, None, None, None, None


def scalar_appearance(
    means: torch.Tensor,
    quaternions: torch.Tensor,
    log_scales: torch.Tensor,
    value_logits: torch.Tensor,
    log_lengths: torch.Tensor,
    smoothing: torch.Tensor | None,
    transfer: TransferFunction,
    camera_centre: torch.Tensor | None,
    chord_lengths: bool,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(scales (N, 3), opacities (N,), colours (N, 1)) of scalar Gaussians under ``transfer``, as
    ``ScalarGaussians.scales``, ``opacities`` and ``colours`` give them, differentiable in the
    quaternions, log scales, value logits and log lengths. CPU tensors; chord lengths need
    ``camera_centre``."""
    with_chord = chord_lengths and camera_centre is not None
    dtype = log_scales.dtype
    variances = smoothing if smoothing is not None else torch.zeros(0, dtype=dtype)
    centre = camera_centre if with_chord else torch.zeros(3)
    flags = np.array([smoothing is not None, with_chord])
    parameters = np.array(transfer.march_parameters(), dtype=np.float64)
    return _ScalarAppearance.apply(
        means.detach().to(dtype),
        quaternions.to(dtype),
        log_scales,
        value_logits.to(dtype),
        log_lengths.to(dtype),
        variances.detach().to(dtype),
        centre.detach().to(dtype),
        parameters,
        flags,
    )
