"""Trained Gaussians as a PLY in the reference 3DGS layout (docs/references.md §1.6), which common
splat viewers open: x y z nx ny nz f_dc_0..2 f_rest_0.. opacity scale_0..2 rot_0..3, all float32,
pre-activation (log scales, logit opacity, raw w-first quaternions), f_rest channel-major.

Viewers expect three colour channels, so a grey (C = 1) model is written with its coefficients
in all three, and a comment records that; reading such a file gives C = 1 back.

A scalar scene (``--scalar``) is written in that layout as drawn under its training transfer
function, so every splat viewer opens it, plus the columns a viewer that knows them uses to draw
it under any other: ``scan_value`` (the value in [0, 1]), ``log_optical_length`` (log ℓ, world
units) and ``filter_attenuation`` (what the 3D filter, folded into the scales, leaves of every
opacity); comments record the transfer functions, as JSON, and whether ℓ is scaled by the
Gaussian's chord along each ray (``splat/chord.py``; the reference columns then hold r's mean over
the sphere).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.splat.gaussians import Gaussians
from cubecloud_cli.splat.scalar_gaussians import VALUE_MARGIN, ScalarGaussians
from cubecloud_cli.transfer.function import TransferFunction

GREY_COMMENT = "cubecloud channels 1"
SCAN_VALUE = "scan_value"
LOG_OPTICAL_LENGTH = "log_optical_length"
FILTER_ATTENUATION = "filter_attenuation"
DRAWN_UNDER = "cubecloud drawn under "  # the transfer function of the reference columns
TRAINED_UNDER = "cubecloud trained under "  # every transfer function the scene was trained under
CHORD_LENGTHS = "cubecloud optical length times the chord ratio along the ray"


@dataclass
class ScalarProperties:
    """What a scalar scene's PLY carries beyond the reference layout."""

    values: np.ndarray  # (N,) float32 in (0, 1)
    log_lengths: np.ndarray  # (N,) float32
    attenuation: np.ndarray  # (N,) float32 in (0, 1]
    drawn_under: TransferFunction
    trained_under: list[TransferFunction]
    chord_lengths: bool = False


def scalar_properties(gaussians: ScalarGaussians) -> ScalarProperties:
    with torch.no_grad():
        values = gaussians.values().cpu().float().numpy()
        log_lengths = gaussians.log_lengths.detach().cpu().float().numpy()
        attenuation = gaussians.filter_attenuation().detach().cpu().float().numpy()
    trained_under = list(gaussians.transfers or [gaussians.transfer])
    return ScalarProperties(
        values, log_lengths, attenuation, gaussians.transfer, trained_under, gaussians.chord_lengths
    )


def attribute_names(sh_degree: int) -> list[str]:
    rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def write_gaussians_ply(path: Path, gaussians: Gaussians, scalar: ScalarProperties | None = None) -> None:
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
    names = attribute_names(gaussians.sh_degree)
    comments = [GREY_COMMENT] if gaussians.channels == 1 else []
    if scalar is not None:
        columns += [scalar.values.reshape(count, 1), scalar.log_lengths.reshape(count, 1)]
        columns += [scalar.attenuation.reshape(count, 1)]
        names += [SCAN_VALUE, LOG_OPTICAL_LENGTH, FILTER_ATTENUATION]
        comments += [
            DRAWN_UNDER + json.dumps(scalar.drawn_under.as_dict()),
            TRAINED_UNDER + json.dumps([t.as_dict() for t in scalar.trained_under]),
            *([CHORD_LENGTHS] if scalar.chord_lengths else []),
        ]
    values = np.concatenate(columns, axis=1).astype(np.float32)
    vertices = np.empty(count, dtype=[(name, "f4") for name in names])
    for index, name in enumerate(names):
        vertices[name] = values[:, index]
    PlyData([PlyElement.describe(vertices, "vertex")], comments=comments).write(str(path))


def _read_ply(path: Path) -> PlyData:
    """The PLY at ``path`` with a vertex element, or a one-line error that says what to do."""
    try:
        data = PlyData.read(str(path))
        data["vertex"]
    except FileNotFoundError:
        raise CubecloudError(f"{path} does not exist: train it with `cubecloud splat`") from None
    except Exception as exc:  # plyfile raises many types for a damaged file
        raise CubecloudError(f"{path} is not a readable PLY ({type(exc).__name__}): train it again") from None
    return data


def read_gaussians_ply(path: Path) -> Gaussians:
    """Read a reference-layout PLY (ours or another trainer's), by property name as 3DGS does."""
    return _gaussians(_read_ply(path), path)


def _gaussians(data: PlyData, path: Path) -> Gaussians:
    vertex = data["vertex"]
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


def read_scalar_properties(path: Path) -> ScalarProperties | None:
    """The scalar columns and transfer functions of a scalar scene's PLY; None for any other PLY."""
    return _scalar_properties(_read_ply(path), path)


def _scalar_properties(data: PlyData, path: Path) -> ScalarProperties | None:
    vertex = data["vertex"]
    names = {p.name for p in vertex.properties}
    drawn = [c[len(DRAWN_UNDER) :] for c in data.comments if c.startswith(DRAWN_UNDER)]
    trained = [c[len(TRAINED_UNDER) :] for c in data.comments if c.startswith(TRAINED_UNDER)]
    if not {SCAN_VALUE, LOG_OPTICAL_LENGTH, FILTER_ATTENUATION} <= names or not drawn:
        return None
    try:
        drawn_under = TransferFunction.from_dict(json.loads(drawn[0]))
        trained_under = [TransferFunction.from_dict(t) for t in json.loads(trained[0])] if trained else [drawn_under]
        for function in (drawn_under, *trained_under):
            function.validate()
    except (ValueError, TypeError) as exc:
        raise CubecloudError(f"{path} records a transfer function that is not one ({exc}): train it again") from None
    values = np.asarray(vertex[SCAN_VALUE], dtype=np.float32)
    log_lengths = np.asarray(vertex[LOG_OPTICAL_LENGTH], dtype=np.float32)
    attenuation = np.asarray(vertex[FILTER_ATTENUATION], dtype=np.float32)
    if not all(np.isfinite(a).all() for a in (values, log_lengths, attenuation)):
        raise CubecloudError(f"{path} holds NaN or Inf scan values, optical lengths or attenuations: train it again")
    return ScalarProperties(
        values, log_lengths, attenuation, drawn_under, trained_under, CHORD_LENGTHS in data.comments
    )


def read_scalar_gaussians(path: Path) -> ScalarGaussians | None:
    """A scalar scene as trained (the 3D filter folded in), ready to draw under any transfer
    function; None for a PLY that is not one."""
    model = read_splat_ply(path)
    return model if isinstance(model, ScalarGaussians) else None


def read_splat_ply(path: Path) -> Gaussians | ScalarGaussians:
    """A trained scene from one read of its PLY: a scalar scene's model when it has the scalar
    columns, else the reference layout's Gaussians."""
    data = _read_ply(path)
    reference = _gaussians(data, path)
    scalar = _scalar_properties(data, path)
    if scalar is None:
        return reference
    values = torch.from_numpy(np.clip(scalar.values, VALUE_MARGIN, 1.0 - VALUE_MARGIN))
    return ScalarGaussians(
        reference.means,
        reference.log_scales,
        reference.quaternions,
        torch.logit(values),
        torch.from_numpy(scalar.log_lengths),
        scalar.drawn_under,
        scalar.trained_under,
        opacity_scale=torch.from_numpy(np.clip(scalar.attenuation, 0.0, 1.0)),
        chord_lengths=scalar.chord_lengths,
    )
