"""`cubecloud share`: a finished splat run as a folder to send to someone, its scene as SPZ and one
self-contained ``index.html`` that draws it (cubecloud_cli/share/page.py).

OUT/
  index.html   the page: viewer, scene and all, opens from file:// with no network
  scene.spz    the same Gaussians for other splat viewers (SuperSplat, Spark, …), world units

The folder is written beside OUT and renamed into place, so an interrupted share leaves OUT as it
was; an OUT that exists is replaced only with ``force``.
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cubecloud_cli.core.artifacts import read_manifest
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.eval.runs import find_splat_runs, load_run, resolve_scene
from cubecloud_cli.scene import read_colmap_model
from cubecloud_cli.share.page import page_camera, page_info, render_page, scalar_block, scalar_info
from cubecloud_cli.share.spz import encode_spz
from cubecloud_cli.splat.training_views import export_remake
from cubecloud_cli.transfer.tissue_presets import ct_window
from cubecloud_cli.view.transfer_view import DrawnValues, read_intensity_map, transfer_presets

PAGE_FILE = "index.html"
SPZ_FILE = "scene.spz"
POSITION_STEPS_PER_VOXEL = 64  # SPZ's fixed-point positions resolve 1/64 of a voxel
FINEST_CUBE = 512  # the cube side assumed when the work directory does not say (a foreign scene)


@dataclass(frozen=True)
class SharedScene:
    folder: Path
    gaussians: int
    spz_bytes: int
    page_bytes: int
    antialiased: bool


def position_bits(cube_side: int) -> int:
    """SPZ fractional bits that resolve 1/64 of a voxel of a cube of ``cube_side`` voxels over
    [−1, 1] (12 bits at 128³, 14 at 512³), within the 24-bit positions' useful range."""
    side = cube_side if cube_side and cube_side > 0 else FINEST_CUBE
    return int(min(max(math.ceil(math.log2(POSITION_STEPS_PER_VOXEL * side / 2.0)), 8), 20))


def _world_to_scanner(scene_dir: Path) -> np.ndarray | None:
    try:
        matrix = read_manifest(scene_dir).get("world", {}).get("world_to_scanner")
    except CubecloudError:
        return None
    if matrix is None:
        return None
    matrix = np.asarray(matrix, dtype=np.float64)
    if matrix.shape != (4, 4) or not np.isfinite(matrix).all() or abs(np.linalg.det(matrix[:3, :3])) < 1e-12:
        return None
    return matrix


def _cube_side(work: Path) -> int:
    try:
        return int(read_manifest(Path(work) / "preprocess").get("geometry", {}).get("size", FINEST_CUBE))
    except (CubecloudError, TypeError, ValueError):
        return FINEST_CUBE


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def share_scene(work: Path, run_name: str | None, out: Path, force: bool = False) -> SharedScene:
    """Write OUT (see the module docstring) for ``run_name`` (default: ``splat``) of ``work``."""
    work, out = Path(work), Path(out)
    runs = find_splat_runs(work, report=False)
    name = run_name or "splat"
    if not runs:
        raise CubecloudError(f"{work} has no finished splat run: train one with `cubecloud run SCAN -o {work}`")
    if name not in runs:
        raise CubecloudError(f"{work} has no finished run {name}: choose --run from {', '.join(runs)}")
    if out.exists() and not force:
        raise CubecloudError(f"{out} exists: pass --force to replace it, or choose another folder with -o")
    run = load_run(work, name)
    gaussians = run.gaussians().baked()
    scene_dir = resolve_scene(work, run)
    cameras = read_colmap_model(scene_dir, export_remake(scene_dir)).cameras
    spz = encode_spz(gaussians, run.antialias, position_bits(_cube_side(work)))
    info = page_info(page_camera(cameras, 0), _world_to_scanner(scene_dir), run.antialias, gaussians.log_scales.numpy())
    scalar = run.scalar_gaussians()
    block = None
    if scalar is not None:  # the page recolours it under any transfer function, as `cubecloud view` does
        block = scalar_block(DrawnValues.of(scalar))
        intensity_map = read_intensity_map(work)
        info["scalar"] = scalar_info(
            transfer_presets(scalar, intensity_map), ct_window(intensity_map), scalar.chord_lengths
        )
    page = render_page(spz, info, block).encode("utf-8")
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".partial", dir=out.parent))
    staging.chmod(0o777 & ~_umask())  # mkdtemp's 0700 would keep the folder from whoever it is shared with
    try:
        (staging / SPZ_FILE).write_bytes(spz)
        (staging / PAGE_FILE).write_bytes(page)
        if out.exists():
            retired = out.parent / f".{out.name}.replaced"
            shutil.rmtree(retired, ignore_errors=True)
            out.rename(retired)
            staging.rename(out)
            shutil.rmtree(retired, ignore_errors=True)
        else:
            staging.rename(out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return SharedScene(out, len(gaussians), len(spz), len(page), run.antialias)
