"""The novel-view test's references (docs/design.md §2): renders of the preprocessed volume at views no
camera setup trains on, each pixel the mean over its area.

A splat is a continuous image, and a pixel of a real camera integrates light over its area; a
reference that samples each pixel's centre only would alias when the view zooms out, and score
a correct anti-aliased splat as wrong. So every reference pixel averages a k × k grid of
sub-pixel rays (:data:`cubecloud_cli.cameras.novel.SUPERSAMPLING`,
:mod:`cubecloud_cli.render.pixel_area`).

WORK/export/novel/ holds
  views.json          the directions, poses, magnifications and focal lengths (NovelViewSet.as_json)
  reference.npy       float32 (V, H, W), magnification-major, in the order of views.json's "views"
  transfers.json      with --transfer-set K > 1: the transfer functions held out of training, and
  reference-NAME.npy  the same directions under each at the headline magnifications (0.75–1.33×,
                      as transfers.json lists them), for eval to score scalar scenes on
  contact_sheet.png   every novel reference, for people
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from cubecloud_cli.cameras.novel import SUPERSAMPLING, NovelViewSet
from cubecloud_cli.core.writes import save_array
from cubecloud_cli.export.finished_views import ExportProgress
from cubecloud_cli.export.images import write_contact_sheet
from cubecloud_cli.render import ImageModel
from cubecloud_cli.render.pixel_area import pixel_area_renders
from cubecloud_cli.scene import write_json
from cubecloud_cli.transfer.training_set import NamedTransfer

NOVEL_DIR = "novel"
VIEWS_FILE = "views.json"
REFERENCE_FILE = "reference.npy"
TRANSFERS_FILE = "transfers.json"


def render_novel_references(
    field,
    novel: NovelViewSet,
    models: Sequence[ImageModel],
    device: torch.device,
    progress: ExportProgress,
    on_progress: Callable[[int, int], None],
    prefixes: Sequence[str] = ("novel",),
) -> np.ndarray:
    """(K, V, H, W) pixel-area renders of ``field`` at every novel view under each of K image
    models (one march of a view's rays for all K where the march allows it), saving each image as
    it is done (model j's under ``prefixes[j]``) and reusing the ones an interrupted run saved."""
    count = len(novel.directions)
    images = np.empty((len(models), len(novel), novel.resolution, novel.resolution), dtype=np.float32)
    supports = None
    done = 0
    with torch.no_grad():
        for group, magnification in enumerate(novel.magnifications):
            cameras = novel.cameras(magnification)
            for direction in range(count):
                index = group * count + direction
                names = [f"{prefix}_view_{index:05d}" for prefix in prefixes]
                saved, missing = progress.load_views(names, images.shape[2:])
                for j, view in saved.items():
                    images[j, index] = view
                if missing:
                    if supports is None:
                        supports = [None if m.kind == "slice" else field.support(m.support_threshold) for m in models]
                    images[missing, index] = pixel_area_renders(
                        field, cameras, direction, [models[j] for j in missing], [supports[j] for j in missing],
                        device, SUPERSAMPLING,
                    )  # fmt: skip
                    for j in missing:
                        progress.save(names[j], images[j, index])
                done += len(models)
                on_progress(done, len(models) * len(novel))
    return images


def write_novel(directory: Path, novel: NovelViewSet, reference: np.ndarray) -> None:
    folder = directory / NOVEL_DIR
    folder.mkdir(parents=True, exist_ok=True)
    write_json(folder / VIEWS_FILE, novel.as_json())
    save_array(folder / REFERENCE_FILE, reference)
    write_contact_sheet(
        reference,
        folder / "contact_sheet.png",
        set(),
        f"novel views (rows of {len(novel.directions)} directions at "
        f"{', '.join(f'{m:g}x' for m in novel.magnifications)}), reference renders",
        columns=len(novel.directions),
    )


def held_out_reference_file(name: str) -> str:
    return f"reference-{name}.npy"


def write_held_out(
    directory: Path,
    held_out: list[tuple[NamedTransfer, np.ndarray]],
    not_scored: dict[str, str],
    magnifications: tuple[float, ...],
) -> None:
    """The references under each held-out transfer function (the novel directions at
    ``magnifications``, magnification-major), the list that names them, and why the held-out
    presets left out were left out."""
    folder = directory / NOVEL_DIR
    listed = []
    for named, reference in held_out:
        save_array(folder / held_out_reference_file(named.name), reference)
        listed.append(
            {
                "name": named.name,
                **named.function.as_dict(),
                "file": held_out_reference_file(named.name),
                "magnifications": list(magnifications),
            }
        )
    write_json(folder / TRANSFERS_FILE, {"held_out": listed, "not_scored": not_scored})
