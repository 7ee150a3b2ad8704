"""A scalar scene in the viewer: its Gaussians recoloured under any transfer function and colour
map the page asks for, on the server, without retraining (docs/design.md §4).

A transfer function gives each Gaussian its opacity from its scan value and optical length; a
colour map gives it its colour from the same value (dvr's emission, grey unless a map is chosen).
Presets are the transfer functions the scene was trained under and the named ones, in HU for CT,
as the export resolved them for this volume.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.eval.figures import anchor_colours
from cubecloud_cli.splat.chord import chord_log_ratio, sphere_mean_log_ratio
from cubecloud_cli.splat.scalar_gaussians import LOG_LENGTH_LIMIT, ScalarGaussians
from cubecloud_cli.transfer.function import TransferFunction
from cubecloud_cli.transfer.tissue_presets import TRANSFER_PRESETS, clipped_away, resolve_transfer
from cubecloud_cli.view.splats import ViewSplats, importance_order, mean_variances, view_splats

# Anchor colours, evenly spaced over [0, 1], interpolated linearly in RGB.
COLOUR_MAPS: dict[str, tuple[tuple[float, float, float], ...]] = {
    "grey": ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
    # Warm and bright like bone in a volume renderer: dark red through tan to ivory.
    "bone": ((0.25, 0.05, 0.02), (0.75, 0.45, 0.3), (1.0, 0.93, 0.82)),
    # Black body: black, red, yellow, white.
    "hot": ((0.0, 0.0, 0.0), (0.9, 0.1, 0.0), (1.0, 0.85, 0.1), (1.0, 1.0, 1.0)),
    # Blue to red through white, for values on both sides of a middle.
    "cool-warm": ((0.23, 0.3, 0.75), (0.87, 0.87, 0.87), (0.71, 0.02, 0.15)),
}
TRAINED_PRESET = "as trained"
CUSTOM = "custom"
MAX_OPACITY_SCALE = 100.0
CONTROLS = ("transfer preset", "window low", "window high", "opacity scale", "colour map")


def colour_map(values: np.ndarray, name: str) -> np.ndarray:
    """(N, 3) float32 colours of ``values`` (clipped to [0, 1]; NaN as 0) under the map ``name``."""
    return anchor_colours(values, np.asarray(COLOUR_MAPS[name])).astype(np.float32)


@dataclass(frozen=True)
class ViewTransfer:
    """What the page chose: a transfer function, its opacity scale (× the extinction) and a colour map."""

    function: TransferFunction
    opacity_scale: float = 1.0
    colour_map: str = "grey"

    def effective(self) -> TransferFunction:
        scale = float(np.clip(np.nan_to_num(self.opacity_scale, nan=1.0), 0.0, MAX_OPACITY_SCALE))
        return replace(self.function, density=min(self.function.density * scale, 999_999.0))


def read_intensity_map(work: Path) -> dict | None:
    """The preprocess window (HU for CT) the transfer-function presets are resolved through."""
    try:
        return json.loads((Path(work) / "preprocess" / "manifest.json").read_text()).get("intensity")
    except (OSError, ValueError, AttributeError):
        return None


def shown_presets(intensity_map: dict | None) -> tuple[str, ...]:
    """The named presets this volume can show: not those its window clipped away."""
    return tuple(name for name in TRANSFER_PRESETS if clipped_away(name, intensity_map) is None)


def transfer_presets(scalar: ScalarGaussians, intensity_map: dict | None) -> dict[str, TransferFunction]:
    """The transfer functions the page offers: the one the PLY's reference columns were drawn
    under, then the named presets resolved for this volume's window."""
    presets = {TRAINED_PRESET: scalar.transfer}
    presets.update({name: resolve_transfer(name, intensity_map) for name in shown_presets(intensity_map)})
    return presets


@dataclass(frozen=True)
class ChordGeometry:
    """What a chord-length scene's ratio r(d) needs (splat/chord.py): each Gaussian's centre,
    quaternion and scales as rendered (the 3D filter folded in), float32."""

    means: np.ndarray  # (N, 3)
    quaternions: np.ndarray  # (N, 4)
    scales: np.ndarray  # (N, 3)

    def log_ratios(self, camera_centre: np.ndarray) -> np.ndarray:
        """(N,) log r of each Gaussian seen from ``camera_centre`` (world units)."""
        tensors = (torch.from_numpy(a) for a in (self.means, self.quaternions, self.scales))
        centre = torch.as_tensor(np.asarray(camera_centre, dtype=np.float32))
        with torch.no_grad():
            return chord_log_ratio(*tensors, centre).numpy()


@dataclass(frozen=True)
class DrawnValues:
    """What of a scalar scene no transfer function changes, computed once: each Gaussian's value,
    optical length (world units) and the factor its 3D filter scales every opacity by. A recolour
    is then a few float32 passes over them (2 ms for 100k, where the torch map took 25 ms on a
    machine busy drawing the page). A chord-length scene's ℓ is scaled by r(d) for the camera
    it is seen from, or by r's mean over the sphere without one."""

    values: np.ndarray  # (N,) float32 in [0, 1]
    lengths: np.ndarray  # (N,) float32, exp of the clamped log length
    attenuation: np.ndarray  # (N,) float32 in (0, 1]
    chord: ChordGeometry | None = None  # a chord-length scene's shapes, else None
    sphere_log_ratios: np.ndarray | None = None  # (N,) log r's mean over the sphere (chord scenes)

    @classmethod
    def of(cls, scalar: ScalarGaussians) -> "DrawnValues":
        with torch.no_grad():
            values = scalar.values().clamp(0.0, 1.0)
            lengths = torch.exp(scalar.log_lengths.clamp(-LOG_LENGTH_LIMIT, LOG_LENGTH_LIMIT))
            attenuation = scalar.filter_attenuation().clamp(0.0, 1.0)
            arrays = [t.float().numpy() for t in (values, lengths, attenuation)]
            if not scalar.chord_lengths:
                return cls(*arrays)
            scales = scalar.scales()
            chord = ChordGeometry(*(t.detach().float().numpy() for t in (scalar.means, scalar.quaternions, scales)))
            sphere = sphere_mean_log_ratio(scales.log()).float().numpy()
        return cls(*arrays, chord, sphere)

    def seen_lengths(self, camera_centre: np.ndarray | None = None) -> np.ndarray:
        """(N,) ℓ as drawn: times r seen from ``camera_centre``, or r's mean over the sphere
        without one; ℓ alone for a scene without chord lengths (as ScalarGaussians.seen_log_lengths)."""
        if self.chord is None:
            return self.lengths
        log_ratios = self.sphere_log_ratios if camera_centre is None else self.chord.log_ratios(camera_centre)
        log_lengths = np.log(np.maximum(self.lengths, np.float32(np.exp(-LOG_LENGTH_LIMIT)))) + log_ratios
        return np.exp(np.clip(log_lengths, -LOG_LENGTH_LIMIT, LOG_LENGTH_LIMIT)).astype(np.float32)

    def opacities(self, transfer: TransferFunction, camera_centre: np.ndarray | None = None) -> np.ndarray:
        """(N,) α = (1 − exp(−σ(v) ℓ r)) × the filter's factor, as ScalarGaussians.opacities gives
        it (r seen from ``camera_centre``, see :meth:`seen_lengths`)."""
        return self.opacities_at(transfer, self.seen_lengths(camera_centre))

    def opacities_at(self, transfer: TransferFunction, seen_lengths: np.ndarray) -> np.ndarray:
        """:meth:`opacities` for lengths :meth:`seen_lengths` gave: a recolour under another
        transfer function does not compute r again while the camera rests."""
        depth = np.asarray(transfer.extinction(self.values), dtype=np.float32) * seen_lengths
        return np.clip(-np.expm1(-depth) * self.attenuation, 0.0, 1.0).astype(np.float32)


def recoloured(
    geometry: ViewSplats, drawn: DrawnValues, chosen: ViewTransfer, seen_lengths: np.ndarray | None = None
) -> ViewSplats:
    """``geometry`` (the scene's centres and covariances, in the PLY's order, from
    :func:`view_splats`) with the colours and opacities the rasterizer gives it under ``chosen``
    (with ``seen_lengths`` from :meth:`DrawnValues.seen_lengths`; the camera-less ones without):
    only these change with a transfer function, so a change of control redoes nothing else."""
    lengths = drawn.seen_lengths() if seen_lengths is None else seen_lengths
    opacities = drawn.opacities_at(chosen.effective(), lengths)
    # Grey is the value itself: no interpolation (a sixth of a recolouring's time for 100k).
    grey = chosen.colour_map == "grey"
    rgbs = np.repeat(drawn.values[:, None], 3, axis=1) if grey else colour_map(drawn.values, chosen.colour_map)
    return ViewSplats(geometry.centers, geometry.covariances, rgbs, opacities[:, None])


class ScalarScene:
    """A scalar run as the viewer shows it: its geometry once, its colours and opacities under
    the transfer function, opacity scale and colour map chosen last."""

    def __init__(self, scalar: ScalarGaussians, intensity_map: dict | None):
        self.scalar = scalar
        self.drawn = DrawnValues.of(scalar)
        self.geometry = view_splats(scalar)
        self.variances = mean_variances(self.geometry.covariances)  # the importance order's other factor
        self.presets = transfer_presets(scalar, intensity_map)
        self.chosen = ViewTransfer(scalar.transfer)
        self.camera_centre: np.ndarray | None = None  # where a chord-length scene is seen from
        self.seen_lengths = self.drawn.seen_lengths()  # ℓ as drawn from there, kept while it rests

    @property
    def follows_camera(self) -> bool:
        """Whether the opacities change with the camera (a chord-length scene)."""
        return self.drawn.chord is not None

    def look_from(self, camera_centre: np.ndarray | None) -> bool:
        """Draw a chord-length scene as seen from ``camera_centre`` (world units; None: r's mean
        over the sphere); True when that changes its opacities."""
        if not self.follows_camera:
            return False
        centre = None if camera_centre is None else np.asarray(camera_centre, dtype=np.float64).copy()
        if np.array_equal(centre, self.camera_centre):  # None against None too
            return False
        self.camera_centre = centre
        self.seen_lengths = self.drawn.seen_lengths(centre)
        return True

    def splats(self) -> ViewSplats:
        """The Gaussians under the current choice, in importance order (it changes with opacity)."""
        splats = recoloured(self.geometry, self.drawn, self.chosen, self.seen_lengths)
        return splats.subset(importance_order(splats, self.variances, stable=False))

    def choose(
        self,
        preset: str | None = None,
        low: float | None = None,
        high: float | None = None,
        opacity: float | None = None,
        colour_map: str | None = None,
    ) -> bool:
        """Take a preset, or move the window (preprocessed intensities, kept within [0, 1] and
        low ≤ high), the opacity scale or the colour map; True when the choice changed."""
        if preset is not None and preset not in self.presets:
            raise CubecloudError(f"transfer preset {preset!r} must be one of {', '.join(self.presets)}")
        if colour_map is not None and colour_map not in COLOUR_MAPS:
            raise CubecloudError(f"colour map {colour_map!r} must be one of {', '.join(COLOUR_MAPS)}")
        function = self.presets[preset] if preset is not None else self.chosen.function
        if low is not None or high is not None:
            new_low = float(np.clip(np.nan_to_num(function.low if low is None else low), 0.0, 1.0))
            new_high = float(np.clip(np.nan_to_num(function.high if high is None else high), new_low, 1.0))
            function = function.with_window(new_low, new_high)
        scale = (
            self.chosen.opacity_scale
            if opacity is None
            else float(np.clip(np.nan_to_num(opacity, nan=1.0), 0.0, MAX_OPACITY_SCALE))
        )
        wanted = ViewTransfer(function, scale, self.chosen.colour_map if colour_map is None else colour_map)
        changed, self.chosen = wanted != self.chosen, wanted
        return changed

    def control_values(self) -> dict:
        """What the page's controls show for the current choice."""
        chosen = self.chosen
        preset = next((name for name, f in self.presets.items() if f == chosen.function), CUSTOM)
        return dict(
            zip(CONTROLS, (preset, chosen.function.low, chosen.function.high, chosen.opacity_scale, chosen.colour_map))
        )


def add_transfer_controls(
    gui, set_transfer: Callable[..., None], presets: tuple[str, ...], expand: bool = True
) -> dict:
    """The page's "Transfer function" folder (``expand``: open at first) offering ``presets``, each
    control calling ``set_transfer``; returns the controls by the names of :data:`CONTROLS`."""
    with gui.add_folder("Transfer function", expand_by_default=expand):
        preset = gui.add_dropdown("Preset", (TRAINED_PRESET, *presets, CUSTOM), initial_value=TRAINED_PRESET,
                                  hint="What tissue the scalar scene shows, without retraining")  # fmt: skip
        low = gui.add_slider("Window low", min=0.0, max=1.0, step=0.005, initial_value=0.0)
        high = gui.add_slider("Window high", min=0.0, max=1.0, step=0.005, initial_value=1.0)
        opacity = gui.add_slider("Opacity scale", min=0.0, max=20.0, step=0.1, initial_value=1.0,
                                 hint="Multiplies the extinction: above 1 denser, below 1 clearer")  # fmt: skip
        colours = gui.add_dropdown("Colour map", tuple(COLOUR_MAPS), initial_value="grey")
    preset.on_update(lambda _: preset.value != CUSTOM and set_transfer(preset=preset.value))
    low.on_update(lambda _: set_transfer(low=low.value))
    high.on_update(lambda _: set_transfer(high=high.value))
    opacity.on_update(lambda _: set_transfer(opacity=opacity.value))
    colours.on_update(lambda _: set_transfer(colour_map=colours.value))
    return dict(zip(CONTROLS, (preset, low, high, opacity, colours)))
