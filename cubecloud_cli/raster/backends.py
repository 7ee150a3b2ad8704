"""One rasterization call, three implementations: which runs depends on the device.

* ``numba``: the CPU kernels (``cpu/``), projection and compositing with hand-written backwards;
* ``gsplat``: gsplat's CUDA rasterizer, on a CUDA device when gsplat is installed;
* ``torch``: the plain PyTorch path (``projection.py`` + ``pairs.py``), on any device.

All three take the same Gaussians and pinhole pose (OpenCV/COLMAP world-to-camera, principal point
at the image centre, pixel centres at +0.5). ``numba`` and ``torch`` follow the reference 3DGS
rules exactly (0.3 px² dilation, α ≤ 0.99, α < 1/255 skipped, stop before T < 1e-4) and agree to
rounding; with ``antialias`` all three apply Mip-Splatting's 2D filter (``projection.py``). gsplat differs in small ways of its own: α is capped at 0.999, a pixel stops at
T ≤ 1e-4, and from version 1.5 boxes are opacity-aware (up to 3.33σ) and Gaussians with opacity
below 1/255 are culled; a model trained with one renders nearly, not exactly, the same with it.
Training reads the screen-space gradient of the means for densification, in pixels on every
backend.
"""

from __future__ import annotations

import functools
import importlib.util
import logging
from dataclasses import dataclass
from typing import Callable

import torch

from cubecloud_cli.raster.pairs import composite
from cubecloud_cli.raster.projection import NEAR_PLANE, dilation, project

log = logging.getLogger("cubecloud")


@dataclass
class Rasterized:
    image: torch.Tensor  # (H, W, C)
    radii: torch.Tensor  # (N,) > 0 where the Gaussian was drawn
    screen_means: torch.Tensor  # (N, 2) pixel positions, or gsplat's (1, N, 2)

    def screen_gradient(self) -> torch.Tensor | None:
        """(N, 2) gradient of the loss with respect to the pixel positions of the means, after
        ``backward`` (``retain_screen_grad=True``), or None."""
        grad = self.screen_means.grad
        return None if grad is None else grad.reshape(-1, 2)


RenderFunction = Callable[..., Rasterized]


@dataclass(frozen=True)
class Rasterizer:
    name: str
    description: str
    render: RenderFunction


def _render_with(projector, compositor):
    def render(
        means,
        scales,
        quaternions,
        opacities,
        colours,
        rotation,
        translation,
        focal,
        width,
        height,
        background=None,
        retain_screen_grad=False,
        antialias=False,
    ) -> Rasterized:
        projected = projector(
            means, scales, quaternions, rotation, translation, focal, width, height, antialias=antialias
        )
        if retain_screen_grad and projected.means2d.requires_grad:
            projected.means2d.retain_grad()
        image, _ = compositor(projected, colours, projected.effective_opacities(opacities), width, height, background)
        return Rasterized(image, projected.radii, projected.means2d)

    return render


def _render_numba(*args, **kwargs) -> Rasterized:
    from cubecloud_cli.raster.cpu.autograd import composite_cpu, project_cpu

    return _render_with(project_cpu, composite_cpu)(*args, **kwargs)


def gsplat_inputs(rotation: torch.Tensor, translation: torch.Tensor, focal: float, width: int, height: int):
    """Our pose as gsplat's (1, 4, 4) world-to-camera ``viewmats`` and (1, 3, 3) intrinsics ``Ks``."""
    viewmat = torch.eye(4, dtype=rotation.dtype, device=rotation.device)
    viewmat[:3, :3] = rotation
    viewmat[:3, 3] = translation
    intrinsics = torch.tensor(
        [[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]],
        dtype=rotation.dtype,
        device=rotation.device,
    )
    return viewmat[None], intrinsics[None]


def _render_gsplat(
    means,
    scales,
    quaternions,
    opacities,
    colours,
    rotation,
    translation,
    focal,
    width,
    height,
    background=None,
    retain_screen_grad=False,
    antialias=False,
) -> Rasterized:
    import gsplat

    viewmats, intrinsics = gsplat_inputs(rotation, translation, focal, width, height)
    # gsplat's antialiased mode is the 2D Mip filter: eps2d added, opacity × √(det Σ / det(Σ + eps2d·I)).
    colours_out, _, meta = gsplat.rasterization(
        means,
        quaternions,
        scales,
        opacities,
        colours,
        viewmats,
        intrinsics,
        width,
        height,
        near_plane=NEAR_PLANE,
        eps2d=dilation(antialias),
        packed=False,
        rasterize_mode="antialiased" if antialias else "classic",
        backgrounds=None if background is None else background[None],
    )
    screen_means = meta["means2d"]
    if retain_screen_grad and screen_means.requires_grad:
        screen_means.retain_grad()
    radii = meta["radii"].reshape(means.shape[0], -1).amax(dim=1)  # newer gsplat gives x and y radii
    return Rasterized(colours_out[0], radii, screen_means)


@functools.cache
def gsplat_available() -> bool:
    """Whether gsplat is installed and its CUDA kernels load. gsplat compiles them at its first
    import (75 s on 16 cores of an H200 machine, docs/gpu.md); without a CUDA toolkit it leaves
    them out, and a failed build raises whatever the compiler said. Either way the PyTorch path
    draws instead, and the user is told why."""
    if importlib.util.find_spec("gsplat") is None:
        return False
    try:
        from gsplat.cuda._backend import _C
    except ModuleNotFoundError as error:
        if (error.name or "").startswith("gsplat"):  # its private layout moved: rasterization() decides
            return True
        log.warning(f"gsplat cannot load ({error}); using plain PyTorch")
        return False
    except Exception as error:  # noqa: BLE001 (a build failure may be any exception)
        log.warning(f"gsplat's CUDA kernels did not build ({error}); using plain PyTorch")
        return False
    if _C is None:
        log.warning("gsplat found no CUDA toolkit to build its kernels; using plain PyTorch")
    return _C is not None


NUMBA = Rasterizer("numba", "numba CPU kernels", _render_numba)
GSPLAT = Rasterizer("gsplat", "gsplat CUDA kernels", _render_gsplat)
TORCH = Rasterizer("torch", "plain PyTorch", _render_with(project, composite))


def rasterizer_for(device: torch.device) -> Rasterizer:
    """numba on the CPU; gsplat on CUDA when installed; otherwise the plain PyTorch path."""
    if device.type == "cpu":
        return NUMBA
    if device.type == "cuda" and gsplat_available():
        return GSPLAT
    return TORCH
