"""A direction in a Gaussian's own axes, and the gradient through that rotation to its raw
quaternion, inlined into the per-Gaussian numba kernels of a scalar scene (the chord ratio,
``splat/chord.py``, also inside ``splat/scalar_appearance.py``; the scan's spread over a
Gaussian, ``splat/value_spread.py``).

The quaternion q = (w, x, y, z) is unit (the kernels divide the raw one by its length first) and
R its rotation, whose columns are the Gaussian's axes. ``local`` is l = Rᵀd. Given the gradient
h = ∂f/∂l of some f(l), ``raw_quaternion_gradient`` gives ∂f/∂u for the raw quaternion u = |u| q:
through R's entries (∂l_j/∂R_kj = d_k), to q, then through the normalisation.

After editing this file, touch the kernels' files (``splat/chord.py``, ``splat/value_spread.py``,
``splat/scalar_appearance.py``): numba's cache checks only the file of the kernel it caches
(``numerics/jit.py``).
"""

from __future__ import annotations

from numba import njit


@njit(inline="always")
def local(dx, dy, dz, w, x, y, z):
    """Rᵀd: ``d`` in the Gaussian's own axes."""
    l0 = (1 - 2 * (y * y + z * z)) * dx + 2 * (x * y + w * z) * dy + 2 * (x * z - w * y) * dz
    l1 = 2 * (x * y - w * z) * dx + (1 - 2 * (x * x + z * z)) * dy + 2 * (y * z + w * x) * dz
    l2 = 2 * (x * z + w * y) * dx + 2 * (y * z - w * x) * dy + (1 - 2 * (x * x + y * y)) * dz
    return l0, l1, l2


@njit(inline="always")
def raw_quaternion_gradient(dx, dy, dz, h0, h1, h2, w, x, y, z, length_q):
    """∂f/∂u for the raw quaternion u of length ``length_q``, from h = ∂f/∂l at l = Rᵀd."""
    g00, g01, g02 = dx * h0, dx * h1, dx * h2
    g10, g11, g12 = dy * h0, dy * h1, dy * h2
    g20, g21, g22 = dz * h0, dz * h1, dz * h2
    gw = 2 * (-z * g01 + y * g02 + z * g10 - x * g12 - y * g20 + x * g21)
    gx = 2 * (y * g01 + z * g02 + y * g10 - 2 * x * g11 - w * g12 + z * g20 + w * g21 - 2 * x * g22)
    gy = 2 * (-2 * y * g00 + x * g01 + w * g02 + x * g10 + z * g12 - w * g20 + z * g21 - 2 * y * g22)
    gz = 2 * (-2 * z * g00 - w * g01 + x * g02 + w * g10 - 2 * z * g11 + y * g12 + x * g20 + y * g21)
    along = w * gw + x * gx + y * gy + z * gz  # through the normalisation q = u / |u|
    return (
        (gw - w * along) / length_q,
        (gx - x * along) / length_q,
        (gy - y * along) / length_q,
        (gz - z * along) / length_q,
    )
