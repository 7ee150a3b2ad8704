"""The browser viewer: one viser server showing a work directory's splat runs, with a run
selector, a clipping plane into the body, patient-axis labels and the export's first view.

Everything is drawn in view units (world × the view scale, see splats.py); the controls speak
world units, in which the volume fills [−1, 1]³.
"""

from __future__ import annotations

import logging
import socket
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cubecloud_cli.artifacts import is_complete, read_manifest
from cubecloud_cli.errors import CubecloudError
from cubecloud_cli.eval.runs import find_splat_runs
from cubecloud_cli.splat.ply import read_gaussians_ply
from cubecloud_cli.view.splats import CLIP_AXES, ViewSplats, axis_normal, clip_mask, view_scale, view_splats

log = logging.getLogger("cubecloud")

CLIP_CHOICES = ("off", *CLIP_AXES, "view direction")
# Where the patient's axes point in the RAS world (docs/design.md §2), for the labels.
PATIENT_LABELS = {"L": (-1, 0, 0), "R": (1, 0, 0), "P": (0, -1, 0), "A": (0, 1, 0), "I": (0, 0, -1), "S": (0, 0, 1)}
DEFAULT_EYE = np.array([0.0, -4.0, 0.0])  # in front of the patient, when there is no export to follow


@dataclass
class Clip:
    """The clipping plane in world units: ``axis`` one of CLIP_CHOICES, ``position`` along it."""

    axis: str = "off"
    position: float = 0.0
    keep: str = "below"
    view_direction: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))

    def normal(self) -> np.ndarray | None:
        if self.axis == "off":
            return None
        if self.axis == "view direction":
            return -np.asarray(self.view_direction, dtype=np.float64)  # hide what faces the viewer
        return axis_normal(self.axis)


def visible_splats(splats: ViewSplats, clip: Clip) -> ViewSplats:
    """The Gaussians the clipping plane leaves in view."""
    normal = clip.normal()
    if normal is None:
        return splats
    return splats.subset(clip_mask(splats.centers, normal, clip.position, clip.keep))  # type: ignore[arg-type]


def load_runs(work: Path) -> dict[str, Path]:
    """The finished splat runs of ``work`` (splat first), each its point_cloud.ply."""
    work = Path(work)
    if not work.is_dir():
        raise CubecloudError(f"{work} is not a work directory: run `cubecloud run -o {work}` first")
    runs = {name: work / name / "point_cloud.ply" for name in find_splat_runs(work)}
    if not runs:
        raise CubecloudError(f"{work} has no finished splat run: run `cubecloud splat {work}` first")
    return runs


def first_view(work: Path) -> tuple[np.ndarray, float | None]:
    """The export's first camera centre (world units) and its vertical field of view in degrees,
    so the viewer opens on the picture the scene was trained to show first."""
    export = Path(work) / "export"
    if is_complete(export):
        cameras = read_manifest(export).get("cameras", {})
        centres = cameras.get("centres")
        if centres:
            return np.asarray(centres[0], dtype=np.float64), cameras.get("fov_deg")
    return DEFAULT_EYE, None


def check_port_free(host: str, port: int) -> None:
    """A one-line error now, rather than a server that quietly takes another port."""
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as probe:
        try:
            probe.bind((host, port))
        except OSError as exc:
            raise CubecloudError(f"cannot listen on {host}:{port} ({exc.strerror}): choose another --port") from None


class SceneViewer:
    """A running viewer of one work directory."""

    def __init__(self, work: Path, host: str = "127.0.0.1", port: int = 8080, run: str | None = None):
        import viser  # imported here: every other command starts without it

        self.runs = load_runs(work)
        if run is not None and run not in self.runs:
            raise CubecloudError(f"{work} has no finished run {run!r}: choose one of {', '.join(self.runs)}")
        self.current = run or next(iter(self.runs))
        self.splats = view_splats(read_gaussians_ply(self.runs[self.current]))
        self.scale = view_scale(self.splats.covariances)
        self.clip = Clip()
        self._controls: dict = {}
        check_port_free(host, port)
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.scene.set_up_direction("+z")  # RAS: superior is up
        # The black the training images were rendered on (PNG: a tiny JPEG does not reach the page).
        self.server.scene.set_background_image(np.zeros((64, 64, 3), dtype=np.uint8), format="png")
        eye, fov = first_view(work)
        self.server.initial_camera.position = eye * self.scale
        self.server.initial_camera.look_at = np.zeros(3)
        self.server.initial_camera.up = np.array([0.0, 0.0, 1.0])
        if fov is not None:
            self.server.initial_camera.fov = float(np.radians(fov))
        self._add_labels()
        self._add_controls()
        self._draw()

    @property
    def url(self) -> str:
        return f"http://{self.server.get_host()}:{self.server.get_port()}"

    def select_run(self, name: str) -> None:
        self.current = name
        self.splats = view_splats(read_gaussians_ply(self.runs[name]))
        self._draw()

    def set_clip(self, axis: str, position: float | None = None, keep: str | None = None) -> None:
        """Move the clipping plane (from the page or from Python); the page's controls follow."""
        if axis not in CLIP_CHOICES:
            raise CubecloudError(f"clipping axis {axis!r} must be one of {', '.join(CLIP_CHOICES)}")
        wanted = (axis, self.clip.position if position is None else float(position), keep or self.clip.keep)
        if wanted == (self.clip.axis, self.clip.position, self.clip.keep):
            return  # a control echoing a change made from Python
        self.clip.axis, self.clip.position, self.clip.keep = wanted
        for name, value in (("axis", axis), ("position", self.clip.position), ("flip", self.clip.keep == "above")):
            control = self._controls.get(name)
            if control is not None and control.value != value:
                control.value = value
        self._draw()

    def visible_count(self) -> int:
        return len(visible_splats(self.splats, self.clip))

    def stop(self) -> None:
        self.server.stop()

    def _draw(self) -> None:
        shown = visible_splats(self.splats, self.clip).scaled(self.scale)
        self.server.scene.add_gaussian_splats("/splats", shown.centers, shown.covariances, shown.rgbs, shown.opacities)

    def _add_labels(self) -> None:
        for text, direction in PATIENT_LABELS.items():
            position = np.asarray(direction, dtype=np.float64) * 1.15 * self.scale
            self.server.scene.add_label(f"/axes/{text}", text, position=position, anchor="center-center")

    def _add_controls(self) -> None:
        gui = self.server.gui
        run = gui.add_dropdown("Run", tuple(self.runs), initial_value=self.current)
        run.on_update(lambda _: self.select_run(run.value))
        with gui.add_folder("Clipping plane"):
            axis = gui.add_dropdown("Cut", CLIP_CHOICES, initial_value="off")
            position = gui.add_slider("Position", min=-1.0, max=1.0, step=0.01, initial_value=0.0)
            flip = gui.add_checkbox("Keep the other side", initial_value=False)
        self._controls = {"axis": axis, "position": position, "flip": flip}
        axis.on_update(lambda _: self.set_clip(axis.value))
        position.on_update(lambda _: self.set_clip(self.clip.axis, position.value))
        flip.on_update(lambda _: self.set_clip(self.clip.axis, keep="above" if flip.value else "below"))

        @self.server.on_client_connect
        def _follow_camera(client) -> None:
            @client.camera.on_update
            def _(camera) -> None:
                direction = np.asarray(camera.look_at) - np.asarray(camera.position)
                length = float(np.linalg.norm(direction))
                if length > 0:  # kept for the next cut: redrawing on every camera move would flood the page
                    self.clip.view_direction = direction / length
