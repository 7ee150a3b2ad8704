"""The novel-view scores (docs/design.md §5): every run rendered at the export's novel views and scored
against their pixel-area references, overall and per cell of (angle from the nearest training
camera × magnification). The headline is the mean over the magnifications 0.75–1.33.

Pure functions over per-view score rows; ``stage.py`` renders and collects the rows.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cubecloud_cli.cameras.novel import (
    HEADLINE_MAGNIFICATIONS,
    NovelViewSet,
    headline_views,
    is_headline,
    magnification_index,
    nearest_angles_deg,
)
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.eval.scoring import summarize
from cubecloud_cli.transfer.function import TransferFunction

NOVEL_DIR, VIEWS_FILE, REFERENCE_FILE = "novel", "views.json", "reference.npy"
TRANSFERS_FILE = "transfers.json"  # the transfer functions held out of training, with their references
# Angle from the nearest training camera: a sphere of 60 keeps every direction within about 15°;
# a ring leaves the poles 90° away.
ANGLE_BINS = (0.0, 10.0, 20.0, 45.0, 180.0)
# What the report shows as pictures: (label, direction index, magnification).
PICTURED = (
    ("from above (the head)", 0, 1.0),
    ("from below (the feet)", 1, 1.0),
    ("zoomed in 2x", 2, 2.0),
    ("zoomed out 0.5x", 2, 0.5),
)  # ASCII: the pictures' font has no ×


@dataclass
class HeldOutTransfer:
    """A transfer function no scalar scene trains under, and the novel views' references under it."""

    name: str
    function: TransferFunction
    reference: np.ndarray  # (len(magnifications) × D, H, W) float32, magnification-major
    magnifications: tuple[float, ...]  # the headline ones (earlier exports: every one)

    def views_at(self, magnifications: list[float], directions: int) -> list[int]:
        """Where the views of ``magnifications`` (each of them rendered here) lie in ``reference``."""
        order = [magnification_index(self.magnifications, wanted) for wanted in magnifications]
        return [i * directions + d for i in order for d in range(directions)]


@dataclass
class NovelTest:
    views: NovelViewSet
    reference: np.ndarray  # (V, H, W) float32, in views.entries() order
    held_out: list[HeldOutTransfer] = field(default_factory=list)
    not_scored: dict[str, str] = field(default_factory=dict)  # held-out presets the volume cannot show → why


def load_novel_test(scene_dir: Path, fix: str) -> NovelTest | None:
    """The export's novel views and references, or None when it has none (an older export, a
    foreign scene, or ``--novel-directions 0``)."""
    folder = Path(scene_dir) / NOVEL_DIR
    if not (folder / VIEWS_FILE).is_file():
        return None
    try:
        views = NovelViewSet.from_json(json.loads((folder / VIEWS_FILE).read_text()))
        reference = np.load(folder / REFERENCE_FILE, mmap_mode="r")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise CubecloudError(f"{folder} is unreadable ({type(exc).__name__}): run `{fix}`") from None
    expected = (len(views), views.resolution, views.resolution)
    if reference.shape != expected:
        raise CubecloudError(f"{folder / REFERENCE_FILE} holds {reference.shape}, not {expected}: run `{fix}`")
    reference = np.asarray(reference, dtype=np.float32)
    if not np.isfinite(reference).all():
        raise CubecloudError(f"{folder / REFERENCE_FILE} holds NaN or Inf: run `{fix}`")
    return NovelTest(views, reference, *_held_out(folder, views, fix))


def _held_out(folder: Path, views: NovelViewSet, fix: str) -> tuple[list[HeldOutTransfer], dict[str, str]]:
    if not (folder / TRANSFERS_FILE).is_file():
        return [], {}
    held = []
    try:
        listed = json.loads((folder / TRANSFERS_FILE).read_text())
        not_scored = {str(name): str(why) for name, why in listed.get("not_scored", {}).items()}
        for entry in listed["held_out"]:
            function = TransferFunction.from_dict(entry)
            function.validate()
            magnifications = tuple(float(m) for m in entry.get("magnifications", views.magnifications))
            if any(magnification_index(magnifications, h) is None for h in headline_views(views).magnifications):
                raise ValueError(f"{entry['file']} lacks a headline magnification")
            expected = (len(magnifications) * len(views.directions), views.resolution, views.resolution)
            reference = np.asarray(np.load(folder / Path(entry["file"]).name, mmap_mode="r"), dtype=np.float32)
            if reference.shape != expected or not np.isfinite(reference).all():
                raise ValueError(f"{entry['file']} is not {expected} finite values")
            held.append(HeldOutTransfer(str(entry["name"]), function, reference, magnifications))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise CubecloudError(
            f"{folder / TRANSFERS_FILE} or a reference it names is unreadable ({exc}): run `{fix}`"
        ) from None
    return held, not_scored


def angle_bin(angle: float) -> str:
    """The label of the angle bin that holds ``angle`` degrees, e.g. "10–20°"."""
    if not (math.isfinite(angle) and angle >= 0.0):
        return "unknown"
    bounds = list(zip(ANGLE_BINS[:-1], ANGLE_BINS[1:]))
    low, high = next(((low, high) for low, high in bounds if angle < high), bounds[-1])
    return f"≥ {low:g}°" if high == ANGLE_BINS[-1] else f"{low:g}–{high:g}°"


def view_angles(test: NovelTest, training_centres: np.ndarray) -> np.ndarray:
    """Degrees from each novel direction to the nearest training camera."""
    return nearest_angles_deg(test.views.directions, training_centres)


def annotate(rows: list[dict], test: NovelTest, angles: np.ndarray) -> list[dict]:
    """Per-view score rows (in storage order) with their name, magnification, angle and cell."""
    annotated = []
    for row, (name, direction, magnification) in zip(rows, test.views.entries()):
        annotated.append(
            {
                **row,
                "view": name,
                "magnification": magnification,
                "angle_deg": float(angles[direction]),
                "angle_bin": angle_bin(float(angles[direction])),
            }
        )
    return annotated


def summarize_novel(rows: list[dict]) -> dict:
    """The novel-view summary of one run: the headline (0.75–1.33×), each magnification, and each
    (angle bin × magnification) cell, each a :func:`summarize` of its views."""
    magnifications = sorted({row["magnification"] for row in rows})
    bins = [label for label in (angle_bin(a) for a in ANGLE_BINS[:-1]) if any(r["angle_bin"] == label for r in rows)]
    cells = []
    for label in bins:
        for magnification in magnifications:
            members = [r for r in rows if r["angle_bin"] == label and r["magnification"] == magnification]
            if members:
                cells.append({"angle": label, "magnification": magnification, **summarize(members)})
    return {
        "headline": summarize([r for r in rows if is_headline(r["magnification"])]),
        "headline_magnifications": list(HEADLINE_MAGNIFICATIONS),
        "by_magnification": {f"{m:g}": summarize([r for r in rows if r["magnification"] == m]) for m in magnifications},
        "angle_bins": bins,
        "cells": cells,
    }


def pictured_views(test: NovelTest) -> list[tuple[str, int]]:
    """(label, storage index) of the views the report shows, among those the set has."""
    count = len(test.views.directions)
    chosen = []
    for label, direction, magnification in PICTURED:
        if direction < count and magnification in test.views.magnifications:
            chosen.append((label, test.views.magnifications.index(magnification) * count + direction))
    return chosen
