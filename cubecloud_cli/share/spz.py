"""Gaussians as an SPZ file (Niantic's compressed splat format, version 3), written and read by our
own code; tests read what we write with an independent reader (gsply).

The format (github.com/nianticlabs/spz): a gzip stream of a 16-byte header (magic "NGSP", version,
count, SH degree, the positions' fractional bits, flags with bit 0 "anti-aliased", a reserved
byte), then each attribute for every Gaussian in turn: positions as 24-bit signed fixed point,
opacity as 8 bits, the SH DC colour as 8 bits per channel (0.15 per unit around ½), log scales as
8 bits (1/16 per step from −10), rotations as the three smallest quaternion components in 10 bits
each (9 of magnitude, 1 of sign) under the largest one's index. About 16 bytes a Gaussian before
gzip; what each quantization costs a render is measured in bench/share_formats.py.

The Gaussians go in as drawn: the 3D smoothing filter folded into scales and opacities
(``Gaussians.baked``), since no web viewer knows of it, and in cubecloud's world frame (the cube
[−1, 1]³, docs/design.md §2); the page maps that frame to the scanner's millimetres.
"""

from __future__ import annotations

import gzip
import math
import struct
from dataclasses import dataclass

import numpy as np
import torch

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.splat.gaussians import MIN_BAKED_OPACITY, Gaussians

MAGIC = 0x5053474E  # "NGSP", little-endian
VERSION = 3
HEADER = struct.Struct("<IIIBBBB")
FLAG_ANTIALIASED = 0x1
COLOUR_SCALE = 0.15  # SH DC units per unit of the stored byte / 255, around ½
LOG_SCALE_OFFSET = 10.0
LOG_SCALE_STEPS = 16.0  # stored byte = (log scale + 10) · 16
SMALLEST_THREE_BITS = 9  # magnitude bits of each of the three smallest quaternion components
# Fractional bits of the positions: 2⁻¹⁶ world units is 1/512 of a voxel of a 256³ cube, and 24
# bits then reach ±128 world units, far past the cube [−1, 1]³ and any Gaussian trained in it.
FRACTIONAL_BITS = 16
GZIP_LEVEL = 9


@dataclass(frozen=True)
class SpzScene:
    gaussians: Gaussians  # degree-0 SH, 3 channels (SPZ stores RGB), no 3D filter
    antialiased: bool
    fractional_bits: int


def _quantize(values: np.ndarray, low: int, high: int) -> np.ndarray:
    """Round to the nearest integer in [low, high]; NaN (guarded by the caller) would be 0."""
    return np.clip(np.rint(np.nan_to_num(values)), low, high)


def positions_bytes(means: np.ndarray, fractional_bits: int) -> bytes:
    """(N, 3) positions as 24-bit little-endian two's complement fixed point, x y z per Gaussian."""
    limit = 1 << 23
    fixed = _quantize(means.astype(np.float64) * (1 << fractional_bits), -limit, limit - 1).astype(np.int64)
    unsigned = (fixed & 0xFFFFFF).astype(np.uint32).reshape(-1)
    packed = np.stack([(unsigned >> shift) & 0xFF for shift in (0, 8, 16)], axis=1).astype(np.uint8)
    return packed.tobytes()


def smallest_three(quaternions_xyzw: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (x, y, z, w), any length, as SPZ v3's uint32 words: the largest
    component's index in the top 2 bits, then the other three from the lowest index up, each 9
    bits of |q|·√2 and a sign bit, with the highest index in the lowest bits. A quaternion and its
    negation are one rotation, so the largest component is made positive and not stored."""
    q = quaternions_xyzw.astype(np.float64)
    norms = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(norms > 0.0, q / np.where(norms > 0.0, norms, 1.0), np.array([0.0, 0.0, 0.0, 1.0]))
    largest = np.argmax(np.abs(q), axis=1)
    q *= np.where(q[np.arange(len(q)), largest] < 0.0, -1.0, 1.0)[:, None]
    steps = (1 << SMALLEST_THREE_BITS) - 1
    words = np.zeros(len(q), dtype=np.uint64)
    for index in range(4):
        magnitude = _quantize(np.abs(q[:, index]) * math.sqrt(2.0) * steps, 0, steps).astype(np.uint64)
        sign = (q[:, index] < 0.0).astype(np.uint64)
        component = (sign << np.uint64(SMALLEST_THREE_BITS)) | magnitude
        skip = largest == index
        words = np.where(skip, words, (words << np.uint64(10)) | component)
    words |= largest.astype(np.uint64) << np.uint64(30)
    return words.astype(np.uint32)


def encode_spz(gaussians: Gaussians, antialiased: bool, fractional_bits: int = FRACTIONAL_BITS) -> bytes:
    """The SPZ bytes (gzip-compressed) of ``gaussians`` as they are drawn, SH degree 0."""
    drawn = gaussians.baked()
    count = len(drawn)
    with torch.no_grad():
        means = drawn.means.double().numpy()
        log_scales = drawn.log_scales.double().numpy()
        opacities = torch.sigmoid(drawn.opacity_logits.double()).numpy()
        dc = drawn.sh_dc[:, 0, :].double().numpy()
        quaternions = drawn.quaternions.double().numpy()  # (w, x, y, z), as the PLY
    if dc.shape[1] == 1:
        dc = np.repeat(dc, 3, axis=1)
    finite = all(np.isfinite(a).all() for a in (means, log_scales, opacities, dc, quaternions))
    if not finite:
        raise CubecloudError("the Gaussians hold NaN or Inf: retrain them with `cubecloud splat WORK --force`")
    header = HEADER.pack(MAGIC, VERSION, count, 0, fractional_bits, FLAG_ANTIALIASED if antialiased else 0, 0)
    alphas = _quantize(opacities * 255.0, 0, 255).astype(np.uint8)
    colours = _quantize((dc * COLOUR_SCALE + 0.5) * 255.0, 0, 255).astype(np.uint8)
    scales = _quantize((log_scales + LOG_SCALE_OFFSET) * LOG_SCALE_STEPS, 0, 255).astype(np.uint8)
    rotations = smallest_three(np.concatenate([quaternions[:, 1:], quaternions[:, :1]], axis=1))
    body = b"".join(
        [
            header,
            positions_bytes(means, fractional_bits),
            alphas.tobytes(),
            colours.tobytes(),
            scales.tobytes(),
            rotations.astype("<u4").tobytes(),
        ]
    )
    return gzip.compress(body, compresslevel=GZIP_LEVEL, mtime=0)


def _unpack_smallest_three(words: np.ndarray) -> np.ndarray:
    """(N, 4) unit quaternions (x, y, z, w) of SPZ v3 rotation words."""
    words = words.astype(np.uint64)
    largest = (words >> np.uint64(30)).astype(np.int64)
    steps = (1 << SMALLEST_THREE_BITS) - 1
    q = np.zeros((len(words), 4))
    rest = words.copy()
    for index in (3, 2, 1, 0):
        take = largest != index
        magnitude = (rest & np.uint64(steps)).astype(np.float64) / steps / math.sqrt(2.0)
        sign = np.where((rest >> np.uint64(SMALLEST_THREE_BITS)) & np.uint64(1), -1.0, 1.0)
        q[:, index] = np.where(take, sign * magnitude, 0.0)
        rest = np.where(take, rest >> np.uint64(10), rest)
    q[np.arange(len(q)), largest] = np.sqrt(np.maximum(1.0 - (q**2).sum(axis=1), 0.0))
    return q


def decode_spz(data: bytes) -> SpzScene:
    """Gaussians from SPZ bytes of version 3, SH degree 0 (what ``encode_spz`` writes)."""
    try:
        body = gzip.decompress(data)
    except (OSError, EOFError, ValueError) as exc:
        raise CubecloudError(f"not an SPZ file: its gzip stream is damaged ({exc})") from None
    if len(body) < HEADER.size:
        raise CubecloudError("not an SPZ file: shorter than its header")
    magic, version, count, degree, bits, flags, _ = HEADER.unpack_from(body)
    if magic != MAGIC or version != VERSION or degree != 0:
        raise CubecloudError(f"not an SPZ version-3 degree-0 file (magic {magic:#x}, version {version}, SH {degree})")
    expected = HEADER.size + count * (9 + 1 + 3 + 3 + 4)
    if len(body) != expected:
        raise CubecloudError(f"SPZ body holds {len(body)} bytes where {count} Gaussians need {expected}")
    offset = HEADER.size

    def take(size: int) -> np.ndarray:
        nonlocal offset
        chunk = np.frombuffer(body, dtype=np.uint8, count=size, offset=offset)
        offset += size
        return chunk

    raw = take(count * 9).reshape(count, 3, 3).astype(np.int64)
    fixed = raw[:, :, 0] | (raw[:, :, 1] << 8) | (raw[:, :, 2] << 16)
    fixed = np.where(fixed >= 1 << 23, fixed - (1 << 24), fixed)
    means = fixed / float(1 << bits)
    alphas = take(count).astype(np.float64) / 255.0
    dc = (take(count * 3).reshape(count, 3).astype(np.float64) / 255.0 - 0.5) / COLOUR_SCALE
    log_scales = take(count * 3).reshape(count, 3).astype(np.float64) / LOG_SCALE_STEPS - LOG_SCALE_OFFSET
    xyzw = _unpack_smallest_three(take(count * 4).view("<u4"))
    opacities = np.clip(alphas, MIN_BAKED_OPACITY, 1.0 - MIN_BAKED_OPACITY)
    gaussians = Gaussians(
        torch.from_numpy(means).float(),
        torch.from_numpy(log_scales).float(),
        torch.from_numpy(np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)).float(),
        torch.from_numpy(np.log(opacities) - np.log1p(-opacities)).float(),
        torch.from_numpy(dc[:, None, :]).float(),
        torch.zeros(count, 0, 3),
    )
    return SpzScene(gaussians, bool(flags & FLAG_ANTIALIASED), bits)
