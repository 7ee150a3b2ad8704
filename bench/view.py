"""How long `cubecloud view` takes to show a scene: from the page being opened in a browser to the
first frame with the Gaussians drawn, on a 100k-Gaussian scene (issue 18's goal: a few seconds).

    python bench/view.py                        # a synthetic 100k-Gaussian work directory
    python bench/view.py --gaussians 300000
    python bench/view.py --work work            # a finished work directory (its splat run)
    python bench/view.py --detail 10            # the 10 % of the Gaussians that shape the picture most
    python bench/view.py --coarse 3000          # each page gets 3000 Gaussians first instead of 10 000
    python bench/view.py --query fixedDpr=0.5   # the canvas at half the resolution (viser's URL option)
    python bench/view.py --work work --trade    # what --detail costs: held-out PSNR at each detail
    python bench/view.py --work work --bytes    # also the bytes that reach the page, per load
    python bench/view.py --scalar --recolour 20 # a scalar (chord-length) scene: control change, and camera at rest, to colours sent, 20 times each


Chromium is driven over the DevTools protocol, and the page's frames are taken from a screencast
(the frames it draws anyway: polled screenshots made it draw more, which slowed it by seconds). The
clock starts when the page is asked to load. Two figures: the first frame with the scene in its
centre (the coarse set the viewer sends first, view/delivery.py), and the first frame with every
Gaussian, sorted and settled. The browser renders WebGL with whatever it has: on this project's
GPU-less machines that is SwiftShader, a CPU rasterizer, so the figures here bound what a desktop
browser with a GPU needs from above. The first page load of a fresh browser also compiles the
viewer's shaders and WebAssembly sorter; the later loads show the warm figure.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import socket
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from cubecloud_cli.splat.gaussian_ply import scalar_properties, write_gaussians_ply
from cubecloud_cli.splat.gaussians import Gaussians
from cubecloud_cli.splat.scalar_gaussians import ScalarGaussians
from cubecloud_cli.transfer.function import TransferFunction
from cubecloud_cli.view.browser import SETTLED_GREY_LEVELS, Chromium, background_in, frame_change
from cubecloud_cli.view.delivery import COARSE_GAUSSIANS
from cubecloud_cli.view.server import SceneViewer

WINDOW = (900, 700)  # the tests' and the README pictures' page size
SCENE_THRESHOLD = 40  # grey level above the black background
WHOLE_AFTER_FRAMES = 4  # frames after the full set was sent: it was drawn by the second in every run seen


def synthetic_work(directory: Path, count: int, seed: int = 0, scalar: bool = False) -> Path:
    """A work directory holding one finished splat run of ``count`` Gaussians filling a body-like
    ellipsoid, each about as large as its neighbours' spacing (as a trained scene's are)."""
    g = torch.Generator().manual_seed(seed)
    directions = torch.randn(count, 3, generator=g)
    directions /= directions.norm(dim=1, keepdim=True).clamp_min(1e-12)
    radii = torch.rand(count, 1, generator=g) ** (1.0 / 3.0)
    means = directions * radii * torch.tensor([0.8, 0.55, 0.9])
    spacing = (4.0 / count) ** (1.0 / 3.0)
    gaussians = Gaussians(
        means=means,
        log_scales=torch.log(spacing * (0.3 + 0.4 * torch.rand(count, 3, generator=g))),
        quaternions=torch.randn(count, 4, generator=g),
        opacity_logits=torch.logit(0.2 + 0.7 * torch.rand(count, generator=g)),
        sh_dc=(torch.rand(count, 1, 1, generator=g) - 0.5) / 0.28209479177387814,
        sh_rest=torch.zeros(count, 0, 1),
    )
    run = directory / "splat"
    run.mkdir(parents=True)
    if scalar:  # values over the whole range, each Gaussian about as opaque under tissue as above
        model = ScalarGaussians(
            gaussians.means, gaussians.log_scales, gaussians.quaternions,
            torch.logit(0.05 + 0.9 * torch.rand(count, generator=g)), torch.log(0.05 + 0.2 * torch.rand(count, generator=g)),
            TransferFunction(0.3, 0.9, 4.0), chord_lengths=True,
        )  # fmt: skip
        write_gaussians_ply(run / "point_cloud.ply", model.baked(), scalar_properties(model))
    else:
        write_gaussians_ply(run / "point_cloud.ply", gaussians)
    params = {"init": "synthetic", "scalar": scalar}
    (run / "manifest.json").write_text(json.dumps({"stage": "splat", "params": params}))
    return directory


RECOLOUR_CHOICES = (
    {"preset": "bone"},
    {"preset": "soft"},
    {"low": 0.4, "high": 0.5},
    {"opacity": 2.0},
    {"colour_map": "hot"},
    {"preset": "tissue", "opacity": 1.0, "colour_map": "grey"},
)


def time_recolours(viewer: SceneViewer, count: int) -> list[float]:
    """Milliseconds from each control change (set_transfer, as the page's control calls it) to the
    new colours and opacities handed to every open page's websocket."""
    times = []
    for index in range(count):
        start = time.perf_counter()
        viewer.set_transfer(**RECOLOUR_CHOICES[index % len(RECOLOUR_CHOICES)])
        times.append(1000.0 * (time.perf_counter() - start))
    return times


def time_camera_rests(viewer: SceneViewer, count: int) -> list[float]:
    """Milliseconds from a camera coming to rest (look_from, as view/camera_rest.py calls it) to
    a chord-length scene's opacities for it handed to every open page's websocket."""
    times = []
    for index in range(count):
        angle = 2.0 * np.pi * (index + 1) / (count + 1)
        position = 4.0 * viewer.scale * np.array([np.cos(angle), np.sin(angle), 0.3])
        start = time.perf_counter()
        viewer.look_from(position)
        times.append(1000.0 * (time.perf_counter() - start))
    return times


def scene_drawn(image: np.ndarray) -> bool:
    """The viewer's black background is in (the page starts light grey) and Gaussians are drawn in
    the middle of the window, away from the browser's notice and the controls."""
    height, width = image.shape[:2]
    middle = image[height // 4 : 3 * height // 4, width // 6 : width // 2 + width // 8].mean(axis=-1)
    return background_in(image) and float((middle > SCENE_THRESHOLD).mean()) > 0.02


def time_frames(
    browser: Chromium, url: str, viewer: SceneViewer, timeout_s: float = 300.0
) -> tuple[float, float, np.ndarray]:
    """Seconds from asking for the page to its first frame with the scene in it (the coarse set,
    when the scene is larger than that), and to its first frame with every Gaussian that the next
    frame repeats (sorted and settled), and that frame. From a screencast, each frame timed when
    it was drawn: the page is not made to draw extra frames."""
    first, coarse, candidate, since_all = None, None, None, 0
    with contextlib.closing(browser.frames(url, timeout_s)) as frames:
        for seconds, image in frames:
            if first is None and not scene_drawn(image):
                continue
            first = seconds if first is None else first
            if not viewer.delivery.pages_sent_all():
                coarse = image  # the last picture of the coarse set: the whole scene must differ
                continue
            since_all += 1
            # A full set that adds little to the coarse one (--detail near it) looks the same:
            # after a few frames any settled frame is the whole scene.
            if (
                coarse is not None
                and frame_change(image, coarse) < SETTLED_GREY_LEVELS
                and since_all < WHOLE_AFTER_FRAMES
            ):
                continue
            if candidate is not None and frame_change(image, candidate[1]) < SETTLED_GREY_LEVELS:
                return first, *candidate
            candidate = (seconds, image)
    raise SystemExit(f"the scene was not drawn whole within {timeout_s:.0f} s")


def detail_trade(work: Path, percents=(100, 50, 30, 10, 3)) -> None:
    """Held-out PSNR of the splat run drawn with each share of its Gaussians (importance_order),
    rendered by our rasterizer as eval renders it, against the export's reference renders."""
    from cubecloud_cli.core.artifacts import read_manifest
    from cubecloud_cli.eval.runs import SplatRun, load_scored_scene, resolve_scene
    from cubecloud_cli.numerics.metrics import psnr
    from cubecloud_cli.raster.backends import NUMBA
    from cubecloud_cli.splat.gaussian_ply import read_gaussians_ply
    from cubecloud_cli.splat.trainer import render_camera
    from cubecloud_cli.view.splats import detail_count, importance_order, view_splats

    run = SplatRun("splat", work / "splat", read_manifest(work / "splat"))
    scored = load_scored_scene(resolve_scene(work, run))
    scene = scored.scene
    gaussians = read_gaussians_ply(work / "splat" / "point_cloud.ply")
    orders = {
        "importance": torch.as_tensor(importance_order(view_splats(gaussians))),
        "random": torch.randperm(len(gaussians), generator=torch.Generator().manual_seed(0)),
    }
    print(
        f"{run.name}: {len(gaussians)} Gaussians, held-out PSNR over {len(scene.test)} views, by the order they are dropped in"
    )
    for percent in percents:
        count = detail_count(len(gaussians), percent)
        line = [f"detail {percent:>3} % ({count:>6} Gaussians):"]
        for name, order in orders.items():
            keep = order[:count]
            subset = Gaussians(*(None if t is None else t[keep] for t in (
                gaussians.means, gaussians.log_scales, gaussians.quaternions, gaussians.opacity_logits,
                gaussians.sh_dc, gaussians.sh_rest, gaussians.smoothing)))  # fmt: skip
            scores = []
            with torch.no_grad():
                for view in scene.test:
                    image = render_camera(subset, scene.cameras, view, 0, NUMBA, antialias=run.antialias).image
                    reference = torch.from_numpy(np.array(scored.reference[view]))
                    scores.append(psnr(reference, image[..., 0].clamp(0, 1)))
            line.append(f"{name} {np.mean(scores):6.2f} dB")
        print("  ".join(line))


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--gaussians", type=int, default=100_000, help="size of the synthetic scene")
    parser.add_argument("--work", type=Path, help="a finished work directory instead of the synthetic scene")
    parser.add_argument("--loads", type=int, default=3, help="page loads in one browser (the first is cold)")
    parser.add_argument("--detail", type=float, default=100.0, help="percent of the Gaussians drawn (view --detail)")
    parser.add_argument("--coarse", type=int, default=COARSE_GAUSSIANS, help="Gaussians each page gets first")
    parser.add_argument("--trade", action="store_true", help="with --work: held-out PSNR at each detail, no browser")
    parser.add_argument("--query", default="", help="added to the page's URL, e.g. fixedDpr=0.5 (viser's pixel ratio)")
    parser.add_argument("--bytes", action="store_true",
                        help="count the bytes that reach the page (DevTools' network events; they also carry "
                             "each scene message to this script, so the times are not comparable then)")  # fmt: skip
    parser.add_argument("--save", type=Path, help="write the last load's first frame here (a PNG), to look at")
    parser.add_argument(
        "--scalar", action="store_true", help="the synthetic scene carries scan values (splat --scalar)"
    )
    parser.add_argument("--recolour", type=int, default=0,
                        help="after the loads, time this many transfer-function changes with the page open")  # fmt: skip
    args = parser.parse_args()
    if args.trade:
        detail_trade(args.work or parser.error("--trade needs --work"))
        return

    with tempfile.TemporaryDirectory() as scratch:
        scratch = Path(scratch)
        work = args.work or synthetic_work(scratch / "work", args.gaussians, scalar=args.scalar)
        start = time.perf_counter()
        viewer = SceneViewer(work, port=free_port(), detail=args.detail)
        viewer.delivery.coarse = args.coarse
        serve_s = time.perf_counter() - start
        print(f"scene: {len(viewer.splats)} Gaussians from {work}, {viewer.visible_count()} drawn; "
              f"server ready in {serve_s:.2f} s")  # fmt: skip
        try:
            url = f"{viewer.url}/?{args.query}" if args.query else viewer.url
            with Chromium(WINDOW, count_bytes=args.bytes) as browser:
                for load in range(args.loads):
                    first, whole, frame = time_frames(browser, url, viewer)
                    state = "cold" if load == 0 else "warm"
                    print(f"load {load + 1} ({state}): first frame with the scene after {first:.2f} s, "
                          f"with every Gaussian after {whole:.2f} s")  # fmt: skip
                    if args.bytes:
                        http, websocket = browser.received["http"], browser.received["websocket"]
                        print(f"  reached the page: {websocket / 1e6:.2f} MB over the websocket (the scene), "
                              f"{http / 1e6:.2f} MB over HTTP (the viewer's page and script)")  # fmt: skip
                if args.recolour:
                    times = time_recolours(viewer, args.recolour)
                    print(f"recolour, {len(viewer.splats)} Gaussians, one page open: median {np.median(times):.0f} ms, "
                          f"max {max(times):.0f} ms over {len(times)} changes")  # fmt: skip
                    if viewer.scalar_scene is not None and viewer.scalar_scene.follows_camera:
                        times = time_camera_rests(viewer, args.recolour)
                        print(f"camera at rest, chord lengths redrawn: median {np.median(times):.0f} ms, "
                              f"max {max(times):.0f} ms over {len(times)} rests")  # fmt: skip
            if args.save:
                import imageio.v3 as iio

                iio.imwrite(args.save, frame)
        finally:
            viewer.stop()


if __name__ == "__main__":
    main()
