"""Training speed of `cubecloud splat`: iterations per second on an exported scene, and where an
iteration's time goes (render forward, loss, backward, optimizer, densification).

    cubecloud run -o work                          # makes work/export (fast preset: 128²)
    python bench/splat.py work/export              # 300 iterations of the fast preset's schedule
    python bench/splat.py work/export --iterations 300 --schedule-iterations 7000
    python bench/splat.py work/export --preset fast --threads 1 --iterations 600 --profile 100
    python bench/splat.py scalar/export --preset fast --scalar --iterations 600   # after run --scalar

Densification follows the schedule of --schedule-iterations (the preset's length), so the first
few hundred iterations measured here are those of a real run: from the initial cloud, before the
first densification step grows or prunes it. --preset takes the splat settings of a preset (the
anti-aliasing, the budget, the schedule's length); --threads N sets numba's and torch's threads
(1: a run as `cubecloud run` trains it beside the baseline on 2 cores); --profile N runs N more
iterations under cProfile and prints where their time went.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from cubecloud_cli.core.runtime import keep_freed_memory
from cubecloud_cli.presets import PRESET_NAMES, resolve, resolve_scalar_run
from cubecloud_cli.scene import read_point_cloud_ply
from cubecloud_cli.splat.densify import strategy_for
from cubecloud_cli.splat.gaussians import gaussians_from_points
from cubecloud_cli.splat.scalar_gaussians import scalar_gaussians_from_points
from cubecloud_cli.splat.settings import SplatSettings
from cubecloud_cli.splat.trainer import SplatTrainer, render
from cubecloud_cli.splat.training_views import load_scene


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene", type=Path, help="an export directory (images.npy, sparse/0, points3D.ply)")
    parser.add_argument("--iterations", type=int, default=300)
    parser.add_argument(
        "--schedule-iterations", type=int, default=2000, help="the run length the schedule is scaled to"
    )
    parser.add_argument("--max-gaussians", type=int, default=200_000)
    parser.add_argument("--preset", choices=PRESET_NAMES, help="the preset's splat settings (its length too)")
    parser.add_argument("--threads", type=int, help="numba's and torch's threads (default: theirs)")
    parser.add_argument("--profile", type=int, default=0, metavar="N", help="N more iterations under cProfile")
    parser.add_argument(
        "--scalar",
        action="store_true",
        help="a scalar scene (splat --scalar) on an export with a transfer-function set, its values held to "
        "WORK/preprocess/volume.npy; with --preset, run --scalar's length and budget",
    )
    parser.add_argument(
        "--no-chord-lengths", action="store_true", help="with --scalar: one optical length for every direction"
    )
    args = parser.parse_args()
    keep_freed_memory()  # as every stage's Runtime.apply does
    if args.threads:
        import numba

        numba.set_num_threads(args.threads)
        torch.set_num_threads(args.threads)

    scene = load_scene(args.scene, 1, every_transfer=args.scalar)
    xyz, rgb, extras = read_point_cloud_ply(args.scene / "points3D.ply")
    scalar = resolve_scalar_run(args.preset, "splat", {}) if args.scalar and args.preset else {"scalar": args.scalar}
    scalar = {**scalar, "chord_lengths": not args.no_chord_lengths}
    if args.preset:
        settings = SplatSettings(**resolve("splat", args.preset, scalar))
    else:
        settings = SplatSettings(iterations=args.schedule_iterations, max_gaussians=args.max_gaussians, **scalar)
    if args.scalar:
        gaussians = scalar_gaussians_from_points(xyz, extras["intensity"], scene.transfers, settings.chord_lengths)
    else:
        gaussians = gaussians_from_points(xyz, rgb[:, :1] / 255.0)
    trainer = SplatTrainer(gaussians, scene, settings, torch.device("cpu"), strategy_for(settings, scene.extent))
    if args.scalar:
        trainer.scan_values = torch.from_numpy(np.load(args.scene.parent / "preprocess" / "volume.npy"))
    print(
        f"{scene.cameras.width}² views, {len(trainer.gaussians)} initial Gaussians, {torch.get_num_threads()} threads, "
        f"rasterizer: {trainer.rasterizer.description}"
    )
    trainer.step()  # compiles the kernels
    started = time.perf_counter()
    for _ in range(args.iterations):
        trainer.step()
    elapsed = time.perf_counter() - started
    print(
        f"  training: {args.iterations / elapsed:.1f} it/s over {args.iterations} iterations "
        f"({len(trainer.gaussians)} Gaussians at the end)"
    )
    if args.profile:
        profiler = cProfile.Profile()
        started = time.perf_counter()
        profiler.enable()
        for _ in range(args.profile):
            trainer.step()
        profiler.disable()
        per_step = 1000 * (time.perf_counter() - started) / args.profile
        print(f"  {args.profile} more iterations under cProfile: {per_step:.1f} ms each; by own time:")
        pstats.Stats(profiler).sort_stats("tottime").print_stats(20)

    trainer.draw_under_first_transfer()  # a scalar scene: its images' own transfer function
    splits = {"render forward": [], "loss": [], "backward": [], "optimizer": []}
    for _ in range(30):
        view = trainer.next_view()
        t0 = time.perf_counter()
        rendered = render(trainer.gaussians, scene, view, trainer.sh_degree, trainer.rasterizer, retain=True)
        t1 = time.perf_counter()
        loss = trainer.loss(rendered.image, trainer.images[view])  # with a scalar scene's value anchor
        t2 = time.perf_counter()
        loss.backward()
        t3 = time.perf_counter()
        trainer.optimizer.step()
        trainer.optimizer.zero_grad(set_to_none=True)
        t4 = time.perf_counter()
        for key, value in zip(splits, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
            splits[key].append(value)
    parts = ", ".join(f"{key} {1000 * statistics.median(values):.1f}" for key, values in splits.items())
    print(f"  one iteration at {len(trainer.gaussians)} Gaussians, ms (median of 30): {parts}")


if __name__ == "__main__":
    main()
