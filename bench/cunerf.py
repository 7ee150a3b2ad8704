"""Time–PSNR curves of the two cunerf models, seconds per 1000 iterations and peak memory.

Each model trains in a fresh Python process (so its peak RSS is its own) on the bundled abdomen
CT preprocessed to --size³ (128³ by default), with a preset's settings for that model (--preset). At
intervals of training time it pauses the clock and scores the field on a fixed random sample
of voxels (3D PSNR estimated over all voxels and over the body), so the curve costs the same
to draw for both models; the grid model is also scored on the whole volume at the end.

    python bench/cunerf.py                            # fast (full preset) and cunerf (10 min)
    python bench/cunerf.py --models fast --size 64
    python bench/cunerf.py --models cunerf --seconds 1800 --device cuda
    python bench/cunerf.py --models fast --train-scale 2    # zero-shot ×2 super-resolution
    python bench/cunerf.py --models cunerf --preset paper --size 512 --seconds 120   # the paper's rate
    python bench/cunerf.py --models cunerf --preset paper --size 512 --stop-at 4000 --seconds 1e9 \
        --precision bf16 --bake-slices 8 --device cuda    # issue 54: the MLP in bfloat16, and its 512³ bake

With --bake-slices K the cunerf model also times the test render of K middle x-slices of the
volume (air skipped, as the stage does) and projects the whole bake from it.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

CHILD = r"""
import json, math, resource, sys, time
import numpy as np, torch
from cubecloud_cli.cunerf.supervision import TrainingVoxels, holdout_slices, voxel_centres
from cubecloud_cli.cunerf.model import CubeModel, render_many
from cubecloud_cli.cunerf.settings import CunerfSettings
from cubecloud_cli.cunerf.training import Trainer
from cubecloud_cli.cunerf.grid_init import initialise_from_volume
from cubecloud_cli.cunerf.api import CunerfField
from cubecloud_cli.core.runtime import resolve_device
from cubecloud_cli.numerics.metrics import psnr, volume_metrics
from cubecloud_cli.presets import resolve_cunerf

volume_path, model_name, seconds, points, eval_every, device_name, iterations, train_scale, preset, grid_init, precision, bake_slices, stop_at, profile_steps = sys.argv[1:15]
train_scale = int(train_scale)
device = resolve_device(device_name)
volume = np.load(volume_path)
size = volume.shape[0]
overrides = {"iterations": int(iterations)} if int(iterations) > 0 else {}
overrides["train_scale"] = train_scale
if model_name == "fast":
    overrides["grid_init"] = grid_init
overrides["precision"] = precision
settings = CunerfSettings(**resolve_cunerf(preset, model_name, overrides))
torch.manual_seed(0)
model = CubeModel(settings.field_config(size), settings.render_config(size)).to(device)
model.set_precision(settings.precision)
held = holdout_slices(volume, settings.holdout, train_scale)
voxels = TrainingVoxels(torch.from_numpy(volume).to(device), train_scale, held, settings.body_fraction)
if settings.grid_init == "volume":
    initialise_from_volume(model, voxels)
trainer = Trainer(model, voxels, settings, torch.Generator(device=device).manual_seed(0))
rng = np.random.default_rng(0)
sample = rng.integers(0, size, (int(points), 3))
truth = volume[sample[:, 0], sample[:, 1], sample[:, 2]]
centres = voxel_centres(torch.from_numpy(sample).to(device), size)

def score():
    predicted = render_many(model, centres, 8192, generator=torch.Generator(device=device).manual_seed(0)).cpu().numpy()
    return psnr(truth, predicted), psnr(truth, predicted, truth > 0)

budget, every = float(seconds), float(eval_every)
next_eval = every
print(json.dumps({"event": "start", "model": model_name, "settings": settings.as_dict(), "device": str(device)}), flush=True)
p, pb = score()
print(json.dumps({"event": "point", "iteration": 0, "train_s": 0.0, "loss": float("nan"), "psnr_est": p, "psnr_body_est": pb}), flush=True)
stop = int(stop_at) or settings.iterations
while trainer.iteration < stop and trainer.elapsed_s < budget:
    trainer.step()
    if trainer.elapsed_s >= next_eval or trainer.iteration == stop:
        next_eval += every
        trainer.flush_losses()
        loss = trainer.smoothed_loss
        p, pb = score()
        print(json.dumps({"event": "point", "iteration": trainer.iteration, "train_s": trainer.elapsed_s,
                          "loss": loss, "psnr_est": p, "psnr_body_est": pb}), flush=True)
trainer.flush_losses()
final = {"event": "end", "model": model_name, "precision": settings.precision, "iterations": trainer.iteration, "train_s": trainer.elapsed_s,
         "s_per_1000": 1000 * trainer.elapsed_s / max(trainer.iteration, 1),
         "parameters": sum(p.numel() for p in model.parameters())}
if model_name == "fast":
    start = time.perf_counter()
    field = CunerfField(model, size, np.eye(4), voxels.occupancy())
    recon = field.bake(size)
    final["bake_s"] = time.perf_counter() - start
    final.update({f"{k}_3d": v for k, v in volume_metrics(volume, recon).items()})
    if train_scale > 1:
        # The baseline: trilinear interpolation between the training voxels (every s-th).
        low = torch.from_numpy(volume[::train_scale, ::train_scale, ::train_scale].copy())[None, None]
        n = low.shape[-1]
        up = torch.nn.functional.interpolate(low, size=(n - 1) * train_scale + 1, mode="trilinear", align_corners=True)[0, 0]
        baseline = np.pad(up.numpy(), [(0, size - up.shape[0])] * 3, mode="edge")
        final.update({f"trilinear_{k}_3d": v for k, v in volume_metrics(volume, baseline).items()})
if model_name == "cunerf" and int(bake_slices) > 0:
    # The stage's bake, timed over the middle slices (more body than the average slice).
    from cubecloud_cli.cunerf.api import grid_centres
    slices = int(bake_slices)
    low = (size - slices) // 2
    keep = voxels.occupancy().occupied
    centres = grid_centres(size, device, (low, low + slices))
    render_many(model, centres[:4096], keep=keep)  # warm-up
    if device.type == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    render_many(model, centres, keep=keep, generator=torch.Generator(device=device).manual_seed(0))
    if device.type == "cuda":
        torch.cuda.synchronize()
    final["bake_slices"] = slices
    final["bake_slices_s"] = time.perf_counter() - start
    final["bake_projected_s"] = final["bake_slices_s"] * size / slices
if int(profile_steps) > 0 and device.type == "cuda":
    # Where a step's time goes: the GPU's kernels against the wall clock (issue 54).
    from torch.profiler import ProfilerActivity, profile
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        start = time.perf_counter()
        for _ in range(int(profile_steps)):
            trainer.step()
        trainer.flush_losses()
        torch.cuda.synchronize()
        wall = time.perf_counter() - start
    events = prof.key_averages()
    gpu_us = sum(e.self_device_time_total for e in events)
    launches = sum(e.count for e in events if e.key in ("cudaLaunchKernel", "cuLaunchKernel", "cudaLaunchKernelExC"))
    final["profile"] = {"steps": int(profile_steps), "wall_ms_per_step": 1000 * wall / int(profile_steps),
                        "gpu_ms_per_step": gpu_us / 1000 / int(profile_steps), "launches_per_step": launches / int(profile_steps)}
    print(events.table(sort_by="self_device_time_total", row_limit=14), file=sys.stderr, flush=True)
final["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
if device.type == "cuda":
    final["peak_gpu_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
print(json.dumps(final), flush=True)
"""


def preprocessed_volume(work: Path, size: int) -> Path:
    from cubecloud_cli.preprocess import PreprocessSettings, preprocess_scan
    from cubecloud_cli.sample_data import sample_ct_path

    volume = work / "preprocess" / "volume.npy"
    if not volume.exists():
        preprocess_scan(sample_ct_path(), work, PreprocessSettings(size=size))
    return volume


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", nargs="+", default=["fast", "cunerf"], choices=["fast", "cunerf"])
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--seconds", type=float, default=600.0, help="training-time budget per model")
    parser.add_argument("--iterations", type=int, default=0, help="override the preset's iterations")
    parser.add_argument(
        "--preset",
        default="fast",
        choices=["fast", "balanced", "paper"],
        help="whose cunerf settings each model trains with (the volume size is --size)",
    )
    parser.add_argument("--points", type=int, default=32768, help="voxels scored at each curve point")
    parser.add_argument("--eval-every", type=float, default=20.0, help="seconds of training between points")
    parser.add_argument("--device", default="cpu")
    parser.add_argument(
        "--train-scale",
        type=int,
        default=1,
        help="zero-shot super-resolution: train on every s-th voxel, score on all, "
        "beside trilinear interpolation of the same voxels",
    )
    parser.add_argument("--grid-init", default="random", choices=["random", "volume"], help="the fast model's start")
    parser.add_argument(
        "--precision", default="float32", choices=["float32", "tf32", "bf16"], help="the MLP's arithmetic"
    )
    parser.add_argument(
        "--stop-at", type=int, default=0, help="stop at this iteration, on the preset's schedule (0: its end)"
    )
    parser.add_argument("--profile-steps", type=int, default=0, help="on CUDA: profile this many more steps")
    parser.add_argument("--bake-slices", type=int, default=0, help="cunerf model: time the bake of this many x-slices")
    parser.add_argument("--work", type=Path, default=None, help="reuse this work directory's preprocess/")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as temporary:
        work = args.work or Path(temporary) / "work"
        volume = preprocessed_volume(work, args.size)
        for model in args.models:
            command = [
                sys.executable,
                "-c",
                CHILD,
                str(volume),
                model,
                str(args.seconds),
                str(args.points),
                str(args.eval_every),
                args.device,
                str(args.iterations),
                str(args.train_scale),
                args.preset,
                args.grid_init,
                args.precision,
                str(args.bake_slices),
                str(args.stop_at),
                str(args.profile_steps),
            ]
            process = subprocess.Popen(command, stdout=subprocess.PIPE, text=True)
            assert process.stdout is not None
            print(
                f"\n== {model}, {args.preset} preset, on the bundled CT at {args.size}³ ({args.device}, {args.precision}, train scale {args.train_scale}) =="
            )
            print(f"{'iteration':>9} {'train s':>8} {'loss':>10} {'PSNR est':>9} {'body':>7}")
            for line in process.stdout:
                record = json.loads(line)
                if record["event"] == "point":
                    print(
                        f"{record['iteration']:>9} {record['train_s']:>8.1f} {record['loss']:>10.3e} "
                        f"{record['psnr_est']:>9.2f} {record['psnr_body_est']:>7.2f}",
                        flush=True,
                    )
                elif record["event"] == "end":
                    summary = {
                        k: (round(v, 4) if isinstance(v, float) else v) for k, v in record.items() if k != "event"
                    }
                    print("summary:", json.dumps(summary))
            if process.wait() != 0:
                raise SystemExit(f"the {model} run failed")


if __name__ == "__main__":
    main()
