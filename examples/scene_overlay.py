"""Open an exported scene the way a 3DGS trainer does, and check that it lines up.

    cubecloud run -o work
    python examples/scene_overlay.py work/export --view 3 --out overlay.png

Reads sparse/0 (COLMAP) and points3D.ply with cubecloud's own readers, projects every point
into one view through the COLMAP camera, and draws the points over that view's training image
(red: points whose pixel in the image is dark, green: bright). On a good scene the green dots sit
on the anatomy. Prints the cameras' intrinsics and how many points land inside the image.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from PIL import Image

from cubecloud_cli.scene import read_colmap_model, read_point_cloud_ply


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene", type=Path, help="a scene folder with sparse/0 and images/ (e.g. work/export)")
    parser.add_argument("--view", type=int, default=0, help="index of the view, in name order")
    parser.add_argument("--points", type=int, default=3000, help="how many points to draw (a random subset)")
    parser.add_argument("--out", type=Path, default=Path("overlay.png"))
    args = parser.parse_args()

    model = read_colmap_model(args.scene)
    xyz, _, _ = read_point_cloud_ply(args.scene / "sparse" / "0" / "points3D.ply")
    cameras, name = model.cameras, model.image_names[args.view]
    print(
        f"{len(cameras)} PINHOLE views of {cameras.width}x{cameras.height}, focal {cameras.focal:.2f} px, "
        f"{len(xyz)} points; drawing view {args.view} ({name})"
    )

    image = np.asarray(Image.open(args.scene / "images" / name).convert("RGB")).copy()
    if len(xyz) > args.points:
        xyz = xyz[np.random.default_rng(0).choice(len(xyz), args.points, replace=False)]
    pixels, depth = cameras.project(args.view, xyz)
    visible = np.isfinite(pixels).all(axis=1) & (depth > 0)
    columns, rows = np.floor(pixels[visible]).astype(int).T
    inside = (columns >= 0) & (columns < cameras.width) & (rows >= 0) & (rows < cameras.height)
    columns, rows = columns[inside], rows[inside]
    bright = image[rows, columns, 0] > 20
    image[rows[bright], columns[bright]] = (0, 255, 0)
    image[rows[~bright], columns[~bright]] = (255, 0, 0)
    Image.fromarray(image).save(args.out)
    print(
        f"{inside.sum()} of {len(xyz)} drawn points land inside the image, {bright.mean():.1%} of them on "
        f"bright pixels; wrote {args.out}"
    )


if __name__ == "__main__":
    main()
