"""The trained field as a Python object, for `export` and for users' own scripts.

    field = CunerfField.load("work")
    intensity, density = field.query(points)       # any (P, 3) world points, in chunks
    values = field.render_cubes(centres)           # CuNeRF cube renders at any centres
    volume = field.bake(256)                       # the field on a 256³ grid over the cube
    affine = field.bake_affine(256)                # that grid's voxel → scanner-mm affine

World coordinates follow docs/design.md §2: the preprocessed volume fills [−1, 1]³, voxel (i, j, k) of
an S³ grid centred at ((2i+1)/S − 1, …).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from cubecloud_cli.core.artifacts import require_stage, stage_dir_name
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.core.runtime import resolve_device
from cubecloud_cli.core.writes import write_atomically
from cubecloud_cli.cunerf import grid_bake
from cubecloud_cli.cunerf.config import FieldConfig, RenderConfig
from cubecloud_cli.cunerf.model import CubeModel, render_many
from cubecloud_cli.cunerf.supervision import Occupancy, voxel_centres

MODEL_FILE = "model.pt"
MODEL_FORMAT = 1


def grid_centres(size: int, device: torch.device, x_range: tuple[int, int] | None = None) -> torch.Tensor:
    """World centres of the voxels of a size³ grid over [−1, 1]³ (x-major), optionally only
    the x-slab ``x_range``."""
    axis = voxel_centres(torch.arange(size, device=device), size)
    xs = axis if x_range is None else axis[x_range[0] : x_range[1]]
    x, y, z = torch.meshgrid(xs, axis, axis, indexing="ij")
    return torch.stack((x, y, z), dim=-1).reshape(-1, 3)


@dataclass
class CunerfField:
    model: CubeModel
    volume_size: int
    voxel_to_scanner: np.ndarray  # the preprocessed volume's affine
    occupancy: Occupancy | None = None
    settings: dict[str, Any] | None = None

    @property
    def device(self) -> torch.device:
        return next(self.model.parameters()).device

    @property
    def cube_half_size(self) -> float:
        """Half-size of the rendered cubes, in world units."""
        return self.model.render_config.cube_half_size

    # -- saving and loading ---------------------------------------------------------------

    def to_file(self, path: Path) -> None:
        payload = {
            "format": MODEL_FORMAT,
            "field": self.model.field_config.as_dict(),
            "render": self.model.render_config.as_dict(),
            "volume_size": self.volume_size,
            "voxel_to_scanner": self.voxel_to_scanner.tolist(),
            "settings": self.settings,
            "model": self.model.state_dict(),
            "occupancy": None
            if self.occupancy is None
            else {"blocks": self.occupancy.blocks.cpu(), "block": self.occupancy.block},
        }
        write_atomically(Path(path), lambda temporary: torch.save(payload, temporary))

    @classmethod
    def from_file(cls, path: Path, device: str = "auto") -> "CunerfField":
        target = resolve_device(device)
        try:
            # Memory-mapped on the CPU: the grid's table is read from the file as lookups reach it.
            mapped = target.type == "cpu"
            payload = torch.load(path, map_location=target, weights_only=True, mmap=mapped)
        except FileNotFoundError:
            raise CubecloudError(f"{path} does not exist: run `cubecloud cunerf WORK` first") from None
        except Exception as exc:  # torch raises many types for a damaged file
            raise CubecloudError(
                f"{path} is not a readable cubecloud model ({type(exc).__name__}): rerun `cubecloud cunerf WORK --force`"
            ) from None
        if not isinstance(payload, dict) or payload.get("format") != MODEL_FORMAT:
            raise CubecloudError(
                f"{path} is not a cubecloud model of format {MODEL_FORMAT}: rerun `cubecloud cunerf WORK --force`"
            )
        try:
            model = CubeModel.holding(
                FieldConfig.from_dict(payload["field"]), RenderConfig(**payload["render"]), payload["model"]
            )
        except (RuntimeError, KeyError, TypeError) as exc:  # weights that do not fit the configuration
            raise CubecloudError(
                f"{path} holds weights that do not fit its configuration ({type(exc).__name__}): "
                f"rerun `cubecloud cunerf WORK --force`"
            ) from None
        model.to(target).eval()
        # The arithmetic it trained in, where the device has it (cunerf/precision.py).
        if target.type == "cuda":
            model.set_precision((payload.get("settings") or {}).get("precision", "float32"))
        occupancy = None
        if payload.get("occupancy") is not None:
            occupancy = Occupancy(
                payload["occupancy"]["blocks"].to(target),
                int(payload["occupancy"]["block"]),
                int(payload["volume_size"]),
            )
        return cls(
            model,
            int(payload["volume_size"]),
            np.asarray(payload["voxel_to_scanner"]),
            occupancy,
            payload.get("settings"),
        )

    @classmethod
    def load(cls, work: Path, name: str | None = None, device: str = "auto") -> "CunerfField":
        """The model of a complete WORK/cunerf[-NAME] stage."""
        require_stage(Path(work), "cunerf", name)
        return cls.from_file(Path(work) / stage_dir_name("cunerf", name) / MODEL_FILE, device)

    # -- queries --------------------------------------------------------------------------

    def _as_points(self, points) -> torch.Tensor:
        tensor = torch.as_tensor(np.asarray(points, dtype=np.float32) if not torch.is_tensor(points) else points)
        if tensor.ndim != 2 or tensor.shape[1] != 3:
            raise ValueError(f"points must have shape (P, 3), got {tuple(tensor.shape)}")
        return tensor.to(self.device, torch.float32)

    @torch.no_grad()
    def query(self, points, chunk: int = 1 << 18) -> tuple[np.ndarray, np.ndarray]:
        """Intensity in [0, 1] and density ≥ 0 of the final (fine) field at world points."""
        points = self._as_points(points)
        field = self.model.final_field
        intensity = np.empty(points.shape[0], dtype=np.float32)
        density = np.empty(points.shape[0], dtype=np.float32)
        for start in range(0, points.shape[0], chunk):
            value, sigma = field(points[start : start + chunk])
            intensity[start : start + chunk] = value.cpu().numpy()
            density[start : start + chunk] = sigma.cpu().numpy()
        return intensity, density

    def _keep(self, skip_air: bool) -> Callable[[torch.Tensor], torch.Tensor] | None:
        return self.occupancy.occupied if (skip_air and self.occupancy is not None) else None

    def render_cubes(self, centres, chunk: int | None = None, skip_air: bool = True) -> np.ndarray:
        """CuNeRF's test render of cubes centred at world points (deterministic)."""
        return self.cube_values(self._as_points(centres), chunk, skip_air).cpu().numpy()

    @torch.no_grad()
    def cube_values(self, centres: torch.Tensor, chunk: int | None = None, skip_air: bool = True) -> torch.Tensor:
        """:meth:`render_cubes` for a (P, 3) tensor on the field's device, as a tensor in [0, 1]."""
        generator = torch.Generator(device=self.device).manual_seed(0)
        values = render_many(self.model, centres.to(self.device, torch.float32), chunk, self._keep(skip_air), generator)
        return values.clamp(0.0, 1.0)

    @torch.no_grad()
    def point_density(self, points: torch.Tensor) -> torch.Tensor:
        """The final field's density σ ≥ 0 at a (P, 3) tensor of world points."""
        return self.model.final_field(points.to(self.device, torch.float32))[1]

    def bake(
        self,
        size: int,
        chunk: int | None = None,
        skip_air: bool = True,
        on_progress: Callable[[float], None] = lambda fraction: None,
    ) -> np.ndarray:
        """Render a cube at every voxel centre of a size³ grid over [−1, 1]³ (RAS axes)."""
        if not 1 <= size <= 4096:
            raise ValueError(f"bake size must be within 1..4096, got {size}")
        volume = np.empty((size, size, size), dtype=np.float32)
        if grid_bake.applies(self.model, self.device, size):
            grid_bake.bake_lattice(self.model, size, self.occupancy if skip_air else None, volume, on_progress)
            return volume
        slab = max(1, (1 << 20) // (size * size))
        generator = torch.Generator(device=self.device).manual_seed(0)
        for start in range(0, size, slab):
            stop = min(size, start + slab)
            centres = grid_centres(size, self.device, (start, stop))
            values = render_many(self.model, centres, chunk, self._keep(skip_air), generator)
            volume[start:stop] = values.clamp(0.0, 1.0).reshape(stop - start, size, size).cpu().numpy()
            on_progress(stop / size)
        return volume

    def bake_affine(self, size: int) -> np.ndarray:
        """Voxel → scanner-mm affine of a size³ bake: the same physical cube as the volume."""
        ratio = self.volume_size / size
        scale = np.eye(4)
        scale[:3, :3] *= ratio
        scale[:3, 3] = 0.5 * ratio - 0.5
        return self.voxel_to_scanner @ scale
