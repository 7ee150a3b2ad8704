"""The browser viewer: one viser server showing a work directory's splat runs, with a run
selector, a clipping plane into the body, the scan's slices, the Cube-Cloud points and the
export's cameras around them, patient-axis labels and the export's first view.

Everything is drawn in view units (world × the view scale, see splats.py); the controls speak
world units, in which the volume fills [−1, 1]³.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import json
import logging
import math
import threading
from pathlib import Path

import numpy as np

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.eval.runs import find_splat_runs
from cubecloud_cli.splat.gaussian_ply import read_splat_ply
from cubecloud_cli.splat.scalar_gaussians import ScalarGaussians
from cubecloud_cli.view.camera_rest import CameraRest
from cubecloud_cli.view.context import load_context
from cubecloud_cli.view.delivery import SplatDelivery
from cubecloud_cli.view.layers import ANTERIOR_VIEW, SLICE_AXES, SliceLayer, ViewPose, camera_poses, camera_view
from cubecloud_cli.view.listening import check_port_free, start_server
from cubecloud_cli.view.splats import (
    CLIP_CHOICES,
    Clip,
    ViewSplats,
    by_importance,
    clip_mask,
    detail_count,
    detail_percent,
    view_scale,
    view_splats,
    visible_splats,
)
from cubecloud_cli.view.transfer_view import (
    CONTROLS,
    ScalarScene,
    add_transfer_controls,
    read_intensity_map,
    shown_presets,
)

log = logging.getLogger("cubecloud")

# Where the patient's axes point in the RAS world (docs/design.md §2), for the labels.
PATIENT_LABELS = {"L": (-1, 0, 0), "R": (1, 0, 0), "P": (0, -1, 0), "A": (0, 1, 0), "I": (0, 0, -1), "S": (0, 0, 1)}
FRUSTUM_SIZE = 0.08  # of the cameras' distance from the centre: small enough not to hide the body
FRUSTUM_COLOUR = (70, 150, 255)
FALLBACK_VOXELS = 128  # the point size, as a voxel of this cube, when there is no volume to measure


def _is_scalar_run(ply: Path) -> bool:
    try:
        return bool(json.loads((ply.parent / "manifest.json").read_text()).get("params", {}).get("scalar"))
    except (OSError, ValueError, AttributeError):
        return False


def load_runs(work: Path) -> dict[str, Path]:
    """The finished splat runs of ``work`` (splat first), each its point_cloud.ply."""
    work = Path(work)
    if not work.is_dir():
        raise CubecloudError(f"{work} is not a work directory: run `cubecloud run -o {work}` first")
    runs = {name: work / name / "point_cloud.ply" for name in find_splat_runs(work)}
    if not runs:
        raise CubecloudError(f"{work} has no finished splat run: run `cubecloud splat {work}` first")
    return runs


class SceneViewer:
    """A running viewer of one work directory: the Gaussians of a run, and around them the scan's
    slices, the Cube-Cloud points and the export's cameras, each behind its own toggle."""

    def __init__(
        self, work: Path, host: str = "127.0.0.1", port: int = 8080, run: str | None = None, detail: float = 100.0
    ):
        if not (math.isfinite(detail) and 1.0 <= detail <= 100.0):
            raise CubecloudError(
                f"--detail {detail:g} must be a percent from 1 to 100 (e.g. 10 for a browser without a GPU)"
            )
        self.runs = load_runs(work)
        if run is not None and run not in self.runs:
            raise CubecloudError(f"{work} has no finished run {run!r}: choose one of {', '.join(self.runs)}")
        self.current = run or next(iter(self.runs))
        self.intensity_map = read_intensity_map(Path(work))
        self._seen_from: np.ndarray | None = None  # the last camera at rest, world units
        self._redraw_lock = threading.Lock()  # a recolour and a camera's redraw must not cross
        self._load_run(self.current)
        self.scale = view_scale(self.splats.covariances)
        self.detail = detail_percent(detail)
        self.clip = Clip()
        self.context = load_context(work)
        for line in self.context.left_out:
            log.warning(line)
        cameras = self.context.cameras
        self.home = (ANTERIOR_VIEW if cameras is None else camera_view(cameras, 0)).scaled(self.scale)
        self._camera_rest = CameraRest(self.look_from)
        self.look_from(self.home.position, draw=False)
        self.slices = SliceLayer(self.context.volume)
        self._controls: dict = {}  # the page's controls, by name, so changes from Python show there
        self._nodes: dict = {}  # the scene nodes that change after they are drawn
        check_port_free(host, port)
        self.server = start_server(host, port)
        self.server.scene.set_up_direction("+z")  # RAS: superior is up
        # Nothing here is lit (splats, images, points, lines, labels), and the default environment
        # map keeps the canvas at 5 % opacity until the page has built its lighting and faded in
        # over five frames: without a GPU that hid a 100k-Gaussian scene 18–26 s longer (docs/view.md).
        self.server.scene.configure_environment_map(hdri=None)
        self.server.scene.configure_default_lights(enabled=False)
        # The black the training images were rendered on (PNG: a tiny JPEG does not reach the page).
        self.server.scene.set_background_image(np.zeros((64, 64, 3), dtype=np.uint8), format="png")
        self._set_initial_camera()
        # Each page gets its Gaussians once it has connected, after viser has replayed it the shared
        # scene (slices, points, cameras, controls): the coarse set first (delivery.py).
        self.delivery = SplatDelivery(
            self._shown_splats(), connected=lambda client_id: client_id in self.server.get_clients()
        )
        self.server.on_client_connect(self.delivery.open_page)
        self.server.on_client_disconnect(self.delivery.close_page)
        self._add_labels()
        self._add_context_layers()
        self._add_controls()

    @property
    def url(self) -> str:
        return f"http://{self.server.get_host()}:{self.server.get_port()}"

    def select_run(self, name: str) -> None:
        self.current = name
        self._load_run(name)
        self._draw()
        self._sync_transfer_controls()

    def set_transfer(self, **choice) -> None:
        """Recolour a scalar scene: ``preset``, the window ``low``..``high`` (preprocessed
        intensities), ``opacity`` (× the extinction) or ``colour_map``; only colours and
        opacities are computed again and sent (transfer_view.py)."""
        if self.scalar_scene is None:
            raise CubecloudError(f"{self.current} is not a scalar scene: train one with `cubecloud splat --scalar`")
        with self._redraw_lock:
            if self.scalar_scene.choose(**choice):
                self.splats = self.scalar_scene.splats()
                self._draw()
        self._sync_transfer_controls()

    def look_from(self, position, draw: bool = True) -> None:
        """Redraw a chord-length scalar scene as seen from ``position`` (view units), where a
        page's camera came to rest (camera_rest.py); other scenes look alike from everywhere."""
        self._seen_from = np.asarray(position, dtype=np.float64) / self.scale
        with self._redraw_lock:
            if self.scalar_scene is not None and self.scalar_scene.look_from(self._seen_from):
                self.splats = self.scalar_scene.splats()
                if draw:
                    self._draw()

    def set_detail(self, percent: float) -> None:
        """Draw the ``percent`` of the Gaussians that shape the picture most (see by_importance)."""
        percent = detail_percent(percent)
        if percent != self.detail:
            self.detail = percent
            self._draw()
        self._sync_controls(detail=percent)

    def set_clip(self, axis: str, position: float | None = None, keep: str | None = None) -> None:
        """Move the clipping plane (from the page or from Python); the page's controls follow."""
        if axis not in CLIP_CHOICES:
            raise CubecloudError(f"clipping axis {axis!r} must be one of {', '.join(CLIP_CHOICES)}")
        wanted = (axis, self.clip.position if position is None else float(position), keep or self.clip.keep)
        if wanted == (self.clip.axis, self.clip.position, self.clip.keep):
            return  # a control echoing a change made from Python
        self.clip.axis, self.clip.position, self.clip.keep = wanted
        self._sync_controls(axis=axis, position=self.clip.position, flip=self.clip.keep == "above")
        self._draw()
        if "points" in self._nodes and self._nodes["points"].visible:
            self._draw_points()

    def show_slice(self, axis: str, index: int | None = None, visible: bool | None = None) -> None:
        """Move the ``axis`` slice plane to voxel ``index`` and/or show or hide it."""
        if self.context.volume is None:
            raise CubecloudError("this work directory has no preprocessed volume to slice")
        if self.slices.update(axis, index, visible):
            self._draw_slice(axis)
        self._sync_controls(**{f"{axis} index": self.slices.index[axis], f"{axis} shown": self.slices.visible[axis]})

    def set_slice_opacity(self, opacity: float) -> None:
        self.slices.opacity = float(np.clip(np.nan_to_num(opacity, nan=1.0), 0.0, 1.0))
        if self.context.volume is not None:
            for axis in SLICE_AXES:
                self._draw_slice(axis)
        self._sync_controls(opacity=self.slices.opacity)

    def show_splats(self, visible: bool) -> None:
        """Show or hide the Gaussians (to see the slices or the points alone)."""
        self.delivery.set_visible(bool(visible))
        self._sync_controls(splats=bool(visible))

    def show_points(self, visible: bool) -> None:
        node = self._nodes.get("points")
        if node is not None and node.visible != bool(visible):
            node.visible = bool(visible)
            if visible:
                self._draw_points()  # the clipping plane may have moved while they were hidden
        self._sync_controls(points=bool(visible))

    def show_cameras(self, visible: bool) -> None:
        node = self._nodes.get("cameras")
        if node is not None and node.visible != bool(visible):
            node.visible = bool(visible)
        self._sync_controls(cameras=bool(visible))

    def reset_view(self, client=None) -> None:
        """Return ``client`` (every connected one when None) to the export's first view."""
        self._look(client, self.home)

    def look_through(self, client, index: int) -> None:
        """Put ``client`` (every connected one when None) where export camera ``index`` stands."""
        self._look(client, camera_view(self.context.cameras, index).scaled(self.scale))

    def browsers_at_home(self) -> bool:
        """Whether a browser is connected and every connected one reports the home view's camera
        and has drawn every Gaussian it is shown (a screenshot of the first view waits for this;
        it costs each page a frame, see SplatDelivery.pages_drawn)."""
        clients = list(self.server.get_clients().values())
        tolerance = 1e-3 * float(np.linalg.norm(self.home.position - self.home.look_at))
        # The camera first: the drawn check asks each page for a frame.
        return (
            bool(clients)
            and all(
                float(np.linalg.norm(np.asarray(client.camera.position) - self.home.position)) < tolerance
                for client in clients
            )
            and self.delivery.pages_drawn([client.client_id for client in clients])
        )

    def drawn_splats(self) -> ViewSplats:
        """The Gaussians on the page: the detail's share, less those beyond the clipping plane."""
        return visible_splats(self.splats.subset(slice(0, detail_count(len(self.splats), self.detail))), self.clip)

    def visible_count(self) -> int:
        return len(self.drawn_splats())

    def stop(self) -> None:
        self._camera_rest.cancel()
        with contextlib.redirect_stdout(io.StringIO()):  # viser's own "Server stopped"
            self.server.stop()

    # ------------------------------------------------------------------------------- the scene

    def _load_run(self, name: str) -> None:
        """The run's Gaussians in importance order; a scalar run's kept with its values too, to
        recolour under the page's transfer function."""
        model = read_splat_ply(self.runs[name])
        self.scalar_scene = ScalarScene(model, self.intensity_map) if isinstance(model, ScalarGaussians) else None
        if self.scalar_scene is None:
            self.splats = by_importance(view_splats(model))
        else:
            self.scalar_scene.look_from(self._seen_from)
            self.splats = self.scalar_scene.splats()

    def _set_initial_camera(self) -> None:
        camera, home = self.server.initial_camera, self.home
        camera.position, camera.look_at, camera.up = home.position, home.look_at, home.up
        if home.fov is not None:
            camera.fov = home.fov

    def _look(self, client, pose: ViewPose) -> None:
        for each in [client] if client is not None else list(self.server.get_clients().values()):
            with each.atomic():
                each.camera.position, each.camera.look_at = pose.position, pose.look_at
                each.camera.up_direction = pose.up
                if pose.fov is not None:
                    each.camera.fov = pose.fov

    def _shown_splats(self) -> ViewSplats:
        """The drawn Gaussians in view units, as each page gets them."""
        return self.drawn_splats().scaled(self.scale)

    def _draw(self) -> None:
        self.delivery.show(self._shown_splats())

    def _draw_points(self) -> None:
        """The Cube-Cloud points on the kept side of the clipping plane; none while they are hidden
        (they start hidden, and a `detail` scene's 200k points were 2.2 MB of the 5.5 MB that
        reached each page)."""
        shown = self._nodes["points"].visible if "points" in self._nodes else False
        points, colours = self.context.points, self.context.point_colours
        if not shown:
            points, colours = points[:0], colours[:0]
        normal = self.clip.normal()
        if normal is not None:
            keep = clip_mask(points, normal, self.clip.position, self.clip.keep)  # type: ignore[arg-type]
            points, colours = points[keep], colours[keep]
        half_voxel = 1.0 / (self.slices.size or FALLBACK_VOXELS)  # a whole voxel would fill the body solid
        self._nodes["points"] = self.server.scene.add_point_cloud(
            "/cube_cloud", points * self.scale, colours, point_size=half_voxel * self.scale, point_shape="circle",
            visible=shown,
        )  # fmt: skip

    def _add_labels(self) -> None:
        for text, direction in PATIENT_LABELS.items():
            position = np.asarray(direction, dtype=np.float64) * 1.15 * self.scale
            self.server.scene.add_label(f"/axes/{text}", text, position=position, anchor="center-center")

    def _add_context_layers(self) -> None:
        context = self.context
        if context.volume is not None:
            for axis in SLICE_AXES:
                self._draw_slice(axis)
        if context.points is not None:
            self._draw_points()
        if context.cameras is not None:
            self._add_cameras(context.cameras, context.thumbnails)

    def _draw_slice(self, axis: str) -> None:
        image, wxyz, position = self.slices.plane(axis)
        self._nodes[f"slice {axis}"] = self.server.scene.add_image(
            f"/slices/{axis}", image, 2.0 * self.scale, 2.0 * self.scale, format="png", wxyz=wxyz,
            position=position * self.scale, visible=self.slices.visible[axis], cast_shadow=False, receive_shadow=False,
        )  # fmt: skip

    def _add_cameras(self, cameras, images: np.ndarray) -> None:
        self._nodes["cameras"] = self.server.scene.add_frame("/cameras", show_axes=False, visible=False)
        wxyz, centres = camera_poses(cameras)
        size = FRUSTUM_SIZE * float(np.median(np.linalg.norm(centres, axis=1))) * self.scale
        for index in range(len(cameras)):
            frustum = self.server.scene.add_camera_frustum(
                f"/cameras/view_{index:03d}", fov=cameras.fov_y, aspect=cameras.width / cameras.height, scale=size,
                thickness=1.5, thickness_units="screen", color=FRUSTUM_COLOUR, image=np.repeat(images[index][..., None], 3, axis=-1), format="png",
                wxyz=wxyz[index], position=centres[index] * self.scale,
            )  # fmt: skip
            frustum.on_click(lambda event, index=index: self.look_through(event.client, index))

    # ----------------------------------------------------------------------------- the controls

    def _sync_controls(self, **values) -> None:
        """Set the page's controls to ``values`` (a change made from Python shows on the page)."""
        for name, value in values.items():
            control = self._controls.get(name)
            if control is not None and control.value != value:
                control.value = value

    def _add_controls(self) -> None:
        gui = self.server.gui
        run = gui.add_dropdown("Run", tuple(self.runs), initial_value=self.current)
        run.on_update(lambda _: self.select_run(run.value))
        splats = gui.add_checkbox("Gaussians", initial_value=True, hint="Show the trained Gaussians")
        splats.on_update(lambda _: self.show_splats(splats.value))
        detail = gui.add_slider("Detail (%)", min=1, max=100, step=1, initial_value=self.detail,
                                hint="Share of the Gaussians drawn, those that shape the picture most first: "
                                     "lower it where the browser has no GPU")  # fmt: skip
        detail.on_update(lambda _: self.set_detail(detail.value))
        self._controls.update(splats=splats, detail=detail)
        reset = gui.add_button("Reset view", hint="Back to the export's first view")
        reset.on_click(lambda event: self.reset_view(event.client))
        self._add_clip_controls()
        if any(_is_scalar_run(path) for path in self.runs.values()):
            # A baked run leaves the folder disabled; a control's late echo then changes nothing.
            from_page = lambda **choice: self.scalar_scene is not None and self.set_transfer(**choice)  # noqa: E731
            # Open when the first run shown is scalar; a baked one leaves it closed (and disabled).
            self._controls.update(
                add_transfer_controls(
                    self.server.gui, from_page, shown_presets(self.intensity_map), expand=self.scalar_scene is not None
                )
            )
            self._sync_transfer_controls()
        if self.context.volume is not None:
            self._add_slice_controls()
        if self.context.points is not None or self.context.cameras is not None:
            self._add_export_controls()

        @self.server.on_client_connect
        def _follow_camera(client) -> None:
            reports = itertools.count()

            @client.camera.on_update
            def _(camera) -> None:
                direction = np.asarray(camera.look_at) - np.asarray(camera.position)
                length = float(np.linalg.norm(direction))
                if length > 0:  # kept for the next cut: redrawing on every camera move would flood the page
                    self.clip.view_direction = direction / length
                # A page's first report is viser's default camera, from before it took the home view
                # (the scene is drawn from there already); later ones redraw once the camera rests.
                first = next(reports) == 0
                if not first and self.scalar_scene is not None and self.scalar_scene.follows_camera:
                    self._camera_rest.moved(camera.position)

    def _add_clip_controls(self) -> None:
        gui = self.server.gui
        with gui.add_folder("Clipping plane"):
            axis = gui.add_dropdown("Cut", CLIP_CHOICES, initial_value="off")
            position = gui.add_slider("Position", min=-1.0, max=1.0, step=0.01, initial_value=0.0)
            flip = gui.add_checkbox("Keep the other side", initial_value=False)
        self._controls.update(axis=axis, position=position, flip=flip)
        axis.on_update(lambda _: self.set_clip(axis.value))
        position.on_update(lambda _: self.set_clip(self.clip.axis, position.value))
        flip.on_update(lambda _: self.set_clip(self.clip.axis, keep="above" if flip.value else "below"))

    def _sync_transfer_controls(self) -> None:
        """The transfer-function controls show the current run's choice; a baked run disables them."""
        for name in CONTROLS:
            if name in self._controls:
                self._controls[name].disabled = self.scalar_scene is None
        if self.scalar_scene is not None:
            self._sync_controls(**self.scalar_scene.control_values())

    def _add_slice_controls(self) -> None:
        gui, last = self.server.gui, self.slices.size - 1
        with gui.add_folder("Scan slices", expand_by_default=False):
            for axis in SLICE_AXES:
                shown = gui.add_checkbox(axis.capitalize(), initial_value=False, hint=f"Show the {axis} slice")
                index = gui.add_slider(f"{axis.capitalize()} slice", min=0, max=last, step=1,
                                       initial_value=self.slices.index[axis])  # fmt: skip
                shown.on_update(lambda _, axis=axis, shown=shown: self.show_slice(axis, visible=shown.value))
                index.on_update(lambda _, axis=axis, index=index: self.show_slice(axis, index=index.value))
                self._controls.update({f"{axis} shown": shown, f"{axis} index": index})
            opacity = gui.add_slider("Opacity", min=0.0, max=1.0, step=0.05, initial_value=self.slices.opacity)
        opacity.on_update(lambda _: self.set_slice_opacity(opacity.value))
        self._controls["opacity"] = opacity

    def _add_export_controls(self) -> None:
        gui = self.server.gui
        with gui.add_folder("Export", expand_by_default=False):
            if self.context.points is not None:
                points = gui.add_checkbox("Cube-Cloud points", initial_value=False, hint="The points 3DGS started from")
                points.on_update(lambda _: self.show_points(points.value))
                self._controls["points"] = points
            if self.context.cameras is not None:
                cameras = gui.add_checkbox("Cameras", initial_value=False, hint="Click a camera to look through it")
                cameras.on_update(lambda _: self.show_cameras(cameras.value))
                self._controls["cameras"] = cameras
