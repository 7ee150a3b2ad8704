"""Rasterizer speed: forward + backward of one view, the numba CPU kernel against the plain
PyTorch path, on a random scene of Gaussians filling the volume's cube.

    python bench/raster.py                       # 50k Gaussians, 128² (the issue's target scene)
    python bench/raster.py --gaussians 200000 --resolution 256
    python bench/raster.py --cloud work/export/points3D.ply   # the exported Cube-Cloud, as initialised
    python bench/raster.py --antialias           # through the 2D Mip filter (its opacity factor and backward)
    python bench/raster.py --skip-torch --split  # and where the numba frame's time goes, part by part

Prints milliseconds per forward + backward (median of --repeats, after a warm-up that also
compiles the kernels), the split between projection, compositing forward and backward, and the
useful (Gaussian, pixel) pairs per second: pairs with α ≥ 1/255 that were blended. --split times
each compiled part inside the measured frames (projection forward and backward, splat boxes,
binning, compositing kernels, per-Gaussian sums); what is left is torch's autograd, its
operators and the array conversions around the kernels.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from cubecloud_cli.cameras import OrbitSpec, orbit_cameras
from cubecloud_cli.core.runtime import keep_freed_memory
from cubecloud_cli.raster import composite, project, splat_pairs
from cubecloud_cli.raster.cpu.autograd import composite_cpu, project_cpu
from cubecloud_cli.raster.pairs import MAX_ALPHA, MIN_ALPHA


def random_scene(count: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    spacing = (8.0 / count) ** (1.0 / 3.0)  # mean distance between neighbours in the cube
    means = torch.rand(count, 3, generator=g) * 1.8 - 0.9
    log_scales = torch.log(spacing * (0.3 + 0.4 * torch.rand(count, 3, generator=g)))
    quaternions = torch.randn(count, 4, generator=g)
    opacities = 0.05 + 0.9 * torch.rand(count, generator=g)
    colours = torch.rand(count, 1, generator=g)
    return means, log_scales, quaternions, opacities, colours


def cloud_scene(path, count: int, seed: int = 0):
    """Gaussians initialised from an exported point cloud as `splat` does (neighbour scales,
    opacity 0.1), ``count`` of its points drawn at random."""
    import numpy as np

    from cubecloud_cli.scene import read_point_cloud_ply
    from cubecloud_cli.splat import gaussians_from_points

    xyz, rgb, _ = read_point_cloud_ply(path)
    if count < len(xyz):
        keep = np.random.default_rng(seed).choice(len(xyz), count, replace=False)
        xyz, rgb = xyz[keep], rgb[keep]
    gaussians = gaussians_from_points(xyz, rgb[:, :1] / 255.0)
    return gaussians.means, gaussians.log_scales, gaussians.quaternions, gaussians.opacities(), gaussians.colours()


def useful_pairs(projected, opacities, width, height) -> int:
    pairs = splat_pairs(projected, width, height)
    dx = (pairs.pixel % width).float() + 0.5 - projected.means2d[pairs.gaussian, 0].detach()
    dy = (
        torch.div(pairs.pixel, width, rounding_mode="floor").float()
        + 0.5
        - projected.means2d[pairs.gaussian, 1].detach()
    )
    conic = projected.conics[pairs.gaussian].detach()
    power = 0.5 * (conic[:, 0] * dx * dx + conic[:, 2] * dy * dy) + conic[:, 1] * dx * dy
    alpha = torch.clamp(opacities[pairs.gaussian] * torch.exp(-power), max=MAX_ALPHA)
    return int((alpha >= MIN_ALPHA).sum())


# The compiled parts of a numba frame, as cubecloud_cli.raster.cpu.autograd calls them (module, name), and
# what the split calls them.
FRAME_PARTS = (
    ("projection_kernels", "project_forward", "projection forward"),
    ("binning", "splat_boxes", "splat boxes"),
    ("binning", "bin_tiles", "binning"),
    ("compositing", "forward", "compositing forward"),
    ("compositing", "backward", "compositing backward"),
    ("binning", "sum_per_gaussian", "per-Gaussian sums"),
    ("projection_kernels", "project_backward", "projection backward"),
)


def timed_parts(splits: dict[str, list[float]]) -> None:
    """Wrap each compiled part where ``cubecloud_cli.raster.cpu.autograd`` looks it up, adding its time in
    seconds to ``splits[label]`` at every call."""
    from cubecloud_cli.raster.cpu import autograd as cpu

    for module_name, name, label in FRAME_PARTS:
        module = getattr(cpu, module_name)
        part = getattr(module, name)

        def timed(*args, _part=part, _label=label):
            start = time.perf_counter()
            result = _part(*args)
            splits.setdefault(_label, []).append(time.perf_counter() - start)
            return result

        setattr(module, name, timed)


def print_split(splits: dict[str, list[float]]) -> None:
    """Median milliseconds of each part over the measured frames (the warm-up frame left out)."""
    parts = {label: 1000 * statistics.median(splits[label][1:]) for *_, label in FRAME_PARTS}
    frame = 1000 * statistics.median(splits["total"][1:])
    print("  split of the numba frame (medians, ms): " + ", ".join(f"{name} {ms:.2f}" for name, ms in parts.items()))
    print(f"  the rest (autograd, torch operators, conversions): {frame - sum(parts.values()):.2f} of {frame:.2f}")


def timed_frame(projector, compositor, scene, rotation, translation, focal, width, height, antialias=False):
    """One forward and backward of ``scene`` (means, log-scales, quaternions, opacities, colours,
    cloned as leaves) through a backend: seconds of the projection, the compositing and the
    backward, the projection, the image and the leaves (their ``.grad`` filled)."""
    inputs = [t.detach().clone().requires_grad_(True) for t in scene]
    means, log_scales, quaternions, opacities, colours = inputs
    start = time.perf_counter()
    projected = projector(
        means, torch.exp(log_scales), quaternions, rotation, translation, focal, width, height, antialias=antialias
    )
    projected_at = time.perf_counter()
    image, _ = compositor(projected, colours, projected.effective_opacities(opacities), width, height)
    forward_at = time.perf_counter()
    image.sum().backward()
    end = time.perf_counter()
    return (projected_at - start, forward_at - projected_at, end - forward_at), projected, image, inputs


def time_backend(projector, compositor, scene, cameras, width, repeats, antialias=False, splits=None):
    rotation = torch.tensor(cameras.rotations[0], dtype=torch.float32)
    translation = torch.tensor(cameras.translations[0], dtype=torch.float32)
    splits = {} if splits is None else splits
    splits.update({"project": [], "forward": [], "backward": [], "total": []})
    for _ in range(repeats + 1):
        seconds, projected, _, _ = timed_frame(
            projector, compositor, scene, rotation, translation, float(cameras.focal), width, width, antialias
        )
        for key, value in zip(("project", "forward", "backward", "total"), (*seconds, sum(seconds))):
            splits[key].append(value)
    times = {key: 1000 * statistics.median(splits[key][1:]) for key in ("project", "forward", "backward", "total")}
    times["fastest"] = 1000 * min(splits["total"][1:])
    return times, projected


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--gaussians", type=int, default=50_000)
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--skip-torch", action="store_true", help="time only the numba kernel")
    parser.add_argument("--cloud", help="an exported points3D.ply to initialise the scene from (default: random)")
    parser.add_argument(
        "--antialias", action="store_true", help="project through the 2D Mip filter, as anti-aliased training does"
    )
    parser.add_argument("--split", action="store_true", help="time each compiled part of the numba frame")
    args = parser.parse_args()
    keep_freed_memory()  # as training does (Runtime.apply): freed arrays are reused, not re-faulted

    scene = cloud_scene(args.cloud, args.gaussians) if args.cloud else random_scene(args.gaussians)
    cameras = orbit_cameras(OrbitSpec(views=2, resolution=args.resolution))
    print(
        f"{len(scene[0])} Gaussians ({'from ' + args.cloud if args.cloud else 'random'}), {args.resolution}² view, {torch.get_num_threads()} threads, "
        f"{'2D Mip filter' if args.antialias else '0.3 px² dilation'}; median of {args.repeats} forward + backward passes"
    )
    results = {}
    numba_splits: dict[str, list[float]] = {}
    if args.split:
        timed_parts(numba_splits)
    for name, projector, compositor in (("numba", project_cpu, composite_cpu), ("torch", project, composite)):
        if name == "torch" and args.skip_torch:
            continue
        times, projected = time_backend(
            projector,
            compositor,
            scene,
            cameras,
            args.resolution,
            args.repeats if name == "numba" else max(3, args.repeats // 5),
            args.antialias,
            numba_splits if name == "numba" else None,
        )
        results[name] = times
        print(
            f"  {name:<6} total {times['total']:7.2f} ms  (project {times['project']:.2f}, "
            f"composite forward {times['forward']:.2f}, backward {times['backward']:.2f}; fastest frame {times['fastest']:.2f})"
        )
        if name == "numba" and args.split:
            print_split(numba_splits)
    pairs = useful_pairs(projected, projected.effective_opacities(scene[3]), args.resolution, args.resolution)
    print(
        f"  useful pairs (α ≥ 1/255): {pairs:,} -> {pairs / (results['numba']['total'] / 1000) / 1e6:.1f} M pairs/s (numba, fwd+bwd; "
        f"{pairs / (results['numba']['fastest'] / 1000) / 1e6:.1f} M/s in the fastest frame)"
    )
    if "torch" in results:
        print(
            f"  speed-up of numba over the plain PyTorch path: {results['torch']['total'] / results['numba']['total']:.1f}x"
        )


if __name__ == "__main__":
    main()
