"""Export timings and the step-size trade of the renderer.

Three measurements on the bundled abdomen CT (preprocessed on the fly at --size unless --work
names a work directory that has it):

* reference renders: --views views at --resolution² of each image model from the preprocessed
  volume, with views per second;
* the export stage as `cubecloud export` runs it (needs a trained cunerf/ in --work): the time
  split of bake, CuNeRF renders, reference renders, point cloud and writing;
* --steps: the ray step (in voxels) against time and PSNR to a fine reference rendered at a
  quarter voxel, the speed-accuracy trade of --step.

    python bench/export.py --size 256 --resolution 256                # the 30 s target
    python bench/export.py --work /tmp/w --stage                     # the stage's time split
    python bench/export.py --size 128 --resolution 128 --steps 0.5,1,2
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import torch


def preprocessed_volume(work: Path | None, size: int) -> tuple[np.ndarray, dict]:
    from cubecloud_cli.preprocess import PreprocessSettings, preprocess_scan
    from cubecloud_cli.sample_data import sample_ct_path

    if work is None or not (work / "preprocess" / "manifest.json").is_file():
        work = work or Path(tempfile.mkdtemp(prefix="bench-export-"))
        preprocess_scan(sample_ct_path(), work, PreprocessSettings(size=size))
    manifest = json.loads((work / "preprocess" / "manifest.json").read_text())
    return np.load(work / "preprocess" / "volume.npy"), manifest


def time_renders(volume: np.ndarray, manifest: dict, args) -> None:
    from cubecloud_cli.cameras import OrbitSpec, orbit_cameras
    from cubecloud_cli.render import GridField, ImageModel, render_views
    from cubecloud_cli.transfer.tissue_presets import resolve_transfer

    size = volume.shape[0]
    cameras = orbit_cameras(OrbitSpec(views=args.views, resolution=args.resolution))
    transfer = resolve_transfer("tissue", manifest.get("intensity"))
    field = GridField(volume)
    print(
        f"reference renders: {args.views} views at {args.resolution}² from {size}³, step 1 voxel, "
        f"{torch.get_num_threads()} threads"
    )
    for kind in args.models.split(","):
        model = ImageModel(kind, transfer, step=2.0 / size)
        start = time.perf_counter()
        render_views(field, cameras, model)
        seconds = time.perf_counter() - start
        print(f"  {kind:<6} {seconds:7.2f} s   {args.views / seconds:6.2f} views/s")


def step_trade(volume: np.ndarray, manifest: dict, args) -> None:
    from cubecloud_cli.cameras import OrbitSpec, orbit_cameras
    from cubecloud_cli.numerics.metrics import psnr
    from cubecloud_cli.render import GridField, ImageModel, render_views
    from cubecloud_cli.transfer.tissue_presets import resolve_transfer

    size = volume.shape[0]
    cameras = orbit_cameras(OrbitSpec(views=args.views, resolution=args.resolution))
    transfer = resolve_transfer("tissue", manifest.get("intensity"))
    field = GridField(volume)
    fine = render_views(field, cameras, ImageModel("dvr", transfer, step=0.25 * 2.0 / size))
    print(f"dvr step trade ({args.views} views at {args.resolution}² from {size}³; PSNR against step 0.25 voxel)")
    for step in (float(s) for s in args.steps.split(",")):
        start = time.perf_counter()
        images = render_views(field, cameras, ImageModel("dvr", transfer, step=step * 2.0 / size))
        seconds = time.perf_counter() - start
        print(
            f"  step {step:4.2f} voxel  {seconds:7.2f} s   PSNR {psnr(fine, images):6.2f} dB "
            f"(foreground {psnr(fine, images, fine > 0):6.2f} dB)"
        )


def time_stage(work: Path, args) -> None:
    from cubecloud_cli.export import ExportSettings, export_scene

    settings = ExportSettings(views=args.views, resolution=args.resolution, max_points=args.points)
    start = time.perf_counter()
    manifest = export_scene(work, settings, force=True)
    total = time.perf_counter() - start
    timings = manifest["timings_s"]
    if manifest.get("resumed", {}).get("views") or manifest.get("resumed", {}).get("bake"):
        print("warning: this run reused work of an interrupted export; delete WORK/.export.partial for clean timings")
    print(
        f"export stage on {work} ({args.views} views at {args.resolution}², {manifest['metrics']['points']} points): {total:.1f} s"
    )
    for phase in ("load", "bake", "render_images", "render_reference", "point_cloud", "write", "hash_outputs"):
        print(f"  {phase:<17} {timings.get(phase, 0.0):7.2f} s")
    cunerf_part = timings["bake"] + timings["render_images"] + timings["point_cloud"]
    print(f"  CuNeRF renders + point cloud (bake, images, points): {cunerf_part:.1f} s")
    print(
        f"  CuNeRF vs reference on test views: PSNR {manifest['metrics']['cunerf_vs_reference_psnr']:.2f} dB, "
        f"SSIM {manifest['metrics']['cunerf_vs_reference_ssim']:.4f}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, help="work directory (with preprocess/, and cunerf/ for --stage)")
    parser.add_argument("--size", type=int, default=256, help="preprocess size when --work has none")
    parser.add_argument("--views", type=int, default=60)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--models", default="dvr,mip,slice", help="image models to time")
    parser.add_argument("--steps", default="", help="comma-separated ray steps in voxels for the trade")
    parser.add_argument("--stage", action="store_true", help="time the whole export stage (needs cunerf/)")
    parser.add_argument("--points", type=int, default=100_000, help="--max-points for --stage")
    args = parser.parse_args()

    if args.stage:
        time_stage(args.work, args)
        return
    volume, manifest = preprocessed_volume(args.work, args.size)
    if args.steps:
        step_trade(volume, manifest, args)
    else:
        time_renders(volume, manifest, args)


if __name__ == "__main__":
    main()
