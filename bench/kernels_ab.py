"""The compositing kernels of the working tree against those of a git revision, in one process:
the way the rasterizer's kernel changes were measured (docs/history/rasterizer-speed.md), where separate runs of
`bench/raster.py` swing with the host by more than the change.

    python bench/kernels_ab.py                          # HEAD against the working tree, bench frame
    python bench/kernels_ab.py --base HEAD~3 --threads 1
    python bench/kernels_ab.py --work work              # and 12 training views of a trained `fast` scene
    python bench/kernels_ab.py --whole-frame            # whole frames, as bench/raster.py times them

The revision's `cubecloud_cli` is copied under another name (git archive) into a cache folder, so
both import side by side. The inputs of the kernels (projection, boxes, binning) are computed
once, by the working tree; then the forward and backward kernels of each side run on the same
inputs, in the order base, new, new, base, for --rounds rounds. Prints the medians, the 10th
percentiles, their ratios (new / base: below 1 is faster) and whether both sides give the same
bits (image, transmittance, and the gradient rows they write).

--whole-frame times instead whole frames as `bench/raster.py` does (projection, boxes, binning,
both kernels, the per-Gaussian sums and autograd's work around them) through each side's
`raster.cpu`, on the bench frame and with --work on the trained views: for changes outside the two
kernels, whose gain a part's own timing can show and the frame not, and for changes to what the
kernels take (docs/history/rasterizer-speed.md).

Run it twice after changing a kernel: the first process compiles the new kernel, and a kernel
compiled in the process ran 4-8 % slower than one loaded from numba's cache (docs/history/rasterizer-speed.md).
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import numba
import numpy as np
import torch

REPOSITORY = Path(__file__).resolve().parent.parent
CACHE = REPOSITORY / "bench" / ".kernels_ab"  # ignored by git: copies of past revisions


def revision_package(revision: str) -> str:
    """Import name of ``cubecloud_cli`` at ``revision``, copied and renamed under CACHE."""
    commit = subprocess.run(
        ["git", "rev-parse", "--short=12", revision], cwd=REPOSITORY, check=True, capture_output=True, text=True
    ).stdout.strip()
    name = f"cubecloud_{commit}"
    folder = CACHE / commit
    if not (folder / name).is_dir():
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=folder) as scratch, tempfile.TemporaryFile() as archive:
            subprocess.run(["git", "archive", commit, "cubecloud_cli"], cwd=REPOSITORY, check=True, stdout=archive)
            archive.seek(0)
            with tarfile.open(fileobj=archive) as tar:
                tar.extractall(scratch, filter="data")
            unpacked, renamed = Path(scratch) / "cubecloud_cli", Path(scratch) / name
            for source in unpacked.rglob("*"):
                if source.is_file():
                    target = renamed / source.relative_to(unpacked)
                    target.parent.mkdir(parents=True, exist_ok=True)
                    if source.suffix == ".py":
                        target.write_text(source.read_text().replace("cubecloud_cli", name))
                    else:
                        target.write_bytes(source.read_bytes())
            # renamed whole once complete: an interrupted copy is never taken for a finished one
            renamed.rename(folder / name)
    sys.path.insert(0, str(folder))
    return name


def view_inputs(scene, view, seed):
    """What the compositing kernels take for ``view`` of ``scene`` (``raster.cpu.kernel_inputs``,
    computed by the working tree), and a random gradient of the image."""
    from cubecloud_cli.raster.cpu.autograd import kernel_inputs, project_cpu

    means, log_scales, quaternions, opacities, colours = scene
    rotation, translation, focal, width, height = view
    projected = project_cpu(
        means, torch.exp(log_scales), quaternions, rotation, translation, focal, width, height, 0.01
    )
    background = torch.zeros(colours.shape[1])
    offsets, entries, arrays, tiles_x = kernel_inputs(
        projected.means2d, projected.conics, colours, opacities, background, projected.covariances2d,
        projected.radii, projected.depths, width, height,
    )  # fmt: skip
    grad = np.random.default_rng(seed).standard_normal((width * height, colours.shape[1])).astype(np.float32)
    return offsets, entries, arrays, width, height, tiles_x, grad


def bench_scene():
    """``bench/raster.py``'s scene (means, log-scales, quaternions, opacities, colours) and its one
    view (rotation, translation, focal, width, height)."""
    sys.path.insert(0, str(REPOSITORY / "bench"))
    from raster import random_scene

    from cubecloud_cli.cameras import OrbitSpec, orbit_cameras

    cameras = orbit_cameras(OrbitSpec(views=2, resolution=128))
    rotation = torch.tensor(cameras.rotations[0], dtype=torch.float32)
    translation = torch.tensor(cameras.translations[0], dtype=torch.float32)
    return random_scene(50_000), [(rotation, translation, float(cameras.focal), 128, 128)]


def trained_scene(work: Path, views: int):
    """The splat trained in ``work`` as ``bench_scene`` gives its scene, and ``views`` of its
    training views, evenly spaced."""
    from cubecloud_cli.splat.gaussian_ply import read_gaussians_ply
    from cubecloud_cli.splat.training_views import load_scene

    gaussians = read_gaussians_ply(work / "splat" / "point_cloud.ply")
    scene = load_scene(work / "export")
    cameras = scene.cameras
    opacities = torch.sigmoid(gaussians.opacity_logits).reshape(-1)
    colours = gaussians.sh_dc[:, 0, :].contiguous()
    step = max(1, len(scene.train) // views)
    chosen = [scene.train[number] for number in range(0, len(scene.train), step)[:views]]
    poses = [
        (
            torch.tensor(cameras.rotations[index], dtype=torch.float32),
            torch.tensor(cameras.translations[index], dtype=torch.float32),
            float(cameras.focal),
            int(cameras.width),
            int(cameras.height),
        )
        for index in chosen
    ]
    return (gaussians.means, gaussians.log_scales, gaussians.quaternions, opacities, colours), poses


def whole_frame(cpu, scene, view):
    """One frame of ``view`` through ``cpu`` (a side's ``raster.cpu``) as ``bench/raster.py`` times
    it (``timed_frame``): seconds of the forward (projection and compositing) and of the backward,
    the image, and the scene's gradients."""
    from raster import timed_frame

    seconds, _, image, leaves = timed_frame(cpu.project_cpu, cpu.composite_cpu, scene, *view)
    return seconds[0] + seconds[1], seconds[2], image.detach(), [leaf.grad for leaf in leaves]


def abba(base_frames, new_frames, rounds: int) -> dict[tuple[str, str], list[float]]:
    """Milliseconds per frame of each side's forward and backward, round by round, in the order
    base, new, new, base; ``*_frames()`` runs a side over every frame, returning its seconds of
    forward and of backward."""
    times: dict[tuple[str, str], list[float]] = {
        (side, part): [] for side in ("base", "new") for part in ("fwd", "bwd")
    }
    for _ in range(rounds):
        for side, frames in (("base", base_frames), ("new", new_frames), ("new", new_frames), ("base", base_frames)):
            forward_seconds, backward_seconds = frames()
            times[(side, "fwd")].append(1000 * forward_seconds)
            times[(side, "bwd")].append(1000 * backward_seconds)
    return times


def revision_module(package: str, name: str, before_the_move: str):
    """A module of the revision's copy, by its name today or, in a revision from before the CPU
    kernels moved into ``raster/cpu/``, by the name it had then."""
    try:
        return importlib.import_module(f"{package}.{name}")
    except ModuleNotFoundError:
        return importlib.import_module(f"{package}.{before_the_move}")


def compare_whole_frames(label, base_cpu, new_cpu, scene, views, rounds: int) -> None:
    """Both sides' whole frames of every view, ABBA, after two rounds that are not timed."""
    same_image = same_grads = True
    for view in views:
        results = [whole_frame(cpu, scene, view) for cpu in (base_cpu, new_cpu, base_cpu, new_cpu)]
        (_, _, image_a, grads_a), (_, _, image_b, grads_b) = results[2:]
        same_image &= torch.equal(image_a, image_b)
        same_grads &= all(torch.equal(a, b) for a, b in zip(grads_a, grads_b))

    def frames(cpu):
        seconds = np.sum([whole_frame(cpu, scene, view)[:2] for view in views], axis=0) / len(views)
        return tuple(seconds)

    times = abba(lambda: frames(base_cpu), lambda: frames(new_cpu), rounds)
    for side in ("base", "new"):
        times[(side, "frame")] = [f + b for f, b in zip(times[(side, "fwd")], times[(side, "bwd")])]
    report(label, times, (same_image, same_grads))


def same_bits(base, new, frames) -> tuple[bool, bool]:
    """Whether both sides' forward (image, transmittance) and backward (the gradient rows, and
    each Gaussian's stretch of them) agree bit for bit on every frame."""
    forward_same = backward_same = True
    for offsets, entries, arrays, width, height, tiles_x, grad in frames:
        results = []
        for kernels in (base, new):
            forward = kernels.forward(offsets, entries, *arrays, width, height, tiles_x)
            rows, gaussian_rows = kernels.backward(
                offsets, entries, *arrays, width, height, tiles_x, *forward[1:], grad
            )
            results.append((forward[0], forward[1], rows, gaussian_rows))
        (image_a, t_a, rows_a, owners_a), (image_b, t_b, rows_b, owners_b) = results
        forward_same &= np.array_equal(image_a, image_b) and np.array_equal(t_a, t_b)
        backward_same &= np.array_equal(owners_a, owners_b) and np.array_equal(rows_a, rows_b)
    return forward_same, backward_same


def timed_rounds(base, new, frames, rounds: int) -> dict[tuple[str, str], list[float]]:
    """Milliseconds per frame of each side's forward and backward kernels, ABBA."""

    def run(kernels):
        forward_time = backward_time = 0.0
        for offsets, entries, arrays, width, height, tiles_x, grad in frames:
            start = time.perf_counter()
            forward = kernels.forward(offsets, entries, *arrays, width, height, tiles_x)
            middle = time.perf_counter()
            kernels.backward(offsets, entries, *arrays, width, height, tiles_x, *forward[1:], grad)
            forward_time += middle - start
            backward_time += time.perf_counter() - middle
        return forward_time / len(frames), backward_time / len(frames)

    return abba(lambda: run(base), lambda: run(new), rounds)


def report(label: str, times, same: tuple[bool, bool]) -> None:
    print(f"{label}: same bits forward {same[0]}, backward {same[1]}")
    for part, name in (("fwd", "forward"), ("bwd", "backward"), ("frame", "frame")):
        if ("base", part) not in times:
            continue
        base, new = times[("base", part)], times[("new", part)]
        median_base, median_new = statistics.median(base), statistics.median(new)
        low_base, low_new = sorted(base)[len(base) // 10], sorted(new)[len(new) // 10]
        print(
            f"  {name:8s} median {median_base:.3f} -> {median_new:.3f} ms ({median_new / median_base:.3f}); "
            f"10th percentile {low_base:.3f} -> {low_new:.3f} ms ({low_new / low_base:.3f})"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--base", default="HEAD", help="the git revision to compare against (default: HEAD)")
    parser.add_argument("--threads", type=int, default=2, help="numba's and torch's threads")
    parser.add_argument("--rounds", type=int, default=60, help="ABBA rounds on the bench frame (a quarter on --work)")
    parser.add_argument("--work", type=Path, help="a `cubecloud run` work directory: also its trained splat's views")
    parser.add_argument("--views", type=int, default=12, help="training views of --work")
    parser.add_argument(
        "--whole-frame",
        action="store_true",
        help="time whole frames (projection to per-Gaussian sums, autograd included) instead of the kernels",
    )
    args = parser.parse_args()
    numba.set_num_threads(args.threads)
    torch.set_num_threads(args.threads)

    from cubecloud_cli.core.runtime import keep_freed_memory

    keep_freed_memory()
    print(f"{args.base} (base) against the working tree (new), {args.threads} threads")
    scenes = [("bench frame (50 000 random Gaussians, 128²)", *bench_scene(), args.rounds)]
    if args.work:
        scenes.append(
            (
                f"{args.views} training views of {args.work}",
                *trained_scene(args.work, args.views),
                max(3, args.rounds // 4),
            )
        )
    package = revision_package(args.base)
    if args.whole_frame:
        base_cpu = revision_module(package, "raster.cpu.autograd", "raster.cpu")
        new_cpu = importlib.import_module("cubecloud_cli.raster.cpu.autograd")
        for label, scene, views, rounds in scenes:
            compare_whole_frames(f"whole frames, {label}", base_cpu, new_cpu, scene, views, rounds)
        return
    new = importlib.import_module("cubecloud_cli.raster.cpu.compositing")
    base = revision_module(package, "raster.cpu.compositing", "raster.cpu_kernels")
    if "slots" in inspect.signature(base.backward.py_func).parameters:
        sys.exit(
            f"{args.base}'s compositing backward still takes the binning's slots (its gradient rows were "
            "numbered before the forward): compare the two with --whole-frame"
        )
    for label, scene, views, rounds in scenes:
        frames = [view_inputs(scene, view, number) for number, view in enumerate(views)]
        report(label, timed_rounds(base, new, frames, rounds), same_bits(base, new, frames))


if __name__ == "__main__":
    main()
