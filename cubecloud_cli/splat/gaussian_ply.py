"""Trained Gaussians as a PLY in the reference 3DGS layout (docs/references.md §1.6), which common
splat viewers open: x y z nx ny nz f_dc_0..2 f_rest_0.. opacity scale_0..2 rot_0..3, all float32,
pre-activation (log scales, logit opacity, raw w-first quaternions), f_rest channel-major.

Viewers expect three colour channels, so a grey (C = 1) model is written with its coefficients
in all three, and a comment records that; reading such a file gives C = 1 back.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.splat.gaussians import Gaussians

GREY_COMMENT = "cubecloud channels 1"


def attribute_names(sh_degree: int) -> list[str]:
    rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def write_gaussians_ply(path: Path, gaussians: Gaussians) -> None:
    count, coefficients = len(gaussians), gaussians.sh.shape[1]
    sh = gaussians.sh.detach().cpu().float()
    if gaussians.channels == 1:
        sh = sh.repeat(1, 1, 3)
    columns = [
        gaussians.means.detach().cpu().float().numpy(),
        np.zeros((count, 3), dtype=np.float32),
        sh[:, 0, :].numpy(),
        sh[:, 1:, :].transpose(1, 2).reshape(count, 3 * (coefficients - 1)).numpy(),  # channel-major
        gaussians.opacity_logits.detach().cpu().float().numpy()[:, None],
        gaussians.log_scales.detach().cpu().float().numpy(),
        gaussians.quaternions.detach().cpu().float().numpy(),
    ]
    values = np.concatenate(columns, axis=1).astype(np.float32)
    names = attribute_names(gaussians.sh_degree)
    vertices = np.empty(count, dtype=[(name, "f4") for name in names])
    for index, name in enumerate(names):
        vertices[name] = values[:, index]
    comments = [GREY_COMMENT] if gaussians.channels == 1 else []
    PlyData([PlyElement.describe(vertices, "vertex")], comments=comments).write(str(path))


def read_gaussians_ply(path: Path) -> Gaussians:
    """Read a reference-layout PLY (ours or another trainer's), by property name as 3DGS does."""
    try:
        data = PlyData.read(str(path))
        vertex = data["vertex"]
    except FileNotFoundError:
        raise CubecloudError(f"{path} does not exist: train it with `cubecloud splat`") from None
    except Exception as exc:
        raise CubecloudError(f"{path} is not a readable PLY ({type(exc).__name__}): train it again") from None
    names = [p.name for p in vertex.properties]
    rest = sorted((n for n in names if n.startswith("f_rest_")), key=lambda n: int(n.split("_")[-1]))
    coefficients = len(rest) // 3 + 1
    degree = int(round(coefficients**0.5)) - 1
    required = [
        "x",
        "y",
        "z",
        "f_dc_0",
        "f_dc_1",
        "f_dc_2",
        "opacity",
        "scale_0",
        "scale_1",
        "scale_2",
        "rot_0",
        "rot_1",
        "rot_2",
        "rot_3",
    ]
    missing = [n for n in required if n not in names]
    if missing or len(rest) != 3 * ((degree + 1) ** 2 - 1):
        raise CubecloudError(f"{path} is not a 3DGS Gaussian PLY (missing {', '.join(missing) or 'SH coefficients'})")

    def column(*keys: str) -> torch.Tensor:
        return torch.from_numpy(np.stack([np.asarray(vertex[k], dtype=np.float32) for k in keys], axis=1))

    count = len(vertex["x"])
    dc = column("f_dc_0", "f_dc_1", "f_dc_2")
    sh_rest = column(*rest).reshape(count, 3, coefficients - 1).transpose(1, 2) if rest else torch.zeros(count, 0, 3)
    sh = torch.cat([dc[:, None, :], sh_rest], dim=1)
    if GREY_COMMENT in data.comments:
        sh = sh[:, :, :1]
    return Gaussians(
        column("x", "y", "z"),
        column("scale_0", "scale_1", "scale_2"),
        column("rot_0", "rot_1", "rot_2", "rot_3"),
        column("opacity")[:, 0],
        sh[:, :1].contiguous(),
        sh[:, 1:].contiguous(),
    )
