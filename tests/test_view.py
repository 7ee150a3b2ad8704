"""`cubecloud view`: the bad-input contract, the server's clipping, and the page in a real browser."""

import base64
import math
import shutil
import signal
import socket
import subprocess
import sys

import numpy as np
import pytest
import torch
from cli_helpers import assert_one_line_error, invoke
from hypothesis import given
from hypothesis import strategies as st

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.view.browser import chromium, received_bytes, screenshot
from cubecloud_cli.view.transfer_view import TRAINED_PRESET

pytestmark = pytest.mark.slow  # runs first: pytest-xdist's workers then end together


@pytest.fixture(scope="module")
def work(viewable_work):
    return viewable_work


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_bad_input_is_one_line_with_exit_2(work, tmp_path):
    assert_one_line_error(invoke("view", tmp_path / "nowhere"), r"is not a work directory: run `cubecloud run")
    (tmp_path / "empty").mkdir()
    assert_one_line_error(invoke("view", tmp_path / "empty"), r"has no finished splat run: run `cubecloud splat")
    assert_one_line_error(invoke("view", work, "--run", "splat-nothing"), r"no finished run 'splat-nothing'")
    assert_one_line_error(invoke("view", work, "--detail", "0"), r"--detail 0 must be a percent from 1 to 100")
    broken = tmp_path / "broken"
    shutil.copytree(work, broken)
    (broken / "splat" / "point_cloud.ply").write_bytes(b"ply\nformat ascii 1.0\nend_header\ngarbage")
    assert_one_line_error(invoke("view", broken), r"point_cloud.ply is not")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert_one_line_error(invoke("view", work, "--port", str(port)), rf"cannot listen on 127.0.0.1:{port}.*--port")
    for port in ("70000", "-1", "0"):
        assert_one_line_error(invoke("view", work, "--port", port), rf"--port {port} is not a port: .* 1 to 65535")
    result = invoke("view", work, "--host", "not-a-host.invalid")
    assert_one_line_error(result, r"--host not-a-host.invalid does not resolve")
    assert "listening on" not in result.output  # no warning about a server that never starts


def test_sigterm_stops_the_viewer_as_ctrl_c_does(work):
    """What a scheduler or `kill` sends: the server stops and says so, with no traceback."""
    command = [sys.executable, "-m", "cubecloud_cli", "view", str(work), "--port", str(free_port())]
    server = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = []
    for line in server.stdout:
        lines.append(line)
        if "Ctrl-C stops" in line:
            break
    server.send_signal(signal.SIGTERM)
    output, _ = server.communicate(timeout=60)
    assert server.returncode == 0, "".join(lines) + output
    assert "viewer stopped" in output and "Traceback" not in output


@given(st.binary(max_size=40), st.text(max_size=40), st.integers(0, 10**9))
def test_the_byte_count_reads_what_devtools_says_reached_the_page(payload, text, encoded):
    def frame(opcode, data):
        return {
            "method": "Network.webSocketFrameReceived",
            "params": {"response": {"opcode": opcode, "payloadData": data}},
        }

    assert received_bytes(frame(2, base64.b64encode(payload).decode())) == ("websocket", len(payload))
    assert received_bytes(frame(1, text)) == ("websocket", len(text.encode()))
    finished = {"method": "Network.loadingFinished", "params": {"encodedDataLength": encoded}}
    assert received_bytes(finished) == ("http", encoded)
    assert received_bytes({"method": "Page.screencastFrame", "params": {"data": "AAAA"}}) == ("", 0)


def test_a_port_whose_last_connection_is_closing_counts_as_free():
    """A viewer stopped and started again at once finds its port's old connections in TIME_WAIT
    for a minute; the port is free to listen on (as viser's own server sees it)."""
    from cubecloud_cli.view.listening import check_port_free

    with socket.socket() as listener:
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as viser's server (asyncio) listens
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        port = listener.getsockname()[1]
        with socket.create_connection(("127.0.0.1", port)) as client:
            accepted, _ = listener.accept()
            accepted.close()  # the server's side closes first, so its port waits in TIME_WAIT
            client.recv(1)
    check_port_free("127.0.0.1", port)


@pytest.fixture
def viewer(work):
    from cubecloud_cli.view.server import SceneViewer

    viewer = SceneViewer(work, port=free_port())
    yield viewer
    viewer.stop()


@pytest.fixture(scope="module")
def scalar_viewer(work):
    from cubecloud_cli.view.server import SceneViewer

    viewer = SceneViewer(work, port=free_port(), run="splat-scalar")
    yield viewer
    viewer.stop()


def test_the_scene_has_no_lighting_to_wait_for(work, monkeypatch):
    """Nothing in the scene is lit, and viser's default environment map keeps the page's canvas
    at 5 % opacity until its lighting is built: the viewer turns both off."""
    from viser import _messages
    from viser.infra import WebsockMessageHandler

    from cubecloud_cli.view.server import SceneViewer

    sent = []
    queue_message = WebsockMessageHandler.queue_message
    monkeypatch.setattr(
        WebsockMessageHandler,
        "queue_message",
        lambda self, message: (sent.append(message), queue_message(self, message))[1],
    )
    viewer = SceneViewer(work, port=free_port())
    viewer.stop()
    environment = [message for message in sent if isinstance(message, _messages.EnvironmentMapMessage)]
    lights = [message for message in sent if isinstance(message, _messages.EnableLightsMessage)]
    assert environment and environment[-1].hdri_data is None
    assert lights and not lights[-1].enabled


def test_the_server_listens_on_localhost_and_the_clipping_plane_hides_half_the_body(viewer):
    assert viewer.url.startswith("http://127.0.0.1:")
    everything = viewer.visible_count()
    assert everything == len(viewer.splats) > 100
    viewer.set_clip("sagittal", 0.0)
    left = viewer.visible_count()
    viewer.set_clip("sagittal", 0.0, keep="above")
    right = viewer.visible_count()
    assert 0.25 * everything < left < 0.75 * everything and left + right >= everything
    viewer.set_clip("axial", float(viewer.splats.centers[:, 2].max()), keep="below")
    assert viewer.visible_count() == everything  # a plane above the highest Gaussian hides nothing
    viewer.set_clip("off")
    assert viewer.visible_count() == everything


def test_a_lower_detail_draws_the_most_important_gaussians(viewer):
    everything = viewer.visible_count()
    viewer.set_detail(10)
    assert viewer.visible_count() == math.ceil(everything / 10) and viewer._controls["detail"].value == 10
    drawn = viewer.drawn_splats()
    assert np.array_equal(drawn.centers, viewer.splats.centers[: len(drawn)])  # the run is kept in importance order
    weight = viewer.splats.opacities[:, 0] * np.trace(viewer.splats.covariances, axis1=1, axis2=2)
    assert weight[: len(drawn)].min() >= weight[len(drawn) :].max()
    viewer.set_detail(float("nan"))
    assert viewer.visible_count() == everything


def test_the_slices_points_and_cameras_follow_their_controls(viewer, work):
    context = viewer.context
    assert context.left_out == [] and context.volume.shape == (32, 32, 32)
    assert len(context.cameras) == 16 and context.thumbnails.shape == (16, 32, 32)
    assert not viewer._nodes["slice axial"].visible  # the Gaussians come first; the slices are asked for
    viewer.show_slice("axial", index=5, visible=True)
    axial = viewer._nodes["slice axial"]
    assert axial.visible and viewer._controls["axial index"].value == 5 and viewer._controls["axial shown"].value
    assert axial.position[2] == pytest.approx((11 / 32 - 1) * viewer.scale)
    assert np.array_equal(axial.image[..., 0], np.round(np.clip(context.volume[:, :, 5].T, 0, 1) * 255))
    viewer.set_slice_opacity(0.5)
    assert np.all(viewer._nodes["slice axial"].image[..., 3] == 128)

    points = len(context.points)
    assert len(viewer._nodes["points"].points) == 0  # hidden points are not sent to the pages
    viewer.show_points(True)
    assert viewer._nodes["points"].visible and len(viewer._nodes["points"].points) == points
    viewer.set_clip("coronal", 0.0)
    assert 0.2 * points < len(viewer._nodes["points"].points) < 0.8 * points  # the cut takes the points too
    assert viewer._nodes["points"].visible
    viewer.show_cameras(True)
    assert viewer._nodes["cameras"].visible and viewer._controls["cameras"].value


class FakeClient:
    """What SceneViewer needs of a connected browser: its id and its camera, set atomically."""

    def __init__(self, client_id: int = 0):
        self.client_id = client_id
        self.camera = type("Camera", (), {})()

    def atomic(self):
        import contextlib

        return contextlib.nullcontext()


def test_reset_view_and_a_click_on_a_camera_move_the_browsers_camera(viewer):
    from cubecloud_cli.view.layers import camera_view

    client = FakeClient()
    viewer.look_through(client, 3)
    expected = camera_view(viewer.context.cameras, 3)
    assert np.allclose(client.camera.position, expected.position * viewer.scale)
    assert np.allclose(client.camera.up_direction, expected.up) and client.camera.fov == expected.fov
    viewer.reset_view(client)
    assert np.allclose(client.camera.position, viewer.home.position)
    assert np.allclose(viewer.home.position, viewer.context.cameras.centres()[0] * viewer.scale)


def test_a_screenshot_waits_for_every_browser_to_reach_the_home_view_with_every_gaussian(viewer, monkeypatch):
    clients, drawn = {}, [True]
    monkeypatch.setattr(viewer.server, "get_clients", lambda: clients)
    monkeypatch.setattr(viewer.delivery, "pages_drawn", lambda client_ids: drawn[0] and list(client_ids) == [0, 1])
    assert not viewer.browsers_at_home()  # none connected yet
    at_home, elsewhere = FakeClient(0), FakeClient(1)
    viewer.reset_view(at_home)
    viewer.look_through(elsewhere, 3)
    clients.update({0: at_home, 1: elsewhere})
    assert not viewer.browsers_at_home()
    viewer.reset_view(elsewhere)
    assert viewer.browsers_at_home()
    drawn[0] = False  # a page has not drawn every Gaussian yet
    assert not viewer.browsers_at_home()


def test_a_damaged_volume_leaves_the_slices_out_and_still_shows_the_gaussians(work, tmp_path):
    from cubecloud_cli.view.server import SceneViewer

    damaged = tmp_path / "damaged"
    shutil.copytree(work, damaged)
    (damaged / "preprocess" / "volume.npy").write_bytes(b"not an array")
    viewer = SceneViewer(damaged, port=free_port())
    try:
        assert viewer.context.volume is None and viewer.visible_count() > 100
        assert "slice axial" not in viewer._nodes and "axial index" not in viewer._controls
        [line] = viewer.context.left_out
        assert line.startswith("scan slices left out") and "volume.npy" in line and "--force" in line
    finally:
        viewer.stop()


# ------------------------------------------------------------------------------ in a real browser


def scene_pixels(image: np.ndarray) -> np.ndarray:
    """Where the splats are drawn: brighter than the black background, away from the GUI panels."""
    mask = image.mean(axis=-1) > 40
    mask[:160, :330] = False  # the browser's software-rendering notice
    mask[:300, 560:] = False  # the control panel
    return mask


def drawn(image: np.ndarray) -> bool:
    """Something of the scene is on the page (not only the background, the labels and the GUI)."""
    return scene_pixels(image).sum() > 0.01 * image.shape[0] * image.shape[1]


def window_pixels(pose, points: np.ndarray, width: int, height: int) -> np.ndarray:
    """Where a perspective camera at ``pose`` (the browser's: vertical field of view, principal
    point at the window's centre) puts world ``points``, as (column, row) in pixels."""
    forward = (pose.look_at - pose.position) / np.linalg.norm(pose.look_at - pose.position)
    right = np.cross(forward, pose.up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    focal = (height / 2) / np.tan(pose.fov / 2)
    relative = points - pose.position
    depth = relative @ forward
    return np.stack([width / 2 + focal * (relative @ right) / depth, height / 2 + focal * (relative @ down) / depth], 1)


def agreement(shot: np.ndarray, pixels: np.ndarray, values: np.ndarray) -> float:
    """Pearson r between the screenshot's grey at ``pixels`` and the expected ``values`` (pixels
    under the page's panels are left out)."""
    grey = shot.mean(axis=-1)
    column, row = pixels[:, 0].astype(int), pixels[:, 1].astype(int)
    inside = (column >= 0) & (column < grey.shape[1]) & (row >= 0) & (row < grey.shape[0])
    clear = inside & ~((column >= 560) & (row < 300)) & ~((column < 330) & (row < 160))
    return float(np.corrcoef(grey[row[clear], column[clear]], values[clear])[0, 1])


@pytest.mark.skipif(chromium() is None, reason="needs chromium (.ci/run installs it)")
@pytest.mark.usefixtures("every_core")  # SwiftShader on one core took 3 times as long
def test_a_real_browser_shows_the_exports_first_view_a_cut_and_slices_that_line_up(viewer, work, tmp_path):
    from cubecloud_cli.view.layers import camera_view, slice_pixel_world

    def ready(image: np.ndarray) -> bool:
        return drawn(image) and viewer.browsers_at_home()

    viewer.delivery.coarse = len(viewer.splats) // 4  # the page gets a coarse set first, as a large scene's would
    shot = screenshot(viewer.url, tmp_path / "home.png", ready=ready)
    before = scene_pixels(shot)
    height, width = before.shape
    assert before.sum() > 0.02 * height * width, "no scene drawn"
    # The page opens on the export's first view: its training image, scaled to the window's height.
    cameras, image = viewer.context.cameras, np.load(work / "export" / "images.npy")[0]
    rows, columns = np.mgrid[0 : cameras.height, 0 : cameras.width]
    magnification = (height / 2) / np.tan(cameras.fov_y / 2) / cameras.focal
    pixels = np.stack([width / 2 + (columns + 0.5 - cameras.cx) * magnification,
                       height / 2 + (rows + 0.5 - cameras.cy) * magnification], -1).reshape(-1, 2)  # fmt: skip
    assert agreement(shot, pixels, image.reshape(-1)) > 0.85, "the first view is not the export's"

    viewer.set_clip("sagittal", 0.0)
    after = scene_pixels(screenshot(viewer.url, tmp_path / "cut.png", ready=ready))
    assert 0.2 * before.sum() < after.sum() < 0.8 * before.sum()
    removed = before & ~after
    kept_centre = np.array(np.nonzero(after)).mean(axis=1)
    removed_centre = np.array(np.nonzero(removed)).mean(axis=1)
    assert np.linalg.norm(kept_centre - removed_centre) > 0.08 * min(height, width), "the cut took no side away"

    # The axial slice alone: each voxel shows where the volume's voxel is, seen from the first view.
    viewer.set_clip("off")
    viewer.show_splats(False)
    viewer.show_slice("axial", index=16, visible=True)
    shot = screenshot(viewer.url, tmp_path / "slice.png", ready=ready)
    size = viewer.slices.size
    cells = [(row, column) for row in range(size) for column in range(size)]
    world = np.array([slice_pixel_world("axial", 16, size, row, column) for row, column in cells])
    pixels = window_pixels(camera_view(cameras, 0), world, width, height)
    values = viewer.context.volume[:, :, 16].T.reshape(-1)
    assert agreement(shot, pixels, values) > 0.85, "the slice does not lie where its voxels are"


# -- a scalar scene (splat --scalar): the transfer-function panel ------------------------------------


def test_the_viewer_recolours_a_scalar_run_and_refuses_a_baked_one(scalar_viewer):
    viewer = scalar_viewer
    assert viewer.current == "splat-scalar" and viewer.scalar_scene is not None
    trained = viewer.splats.opacities.copy()
    viewer.set_transfer(preset="bone")
    assert viewer._controls["transfer preset"].value == "bone" and not viewer._controls["window low"].disabled
    assert not np.array_equal(np.sort(trained[:, 0]), np.sort(viewer.splats.opacities[:, 0]))
    viewer.set_transfer(colour_map="hot")
    assert not np.allclose(viewer.splats.rgbs[:, 0], viewer.splats.rgbs[:, 2])  # no longer grey
    viewer.select_run("splat")
    assert viewer._controls["transfer preset"].disabled
    with pytest.raises(CubecloudError, match="not a scalar scene"):
        viewer.set_transfer(preset="bone")
    viewer.select_run("splat-scalar")
    assert viewer._controls["transfer preset"].value == TRAINED_PRESET


def test_a_chord_scene_is_drawn_for_the_camera_it_rests_at(scalar_viewer):
    """The scalar scene's opacities follow the view (chord lengths): the viewer draws them as the
    trainer does for the camera at rest, first the export's first view, then wherever a page's
    camera stops."""
    viewer = scalar_viewer
    scalar = viewer.scalar_scene.scalar
    assert viewer.scalar_scene.follows_camera
    centres = viewer.context.cameras.centres()

    def model_opacities(centre):
        with torch.no_grad():
            return np.sort(scalar.opacities(torch.as_tensor(centre, dtype=torch.float32)).numpy())

    drawn = np.sort(viewer.splats.opacities[:, 0])
    np.testing.assert_allclose(drawn, model_opacities(centres[0]), atol=2e-5)
    viewer.look_from(centres[5] * viewer.scale)
    moved = np.sort(viewer.splats.opacities[:, 0])
    np.testing.assert_allclose(moved, model_opacities(centres[5]), atol=2e-5)
    assert np.abs(moved - drawn).max() > 1e-3
    viewer.look_from(centres[0] * viewer.scale)


@pytest.mark.skipif(chromium() is None, reason="needs chromium (.ci/run installs it)")
@pytest.mark.usefixtures("every_core")
def test_a_real_browser_shows_the_scene_under_the_transfer_function_chosen(scalar_viewer, work, tmp_path):
    """From the export's first view, the page under the tissue preset and under a narrow dense
    window (0.30–0.45, opacity × 7.5: the soft tissue's surface) agrees with the volume rendered
    under each, and better than with the volume under the other (on the 32³ scene bone shows
    almost nothing: 0.5 % of its voxels)."""
    from cubecloud_cli.render import GridField, ImageModel, render_view

    viewer = scalar_viewer
    volume = np.load(work / "preprocess" / "volume.npy")
    cameras = viewer.context.cameras
    expected, shots = {}, {}
    for name, choice in (("tissue", {"preset": "tissue"}), ("window", {"low": 0.3, "high": 0.45, "opacity": 7.5})):
        viewer.set_transfer(**choice)
        model = ImageModel("dvr", viewer.scalar_scene.chosen.effective(), step=2.0 / volume.shape[0])
        expected[name] = render_view(GridField(volume, torch.device("cpu")), cameras, 0, model).numpy().reshape(-1)
        ready = lambda image: drawn(image) and viewer.browsers_at_home()  # noqa: E731
        shots[name] = screenshot(viewer.url, tmp_path / f"{name}.png", ready=ready)
    height, width = shots["tissue"].shape[:2]
    rows, columns = np.mgrid[0 : cameras.height, 0 : cameras.width]
    magnification = (height / 2) / np.tan(cameras.fov_y / 2) / cameras.focal
    pixels = np.stack([width / 2 + (columns + 0.5 - cameras.cx) * magnification,
                       height / 2 + (rows + 0.5 - cameras.cy) * magnification], -1).reshape(-1, 2)  # fmt: skip
    scores = {(shot, truth): agreement(shots[shot], pixels, expected[truth]) for shot in shots for truth in expected}
    assert scores["tissue", "tissue"] > 0.75 and scores["window", "window"] > 0.75, scores
    assert scores["tissue", "tissue"] > scores["tissue", "window"], scores
    assert scores["window", "window"] > scores["window", "tissue"], scores
    viewer.set_transfer(preset=TRAINED_PRESET, opacity=1.0)
