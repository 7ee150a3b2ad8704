"""The novel-view test (docs/design.md §2, §5): views that no camera setup trains on.

A fixed set of directions (the two poles of the long axis, from the head and from the feet, then
seeded random directions, uniform over the sphere), each seen at several magnifications, from the
export's camera distance. It depends only on the distance and the image size, never on the
training cameras, so a ring, a sphere or a stack of training views are all scored on the same
views. Magnification 1 is the focal length that fits the whole cube in every one of these
directions, which is within a few per cent of a sphere's training zoom; 2 zooms in twice as far.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from cubecloud_cli.cameras.orbit import fitting_focal
from cubecloud_cli.cameras.pinhole import PinholeCameras
from cubecloud_cli.cameras.sphere import POLE_UP, poses_looking_at_origin

MAGNIFICATIONS = (0.5, 0.75, 1.0, 1.33, 2.0)
# The headline score is the mean over these: zoomed out and in by a third, and the training zoom.
HEADLINE_MAGNIFICATIONS = (0.75, 1.0, 1.33)
DEFAULT_DIRECTIONS = 16
SEED = 1601  # fixed, so every export of every scan draws the same directions
SUPERIOR = np.array([0.0, 0.0, 1.0])
# Sub-pixels per axis of a pixel-area reference. 2 × 2 is enough at every magnification: on the
# bundled CT (128³, dvr) the mean of 2 × 2 sub-pixels is 62–66 dB from that of 6 × 6, from 0.5×
# to 2×, where one sample per pixel is 47–53 dB from it, as far as a splat is from the reference.
SUPERSAMPLING = 2


def novel_directions(count: int, seed: int = SEED) -> np.ndarray:
    """(count, 3) unit directions: from the head (superior), from the feet, then uniform random."""
    if count < 0:
        raise ValueError(f"the number of novel directions must be at least 0, got {count}")
    rng = np.random.default_rng(seed)
    random = rng.normal(size=(max(0, count - 2), 3))
    # A normal draw has norm 0 with probability 0; the floor keeps the division finite anyway.
    random /= np.maximum(np.linalg.norm(random, axis=1, keepdims=True), 1e-12)
    return np.concatenate((SUPERIOR[None], -SUPERIOR[None], random))[:count]


def view_name(magnification: float, direction: int) -> str:
    return f"novel_m{magnification:g}_d{direction:02d}"


@dataclass(frozen=True)
class NovelViewSet:
    directions: np.ndarray  # (D, 3) unit vectors from the origin to the cameras
    rotations: np.ndarray  # (D, 3, 3) world -> camera
    translations: np.ndarray  # (D, 3)
    resolution: int
    base_focal: float  # pixels, magnification 1
    magnifications: tuple[float, ...] = MAGNIFICATIONS

    @classmethod
    def build(cls, count: int, radius: float, resolution: int, seed: int = SEED) -> "NovelViewSet":
        directions = novel_directions(count, seed)
        if count == 0:
            return cls(directions, np.zeros((0, 3, 3)), np.zeros((0, 3)), resolution, 1.0)
        rotations, translations = poses_looking_at_origin(directions, radius, SUPERIOR, np.asarray(POLE_UP["si"]))
        return cls(directions, rotations, translations, resolution, fitting_focal(rotations, translations, resolution))

    def __len__(self) -> int:
        return len(self.directions) * len(self.magnifications)

    def cameras(self, magnification: float) -> PinholeCameras:
        """The D views at ``magnification``."""
        return PinholeCameras(
            self.rotations, self.translations, self.resolution, self.resolution, self.base_focal * magnification
        )

    def entries(self) -> list[tuple[str, int, float]]:
        """(name, direction index, magnification) of every view, in storage order (magnification-major)."""
        return [(view_name(m, d), d, m) for m in self.magnifications for d in range(len(self.directions))]

    def as_json(self) -> dict:
        return {
            "rule": "fixed directions (superior, inferior, then seeded uniform random) at each magnification, from the "
            "export's camera distance; magnification 1 fits the whole cube in every direction",
            "resolution": self.resolution,
            "base_focal": self.base_focal,
            "magnifications": list(self.magnifications),
            "headline_magnifications": list(HEADLINE_MAGNIFICATIONS),
            "supersampling": {f"{m:g}": SUPERSAMPLING for m in self.magnifications},
            "directions": self.directions.round(12).tolist(),
            "rotations": self.rotations.tolist(),
            "translations": self.translations.tolist(),
            "views": [{"name": name, "direction": d, "magnification": m} for name, d, m in self.entries()],
        }

    @classmethod
    def from_json(cls, data: dict) -> "NovelViewSet":
        return cls(
            np.asarray(data["directions"], dtype=np.float64).reshape(-1, 3),
            np.asarray(data["rotations"], dtype=np.float64).reshape(-1, 3, 3),
            np.asarray(data["translations"], dtype=np.float64).reshape(-1, 3),
            int(data["resolution"]),
            float(data["base_focal"]),
            tuple(float(m) for m in data["magnifications"]),
        )


def nearest_angles_deg(directions: np.ndarray, camera_centres: np.ndarray) -> np.ndarray:
    """For each unit direction, the angle (degrees) to the nearest camera centre as seen from the
    origin. Cameras at the origin have no direction and are ignored; none left gives NaN."""
    norms = np.linalg.norm(camera_centres, axis=1)
    centres = camera_centres[norms > 1e-12] / norms[norms > 1e-12, None]
    if len(centres) == 0 or len(directions) == 0:
        return np.full(len(directions), np.nan)
    cosines = np.clip(directions @ centres.T, -1.0, 1.0)
    return np.degrees(np.arccos(cosines.max(axis=1)))


def magnification_index(magnifications: tuple[float, ...] | list[float], wanted: float) -> int | None:
    """Where ``wanted`` is among ``magnifications`` (read back from JSON: compared within 1e-9), or None."""
    return next((i for i, m in enumerate(magnifications) if abs(m - wanted) < 1e-9), None)


def is_headline(magnification: float) -> bool:
    return magnification_index(HEADLINE_MAGNIFICATIONS, magnification) is not None


def headline_views(novel: NovelViewSet) -> NovelViewSet:
    """The same directions at the headline magnifications only (those of ``novel`` among them)."""
    return replace(novel, magnifications=tuple(m for m in novel.magnifications if is_headline(m)))
