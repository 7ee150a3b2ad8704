"""The transfer functions a scalar scene is trained under, and those it is tested under.

A scalar scene must render tissue it was never shown, so it is trained under a set: the
export's own transfer function first, then the presets eval does not hold out, then seeded
random bands and ramps over the value range, by turns, their ends and density drawn so that the
set covers faint and opaque, narrow and wide. A band shows the values inside it with nothing in
front from outside it, so every value range is seen unhidden under some member of the set. eval
holds out other presets and ramps of another seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cubecloud_cli.transfer.function import TransferFunction
from cubecloud_cli.transfer.tissue_presets import TRANSFER_PRESETS, clipped_away, resolve_transfer

# Shown to no training run, so that eval's scores on them measure transfer functions never seen.
HELD_OUT_PRESETS = ("bone", "lung", "vessels")
RANDOM_RAMP = "ramp"
# Ramps start in [0.02, 0.9] of the value range, are 0.02 to 0.6 wide and 1 to 30 per world unit
# dense (log-uniform: as many narrow as wide, as many faint as opaque).
RAMP_START = (0.02, 0.9)
RAMP_WIDTH = (0.02, 0.6)
RAMP_DENSITY = (1.0, 30.0)
# A band's top is 0.02 to 0.3 wide, and it rises and falls over 0.005 to 0.1.
BAND_TOP = (0.02, 0.3)
BAND_SIDE = (0.005, 0.1)
RANDOM_BAND = "band"
TILED_BAND = "tiled-band"
# Half the members past the presets tile the value range; the sides, tops and densities of
# consecutive tiles cycle through these, so that each stretch of the range sees a narrow and a
# wide rise, a narrow and a wide top, and a faint, a middling and an opaque density.
TILED_SHARE = 0.5
TILE_SIDES = (0.01, 0.04)
TILE_TOPS = (0.05, 0.15)
TILE_DENSITIES = (2.0, 6.0, 18.0)
HELD_OUT_SEED_OFFSET = 1_000_003  # eval's ramps come from a stream no training seed reaches
HELD_OUT_WINDOW_SEED_OFFSET = HELD_OUT_SEED_OFFSET + 7  # and its extra bands and ramps from a third
HELD_OUT_WINDOW = "held-out-window"


@dataclass(frozen=True)
class NamedTransfer:
    name: str  # a preset's name, or ramp-N for a seeded random ramp
    function: TransferFunction


def _log_uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    return math.exp(rng.uniform(math.log(bounds[0]), math.log(bounds[1])))


def random_ramps(count: int, seed: int) -> list[NamedTransfer]:
    """``count`` seeded random ramps over the value range."""
    rng = np.random.default_rng(seed)
    ramps = []
    for index in range(count):
        low = float(rng.uniform(*RAMP_START))
        width, density = _log_uniform(rng, RAMP_WIDTH), _log_uniform(rng, RAMP_DENSITY)
        ramps.append(NamedTransfer(f"{RANDOM_RAMP}-{index}", TransferFunction(low, min(1.0, low + width), density)))
    return ramps


def random_windows(count: int, seed: int) -> list[NamedTransfer]:
    """``count`` seeded random transfer functions over the value range: bands and ramps by turns."""
    rng = np.random.default_rng(seed)
    windows = []
    for index in range(count):
        low = float(rng.uniform(*RAMP_START))
        density = _log_uniform(rng, RAMP_DENSITY)
        if index % 2 == 0:
            high = min(1.0, low + _log_uniform(rng, BAND_SIDE))
            fall_low = min(1.0, high + _log_uniform(rng, BAND_TOP))
            fall_high = min(1.0, fall_low + _log_uniform(rng, BAND_SIDE))
            function = TransferFunction(low, high, density, fall_low, fall_high)
            windows.append(NamedTransfer(f"{RANDOM_BAND}-{index}", function))
        else:
            high = min(1.0, low + _log_uniform(rng, RAMP_WIDTH))
            windows.append(NamedTransfer(f"{RANDOM_RAMP}-{index}", TransferFunction(low, high, density)))
    return windows


def tiled_bands(count: int) -> list[NamedTransfer]:
    """``count`` bands whose rises start evenly over RAMP_START, both ends included; tile k takes
    the k-th side (mod 2), top (the k // 2-th, mod 2) and density (mod 3) of the cycles above."""
    bands = []
    for index in range(count):
        low = RAMP_START[0] + (RAMP_START[1] - RAMP_START[0]) * index / max(count - 1, 1)
        side, top = TILE_SIDES[index % 2], TILE_TOPS[(index // 2) % 2]
        high = min(1.0, low + side)
        fall_low = min(1.0, high + top)
        function = TransferFunction(low, high, TILE_DENSITIES[index % 3], fall_low, min(1.0, fall_low + side))
        bands.append(NamedTransfer(f"{TILED_BAND}-{index}", function))
    return bands


def training_transfers(
    primary: NamedTransfer, count: int, intensity_map: dict | None, seed: int
) -> list[NamedTransfer]:
    """``count`` transfer functions: ``primary``, then the presets not held out (in their order),
    then tiled bands (TILED_SHARE of the rest, rounded down), then seeded random bands and ramps.
    Presets the volume's window clips away are left out."""
    if count < 1:
        raise ValueError(f"a training set needs at least one transfer function, got {count}")
    chosen = [primary]
    for name in TRANSFER_PRESETS:
        if len(chosen) == count:
            break
        if name != primary.name and name not in HELD_OUT_PRESETS and clipped_away(name, intensity_map) is None:
            chosen.append(NamedTransfer(name, resolve_transfer(name, intensity_map)))
    chosen += tiled_bands(int((count - len(chosen)) * TILED_SHARE))
    chosen += random_windows(count - len(chosen), seed)
    return chosen


def member_views(member: int, stride: int, views: int) -> list[int]:
    """The views member ``member`` of a training set is rendered at: all of them at stride 1, else
    every ``stride``-th from an offset of its own (``member`` mod ``stride``), so that a set of
    ``stride`` times as many members costs the same renders and its members share the views out.
    Every member gets ``views // stride`` views."""
    if stride < 1 or views < stride:
        raise ValueError(f"a stride of {stride} needs 1 <= stride <= views ({views})")
    start = member % stride
    return list(range(start, start + (views // stride) * stride, stride))


def member_slot(member: int, view: int, stride: int) -> int:
    """Where ``view`` lies among :func:`member_views` of ``member``: its row in the stack."""
    return (view - member % stride) // stride


@dataclass(frozen=True)
class HeldOutSet:
    transfers: list[NamedTransfer]
    not_scored: dict[str, str]  # a held-out preset the volume cannot show → why


def held_out_transfers(
    intensity_map: dict | None, seed: int, trained: list[NamedTransfer], ramps: int = 1, windows: int = 0
) -> HeldOutSet:
    """The transfer functions eval scores a scalar scene under, none of them in ``trained``:
    the held-out presets the volume's window keeps, seeded ramps of another stream, then
    ``windows`` seeded bands and ramps of a third (a wider sample of the transfer functions a
    person might choose, drawn as the training set's random part is)."""
    held, not_scored = [], {}
    trained_names = {t.name for t in trained}
    for name in HELD_OUT_PRESETS:
        why = clipped_away(name, intensity_map)
        if why is not None:
            not_scored[name] = why
        elif name not in trained_names:
            held.append(NamedTransfer(name, resolve_transfer(name, intensity_map)))
        else:
            not_scored[name] = f"{name} is the transfer function the scene was exported under"
    held += [NamedTransfer(f"held-out-{r.name}", r.function) for r in random_ramps(ramps, seed + HELD_OUT_SEED_OFFSET)]
    held += [
        NamedTransfer(f"{HELD_OUT_WINDOW}-{r.name}", r.function)
        for r in random_windows(windows, seed + HELD_OUT_WINDOW_SEED_OFFSET)
    ]
    return HeldOutSet(held, not_scored)
