"""Every constant of the Gaussian rasterizer, in one place: the PyTorch reference, the numba
kernels and the pair lists all read them from here, so the backends cannot drift apart.
Values are the reference 3DGS CUDA rasterizer's unless said otherwise (docs/references.md)."""

from __future__ import annotations

# Projection
NEAR_PLANE = 0.2  # Gaussians nearer than this (camera z, world units) are culled, as the reference
DILATION = 0.3  # px² added to every 2D covariance: plain 3DGS's low-pass filter
MIP_FILTER_VARIANCE = 0.1  # px², Mip-Splatting's 2D filter, used instead of DILATION when anti-aliased
MIN_COMPENSATION = 0.005  # floor of the opacity compensation ρ, as the antialiased 3DGS and gsplat's torch reference
FRUSTUM_CLAMP = 1.3  # view-space x/z and y/z clamped to 1.3 × the half field of view before the Jacobian
MIN_DETERMINANT = 1e-12  # a 2D covariance determinant is floored here so the conic stays finite
EIGENVALUE_FLOOR = 0.1  # px²: the radius uses sqrt(max(middle² − det, 0.1)), as the reference
MIN_QUATERNION_NORM = 1e-12  # a zero quaternion normalises to this length instead of dividing by 0

# Compositing
MAX_ALPHA = 0.99  # α is capped so that 1 − α ≥ 0.01 and the backward pass can divide by it
MIN_ALPHA = 1.0 / 255.0  # contributions below one 8-bit level are skipped
TRANSMITTANCE_STOP = 1e-4  # a pixel stops before the Gaussian that would take T below this

# CPU binning
TILE = 16  # pixels per tile side, as the reference's 16 × 16 blocks
TILE_SHIFT = 4  # log2(TILE)
ALPHA_LEVEL_SCALE = 255.0  # α ≥ 1/255 ⇔ power ≤ ln(255·o): the box a Gaussian covers is cut there
