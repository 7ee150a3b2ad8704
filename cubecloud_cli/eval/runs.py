"""What `cubecloud eval` scores: the splat runs of a work directory, the scenes they trained on,
and the reference renders of those scenes."""

from __future__ import annotations

import logging
import statistics
import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from cubecloud_cli.cameras import OrbitSpec, PinholeCameras, orbit_cameras
from cubecloud_cli.core.artifacts import (
    PARTIAL_SUFFIX,
    is_complete,
    read_manifest,
    require_stage,
    sha256_of_path,
    verify_stage_files,
)
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.eval.novel_scores import NovelTest, load_novel_test
from cubecloud_cli.raster.backends import Rasterizer
from cubecloud_cli.scene import read_colmap_model
from cubecloud_cli.splat.gaussian_ply import read_gaussians_ply, read_scalar_gaussians
from cubecloud_cli.splat.gaussians import Gaussians
from cubecloud_cli.splat.scalar_gaussians import ScalarGaussians
from cubecloud_cli.splat.trainer import render_camera
from cubecloud_cli.splat.training_views import TrainingScene, load_scene

log = logging.getLogger("cubecloud")

SPLAT_PLY = "point_cloud.ply"
MAX_TURNTABLE_FRAMES = 720


@dataclass
class SplatRun:
    name: str  # its folder: splat, splat-random, ...
    directory: Path
    manifest: dict

    @property
    def method(self) -> str:
        """The method as the paper's Table I names it."""
        init = self.manifest.get("params", {}).get("init")
        return {"cloud": "Cube-Cloud 3DGS", "random": "3DGS, random init"}.get(init, f"3DGS ({init})")

    @property
    def antialias(self) -> bool:
        """Whether it trained with the 2D Mip filter, which its renders then need too (its 3D filter
        is baked into the PLY). Runs made before the option were plain 3DGS."""
        return bool(self.manifest.get("params", {}).get("antialias", False))

    @property
    def size_mb(self) -> float:
        return (self.directory / SPLAT_PLY).stat().st_size / 1e6

    @property
    def retrain(self) -> str:
        name = self.name[len("splat-") :] if self.name.startswith("splat-") else None
        return f"cubecloud splat {self.directory.parent}{f' --name {name}' if name else ''} --force"

    @property
    def scalar(self) -> bool:
        """Whether it trained Gaussians that carry the scan's value (``splat --scalar``)."""
        return bool(self.manifest.get("params", {}).get("scalar", False))

    @property
    def chord_lengths(self) -> bool:
        """Whether it is a scalar run whose optical lengths follow the ray (``--chord-lengths``)."""
        return self.scalar and bool(self.manifest.get("params", {}).get("chord_lengths", False))

    def gaussians(self) -> Gaussians | ScalarGaussians:
        """Read when needed, so that only one run's Gaussians are in memory at a time: its PLY's
        reference columns, or a chord-length scene's own model, whose opacities change with the
        view as no PLY column can (``fixed_opacity_gaussians`` are its reference columns)."""
        if self.chord_lengths:
            return read_scalar_gaussians(self.directory / SPLAT_PLY)
        return self.fixed_opacity_gaussians()

    def fixed_opacity_gaussians(self) -> Gaussians:
        """The PLY's reference columns: the run as every splat viewer draws it."""
        return read_gaussians_ply(self.directory / SPLAT_PLY)

    def scalar_gaussians(self) -> ScalarGaussians | None:
        """A scalar run's Gaussians, to draw under any transfer function; None for a baked run."""
        return read_scalar_gaussians(self.directory / SPLAT_PLY) if self.scalar else None


@dataclass
class ScoredScene:
    """A scene with what its renders are compared against."""

    scene: TrainingScene
    reference: np.ndarray  # (V, H, W) float32
    reference_kind: str  # "volume" (renders of the preprocessed volume) or "images" (the training images)
    export_manifest: dict | None
    novel: NovelTest | None = None  # the export's novel views, when it has them


def find_splat_runs(work: Path, report: bool = True) -> list[str]:
    """Names of the complete splat runs in ``work`` (``splat`` first, then ``splat-*`` sorted).
    Incomplete ones are skipped, and reported when ``report`` (once per command, not per look)."""
    names = []
    for directory in sorted(Path(work).glob("splat*")):
        if not directory.is_dir() or not (directory.name == "splat" or directory.name.startswith("splat-")):
            continue
        if not is_complete(directory):
            if report:
                log.warning(
                    f"skipping {directory}: it has no manifest.json (not a finished run); retrain it with `cubecloud "
                    f"splat {work}{_name_option(directory.name)} --force`"
                )
            continue
        names.append(directory.name)
    for partial in sorted(Path(work).glob(f".splat*{PARTIAL_SUFFIX}")):
        folder = partial.name[1 : -len(PARTIAL_SUFFIX)]
        if report and not (Path(work) / folder).exists():
            log.warning(
                f"not evaluating {folder}: its training was interrupted; finish it with `cubecloud splat {work}"
                f"{_name_option(folder)} --resume`"
            )
    return sorted(names, key=lambda name: (name != "splat", name))


def _name_option(folder: str) -> str:
    return f" --name {folder[len('splat-') :]}" if folder.startswith("splat-") else ""


def load_run(work: Path, folder: str) -> SplatRun:
    name = folder[len("splat-") :] if folder.startswith("splat-") else None
    manifest = require_stage(work, "splat", name)
    return SplatRun(folder, Path(work) / folder, manifest)


@lru_cache(maxsize=64)
def _digest(path: Path, size: int, modified_ns: int) -> str:
    return sha256_of_path(path)


def file_digest(path: Path) -> str:
    """sha256 of a file, computed once per (path, size, modification time) in this process."""
    stat = path.stat()
    return _digest(path.resolve(), stat.st_size, stat.st_mtime_ns)


def _is_the_scene(candidate: Path, recorded: dict, images_hash: str | None) -> bool:
    if not candidate.is_dir():
        return False
    images = candidate / "images.npy"
    if images_hash:
        return images.is_file() and file_digest(images) == images_hash
    try:  # a foreign scene of image files: the same views, size and held-out names
        model = read_colmap_model(candidate)
    except CubecloudError:
        return False
    names = set(model.image_names)
    return (
        len(model.image_names) == recorded.get("views")
        and model.cameras.width == recorded.get("width")
        and model.cameras.height == recorded.get("height")
        and set(recorded.get("test", [])) <= names
    )


def resolve_scene(work: Path, run: SplatRun) -> Path:
    """The scene ``run`` trained on, as it is now. A run on its work directory's export is scored
    against that export (so a copied or moved work directory uses its own files); a run on another
    scene against the directory it names. A scene that is gone or whose images changed since is an
    error: its held-out views would not be the run's."""
    recorded = run.manifest.get("scene", {})
    inputs = run.manifest.get("inputs", {})
    images_hash = recorded.get("images_sha256") or inputs.get("export/images.npy")
    own_export = recorded.get("own_export")
    if own_export is None:  # manifests written before the flag: the default scene is WORK/export
        own_export = "export/images.npy" in inputs and Path(recorded.get("directory", "export")).name == "export"
    if own_export:
        if _is_the_scene(Path(work) / "export", recorded, images_hash):
            return (Path(work) / "export").resolve()
        raise CubecloudError(
            f"{Path(work) / 'export'} is gone or has changed since {run.name} was trained on it: "
            f"retrain it with `{run.retrain}`"
        )
    named = [Path(p) for p in (recorded.get("resolved"), recorded.get("directory")) if p]
    for candidate in named:
        if _is_the_scene(candidate, recorded, images_hash):
            return candidate.resolve()
    where = recorded.get("resolved") or recorded.get("directory")
    raise CubecloudError(
        f"{run.name} was trained on the scene {where}, which is gone or has changed since: "
        f"retrain it with `{run.retrain}`"
    )


def load_scored_scene(directory: Path, channels: int = 1) -> ScoredScene:
    """The scene, and its reference: ``reference.npy`` (renders of the preprocessed volume) for an
    export of ours, which must be intact; a foreign COLMAP scene's own images otherwise."""
    directory = Path(directory)
    export_manifest = read_manifest(directory) if is_complete(directory) else None
    is_export = bool(export_manifest) and export_manifest.get("stage") == "export"
    fix = f"cubecloud export {directory.parent} --force"
    if is_export:
        verify_stage_files(directory, export_manifest, fix)
    scene = load_scene(directory, channels)
    reference_file = directory / "reference.npy"
    if is_export or reference_file.is_file():
        try:
            reference = np.load(reference_file, mmap_mode="r")
        except (OSError, ValueError) as exc:
            raise CubecloudError(f"{reference_file} is unreadable ({type(exc).__name__}): run `{fix}`") from None
        expected = (len(scene.names), scene.cameras.height, scene.cameras.width)
        if reference.shape[:3] != expected:
            raise CubecloudError(f"{reference_file} holds {reference.shape}, not {expected}: run `{fix}`")
        reference = np.asarray(reference, dtype=np.float32)
        reference = reference.mean(axis=-1) if reference.ndim == 4 else reference
        kind = "volume"
    else:
        reference, kind = scene.images.numpy().mean(axis=-1), "images"
    if not np.isfinite(reference).all():
        raise CubecloudError(f"the reference images of {directory} hold NaN or Inf: re-export the scene")
    novel = load_novel_test(directory, fix) if is_export else None
    return ScoredScene(scene, reference, kind, export_manifest if is_export else None, novel)


@torch.no_grad()
def render_views(
    gaussians: Gaussians,
    cameras: PinholeCameras,
    views: list[int],
    rasterizer: Rasterizer,
    on_frame=lambda: None,
    antialias: bool = False,
) -> tuple[np.ndarray, float]:
    """(V, H, W) grey renders in [0, 1] of ``views``, and the median milliseconds per frame (the
    first frame, which may compile kernels, is rendered twice and timed the second time)."""
    frames, times = [], []
    for index, view in enumerate(views):
        if index == 0:
            render_camera(gaussians, cameras, view, gaussians.sh_degree, rasterizer, antialias=antialias)
            if gaussians.means.is_cuda:
                torch.cuda.synchronize()
        started = time.perf_counter()
        image = render_camera(gaussians, cameras, view, gaussians.sh_degree, rasterizer, antialias=antialias).image
        if image.is_cuda:
            torch.cuda.synchronize()
        times.append(1000.0 * (time.perf_counter() - started))
        frames.append(image.clamp(0.0, 1.0).mean(dim=-1).cpu().numpy())
        on_frame()
    stack = np.stack(frames) if frames else np.zeros((0, cameras.height, cameras.width), dtype=np.float32)
    return stack.astype(np.float32), (statistics.median(times) if times else float("nan"))


def _downscaled(cameras: PinholeCameras, indices: np.ndarray, max_resolution: int) -> PinholeCameras:
    factor = min(1.0, max_resolution / max(cameras.width, cameras.height))
    return PinholeCameras(
        cameras.rotations[indices],
        cameras.translations[indices],
        max(1, round(cameras.width * factor)),
        max(1, round(cameras.height * factor)),
        cameras.focal * factor,
    )


STACK_TURNTABLE_AXES = {"lr": "si", "ap": "si", "si": "ap"}  # slice normal -> an orbit axis across it


def turntable_cameras(scored: ScoredScene, frames: int, max_resolution: int) -> PinholeCameras:
    """A dense orbit like the export's (same axis, radius, elevation and field of view), or, for a
    foreign scene, ``frames`` of its own cameras in order; at most ``max_resolution`` pixels."""
    manifest = scored.export_manifest
    if manifest is None or "cameras" not in manifest:
        cameras = scored.scene.cameras
        indices = np.unique(np.linspace(0, len(cameras) - 1, min(frames, len(cameras))).round().astype(np.int64))
        return _downscaled(cameras, indices, max_resolution)
    params = manifest.get("params", {})
    resolution = min(int(manifest["cameras"]["width"]), max_resolution)
    if params.get("cameras") == "stack":
        # One pose: turn about an axis across the slice normal, so the trained view comes round,
        # with a field of view that fits the cube from every side.
        axis = STACK_TURNTABLE_AXES.get(params.get("axis"), "si")
        return orbit_cameras(
            OrbitSpec(views=frames, axis=axis, radius=float(params.get("radius", 4.0)), resolution=resolution)
        )
    return orbit_cameras(
        OrbitSpec(
            views=frames,
            axis=params.get("axis", "si"),
            radius=float(params.get("radius", 4.0)),
            resolution=resolution,
            elevation=float(params.get("elevation", 0.0)),
            fov=float(manifest["cameras"]["fov_deg"]),
        )
    )
