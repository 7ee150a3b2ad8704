"""What each web splat format costs a finished scene (issue 53's choice): bytes per Gaussian and
the novel-view PSNR lost against the uncompressed run, rendered by our rasterizer as eval does.

    cubecloud run -o work                    # the bundled CT, `fast`
    python bench/share_formats.py work       # its `splat` run
    python bench/share_formats.py work --run splat-random

Formats, each decoded back to Gaussians and scored at the export's novel views (0.75–1.33×, whole
image and foreground):

- `ply`: the run's point_cloud.ply, float32 (the reference; 0 dB lost by definition);
- `spz-B`: ours (cubecloud_cli/share/spz.py) with B fractional bits for the positions, decoded by
  gsply when it is installed (the independent reader), else by ours;
- `compressed-ply`: PlayCanvas's compressed PLY as gsply writes and reads it;
- `splat`: antimatter15's .splat (float32 position and linear scale, 8-bit RGBA and quaternion),
  quantized here by its definition, 32 bytes a Gaussian.

gsply is a test extra (`pip install -e .[test]`); without it the two rows that need it are skipped.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from cubecloud_cli.eval.novel_scores import annotate, summarize_novel, view_angles
from cubecloud_cli.eval.runs import load_run, load_scored_scene, render_views, resolve_scene
from cubecloud_cli.eval.scoring import score_views
from cubecloud_cli.raster.backends import rasterizer_for
from cubecloud_cli.share.spz import decode_spz, encode_spz
from cubecloud_cli.splat.gaussians import MIN_BAKED_OPACITY, Gaussians


def _gsply():
    try:
        import gsply
    except ImportError:
        return None
    return gsply


def from_gsply(data) -> Gaussians:
    """Gaussians from a gsply GSData in PLY conventions (log scales, logits, wxyz, SH DC)."""
    count = len(data.means)

    def tensor(a) -> torch.Tensor:
        return torch.from_numpy(np.asarray(a, dtype=np.float32).copy())

    return Gaussians(
        tensor(data.means),
        tensor(data.scales),
        tensor(data.quats),
        tensor(np.asarray(data.opacities).reshape(count)),
        tensor(np.asarray(data.sh0).reshape(count, 1, 3)),
        torch.zeros(count, 0, 3),
    )


def to_gsply(gsply, gaussians: Gaussians):
    drawn = gaussians.baked()
    dc = drawn.sh_dc[:, 0, :].numpy()
    if dc.shape[1] == 1:
        dc = np.repeat(dc, 3, axis=1)
    return gsply.GSData.from_arrays(
        drawn.means.numpy().astype(np.float32),
        drawn.log_scales.numpy().astype(np.float32),
        drawn.quaternions.numpy().astype(np.float32),
        drawn.opacity_logits.numpy().astype(np.float32),
        dc.astype(np.float32),
        format="ply",
    )


def splat_quantized(gaussians: Gaussians) -> Gaussians:
    """The Gaussians as a .splat file holds them: float32 positions and linear scales, RGBA and the
    unit quaternion (w, x, y, z) in 8 bits each (q · 128 + 128)."""
    drawn = gaussians.baked()
    with torch.no_grad():
        colour = (0.5 + 0.28209479177387814 * drawn.sh_dc[:, 0, :].double()).clamp(0, 1)
        colour8 = torch.round(colour * 255) / 255
        alpha = torch.round(torch.sigmoid(drawn.opacity_logits.double()) * 255) / 255
        alpha = alpha.clamp(MIN_BAKED_OPACITY, 1 - MIN_BAKED_OPACITY)
        q = drawn.quaternions.double()
        q = q / q.norm(dim=1, keepdim=True).clamp_min(1e-12)
        q8 = (torch.round(q * 128 + 128).clamp(0, 255) - 128) / 128
    return Gaussians(
        drawn.means.float(),
        torch.log(torch.exp(drawn.log_scales).float()),  # .splat stores the linear scale as float32
        q8.float(),
        (torch.log(alpha) - torch.log1p(-alpha)).float(),
        ((colour8 - 0.5) / 0.28209479177387814)[:, None, :].float(),
        torch.zeros(len(drawn), 0, colour.shape[1]),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("work", type=Path)
    parser.add_argument("--run", default="splat")
    args = parser.parse_args()
    run = load_run(args.work, args.run)
    scored = load_scored_scene(resolve_scene(args.work, run))
    test = scored.novel
    rasterizer = rasterizer_for(torch.device("cpu"))
    angles = view_angles(test, scored.scene.cameras.centres()[scored.scene.train])
    original = run.gaussians()
    count = len(original)

    def score(gaussians: Gaussians) -> tuple[float, float]:
        renders = np.concatenate(
            [
                render_views(gaussians, test.views.cameras(m), list(range(len(test.views.directions))), rasterizer,
                             antialias=run.antialias)[0]
                for m in test.views.magnifications
            ]
        )  # fmt: skip
        headline = summarize_novel(annotate(score_views(test.reference, renders), test, angles))["headline"]
        return headline["psnr"], headline["psnr_foreground"]

    gsply = _gsply()
    rows = [("ply", (run.directory / "point_cloud.ply").stat().st_size, original, 0.0)]
    with tempfile.TemporaryDirectory() as folder:
        for bits in (12, 16):
            started = time.perf_counter()
            data = encode_spz(original, run.antialias, fractional_bits=bits)
            seconds = time.perf_counter() - started
            path = Path(folder) / f"scene-{bits}.spz"
            path.write_bytes(data)
            decoded = from_gsply(gsply.read_spz(path)) if gsply else decode_spz(data).gaussians
            rows.append((f"spz-{bits}", len(data), decoded, seconds))
        if gsply is not None:
            path = Path(folder) / "scene.compressed.ply"
            started = time.perf_counter()
            to_gsply(gsply, original).save(path, compressed=True)
            seconds = time.perf_counter() - started
            rows.append(("compressed-ply", path.stat().st_size, from_gsply(gsply.plyread(path)), seconds))
        rows.append(("splat", 32 * count, splat_quantized(original), 0.0))
        print(f"{args.work}/{args.run}: {count} Gaussians, anti-aliased {run.antialias}")
        print("| format | bytes | bytes per Gaussian | encode s | novel PSNR (fg) | lost (fg) |")
        print("|---|---|---|---|---|---|")
        reference = None
        for name, size, gaussians, seconds in rows:
            psnr, foreground = score(gaussians)
            reference = reference or (psnr, foreground)
            print(
                f"| {name} | {size:,} | {size / count:.2f} | {seconds:.2f} | {psnr:.2f} ({foreground:.2f}) "
                f"| {reference[0] - psnr:.3f} ({reference[1] - foreground:.3f}) |",
                flush=True,
            )


if __name__ == "__main__":
    main()
