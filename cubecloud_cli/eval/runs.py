"""What `cubecloud eval` scores: the splat runs of a work directory, the scenes they trained on,
and the reference renders of those scenes."""

from __future__ import annotations

import logging
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from cubecloud_cli.artifacts import is_complete, read_manifest, require_stage
from cubecloud_cli.cameras import OrbitSpec, PinholeCameras, orbit_cameras
from cubecloud_cli.errors import CubecloudError
from cubecloud_cli.raster.backends import Rasterizer
from cubecloud_cli.splat.data import TrainingScene, load_scene
from cubecloud_cli.splat.gaussians import Gaussians
from cubecloud_cli.splat.ply import read_gaussians_ply
from cubecloud_cli.splat.training import render_camera

log = logging.getLogger("cubecloud")

SPLAT_PLY = "point_cloud.ply"


@dataclass
class SplatRun:
    name: str  # its folder: splat, splat-random, ...
    directory: Path
    manifest: dict
    gaussians: Gaussians

    @property
    def method(self) -> str:
        """The method as the paper's Table I names it."""
        init = self.manifest.get("params", {}).get("init")
        return {"cloud": "Cube-Cloud 3DGS", "random": "3DGS, random init"}.get(init, f"3DGS ({init})")

    @property
    def size_mb(self) -> float:
        return (self.directory / SPLAT_PLY).stat().st_size / 1e6


@dataclass
class ScoredScene:
    """A scene with what its renders are compared against."""

    scene: TrainingScene
    reference: np.ndarray  # (V, H, W) float32
    reference_kind: str  # "volume" (renders of the preprocessed volume) or "images" (the training images)
    export_manifest: dict | None


def find_splat_runs(work: Path) -> list[str]:
    """Names of the complete splat runs in ``work`` (``splat`` first, then ``splat-*`` sorted).
    Folders without a manifest (interrupted runs) are reported and skipped."""
    names = []
    for directory in sorted(Path(work).glob("splat*")):
        if not directory.is_dir() or not (directory.name == "splat" or directory.name.startswith("splat-")):
            continue
        if not is_complete(directory):
            log.warning(f"skipping {directory}: it is incomplete (an interrupted run); finish it with "
                        f"`cubecloud splat {work} --resume`")
            continue
        names.append(directory.name)
    return sorted(names, key=lambda name: (name != "splat", name))


def load_run(work: Path, folder: str) -> SplatRun:
    name = folder[len("splat-"):] if folder.startswith("splat-") else None
    manifest = require_stage(work, "splat", name)
    gaussians = read_gaussians_ply(Path(work) / folder / SPLAT_PLY)
    return SplatRun(folder, Path(work) / folder, manifest, gaussians)


def load_scored_scene(directory: Path, channels: int = 1) -> ScoredScene:
    """The scene, and its reference: ``reference.npy`` (renders of the preprocessed volume, written
    by `cubecloud export`) when present, otherwise its own images (a foreign COLMAP scene)."""
    directory = Path(directory)
    if not directory.is_dir():
        raise CubecloudError(f"the scene {directory} a splat run was trained on is gone: export it again, or retrain")
    scene = load_scene(directory, channels)
    reference_file = directory / "reference.npy"
    if reference_file.is_file():
        try:
            reference = np.load(reference_file, mmap_mode="r")
        except (OSError, ValueError) as exc:
            raise CubecloudError(f"{reference_file} is unreadable ({exc}): re-export with `cubecloud export --force`") from None
        expected = (len(scene.names), scene.cameras.height, scene.cameras.width)
        if reference.shape[:3] != expected:
            raise CubecloudError(f"{reference_file} holds {reference.shape}, not {expected}: re-export with `cubecloud export --force`")
        reference = np.asarray(reference, dtype=np.float32)
        reference = reference.mean(axis=-1) if reference.ndim == 4 else reference
        kind = "volume"
    else:
        reference, kind = scene.images.numpy().mean(axis=-1), "images"
    if not np.isfinite(reference).all():
        raise CubecloudError(f"the reference images of {directory} hold NaN or Inf: re-export the scene")
    export_manifest = read_manifest(directory) if (directory / "manifest.json").is_file() else None
    return ScoredScene(scene, reference, kind, export_manifest)


@torch.no_grad()
def render_views(gaussians: Gaussians, cameras: PinholeCameras, views: list[int], rasterizer: Rasterizer,
                 on_frame=lambda: None) -> tuple[np.ndarray, float]:
    """(V, H, W) grey renders in [0, 1] of ``views``, and the median milliseconds per frame (the
    first frame, which may compile kernels, is rendered twice and timed the second time)."""
    frames, times = [], []
    for index, view in enumerate(views):
        if index == 0:
            render_camera(gaussians, cameras, view, gaussians.sh_degree, rasterizer)
        started = time.perf_counter()
        image = render_camera(gaussians, cameras, view, gaussians.sh_degree, rasterizer).image
        if image.is_cuda:
            torch.cuda.synchronize()
        times.append(1000.0 * (time.perf_counter() - started))
        frames.append(image.clamp(0.0, 1.0).mean(dim=-1).cpu().numpy())
        on_frame()
    height, width = cameras.height, cameras.width
    stack = np.stack(frames) if frames else np.zeros((0, height, width), dtype=np.float32)
    return stack.astype(np.float32), (statistics.median(times) if times else float("nan"))


def turntable_cameras(scored: ScoredScene, frames: int, max_resolution: int) -> PinholeCameras:
    """A dense orbit like the export's (same axis, radius, elevation and field of view), or, for a
    foreign scene, its own cameras in order."""
    manifest = scored.export_manifest
    if manifest is None or "cameras" not in manifest:
        return scored.scene.cameras
    params = manifest.get("params", {})
    resolution = min(int(manifest["cameras"]["width"]), max_resolution)
    return orbit_cameras(OrbitSpec(views=frames, axis=params.get("axis", "si"), radius=float(params.get("radius", 4.0)),
                                   resolution=resolution, elevation=float(params.get("elevation", 0.0)),
                                   fov=float(manifest["cameras"]["fov_deg"])))
