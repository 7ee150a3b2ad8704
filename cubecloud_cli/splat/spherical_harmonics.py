"""View-dependent colour from real spherical harmonics, in the basis and sign convention of the
reference 3DGS code (docs/references.md §1.5), so coefficients trained here mean the same there.

colour = max(Σ_l Σ_m c_lm Y_lm(direction) + 0.5, 0), direction = unit(mean − camera centre).
"""

from __future__ import annotations

import torch

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
MAX_DEGREE = 3


def coefficient_count(degree: int) -> int:
    return (degree + 1) ** 2


def rgb_to_sh(colour: torch.Tensor) -> torch.Tensor:
    """The degree-0 coefficient that renders ``colour`` (3DGS ``RGB2SH``)."""
    return (colour - 0.5) / SH_C0


def sh_to_colour(coefficients: torch.Tensor, directions: torch.Tensor | None, degree: int) -> torch.Tensor:
    """(N, K, C) coefficients and (N, 3) view directions → (N, C) colours ≥ 0.

    Only the first (degree + 1)² coefficients are used; degree 0 needs no directions.
    """
    result = SH_C0 * coefficients[:, 0]
    if degree > 0:
        d = directions / directions.norm(dim=1, keepdim=True).clamp_min(1e-12)
        x, y, z = (d[:, i : i + 1] for i in range(3))
        sh = coefficients
        result = result - SH_C1 * y * sh[:, 1] + SH_C1 * z * sh[:, 2] - SH_C1 * x * sh[:, 3]
        if degree > 1:
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            result = (
                result
                + SH_C2[0] * xy * sh[:, 4]
                + SH_C2[1] * yz * sh[:, 5]
                + SH_C2[2] * (2.0 * zz - xx - yy) * sh[:, 6]
                + SH_C2[3] * xz * sh[:, 7]
                + SH_C2[4] * (xx - yy) * sh[:, 8]
            )
            if degree > 2:
                result = (
                    result
                    + SH_C3[0] * y * (3.0 * xx - yy) * sh[:, 9]
                    + SH_C3[1] * xy * z * sh[:, 10]
                    + SH_C3[2] * y * (4.0 * zz - xx - yy) * sh[:, 11]
                    + SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh[:, 12]
                    + SH_C3[4] * x * (4.0 * zz - xx - yy) * sh[:, 13]
                    + SH_C3[5] * z * (xx - yy) * sh[:, 14]
                    + SH_C3[6] * x * (xx - 3.0 * yy) * sh[:, 15]
                )
    return (result + 0.5).clamp_min(0.0)
