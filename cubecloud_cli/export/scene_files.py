"""The files of a finished export: views as PNG and float stacks, the COLMAP model, the point-cloud
PLYs and transforms.json."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

from cubecloud_cli.cameras import PinholeCameras
from cubecloud_cli.core.writes import save_array
from cubecloud_cli.export.images import write_contact_sheet, write_views
from cubecloud_cli.export.point_cloud import PointCloud
from cubecloud_cli.scene import transforms_json, write_colmap_model, write_json, write_point_cloud_ply, write_test_list

HOLDOUT_EVERY = 8  # docs/design.md §2 and the reference 3DGS evaluation: views with index % 8 == 0


def held_out_views(count: int) -> list[int]:
    return [index for index in range(count) if index % HOLDOUT_EVERY == 0]


def write_scene(
    directory: Path,
    cameras: PinholeCameras,
    names: list[str],
    images: np.ndarray,
    reference: np.ndarray,
    cloud: PointCloud,
) -> None:
    held_out = set(held_out_views(len(names)))
    test_names = [names[i] for i in sorted(held_out)]
    train_names = [n for i, n in enumerate(names) if i not in held_out]
    write_views(images, directory / "images", names)
    write_views(reference, directory / "reference", names)
    save_array(directory / "images.npy", images)
    save_array(directory / "reference.npy", reference)

    sparse = directory / "sparse" / "0"
    sparse.mkdir(parents=True)
    write_colmap_model(sparse, cameras, names, cloud.xyz, cloud.rgb)
    write_test_list(sparse, test_names)
    extras = {"intensity": cloud.intensity, "density": cloud.density}
    write_point_cloud_ply(directory / "points3D.ply", cloud.xyz, cloud.rgb, extras)
    # nerfstudio-format readers take ply_file_path's properties in a fixed order (OpenSplat reads
    # x y z [normals] [colours] by position, so our extra columns would shift every point after
    # the first): they get the plain layout, under nerfstudio's own name for the seed cloud.
    write_point_cloud_ply(directory / "sparse_pc.ply", cloud.xyz, cloud.rgb)
    # The reference 3DGS loader reads sparse/0/points3D.ply when it exists (and otherwise writes
    # one there); a hard link gives it ours without a second copy on disk.
    try:
        os.link(directory / "points3D.ply", sparse / "points3D.ply")
    except OSError:
        shutil.copyfile(directory / "points3D.ply", sparse / "points3D.ply")

    paths = [f"images/{n}" for n in names]
    write_json(
        directory / "transforms.json",
        transforms_json(
            cameras,
            paths,
            train_file_paths=[f"images/{n}" for n in train_names],
            test_file_paths=[f"images/{n}" for n in test_names],
            ply_file_path="sparse_pc.ply",
        ),
    )
    write_json(
        directory / "split.json",
        {
            "rule": f"views with index % {HOLDOUT_EVERY} == 0 are held out for testing (reference 3DGS llffhold)",
            "train": train_names,
            "test": test_names,
        },
    )
    write_contact_sheet(images, directory / "contact_sheet.png", held_out, "CuNeRF renders (training images)")
    write_contact_sheet(
        reference, directory / "contact_sheet_reference.png", held_out, "reference renders (preprocessed volume)"
    )
