"""`cubecloud view`: the bad-input contract, the server's clipping, and the page in a real browser."""

import shutil
import socket
import time

import numpy as np
import pytest
from cli_helpers import assert_one_line_error, invoke, tiny_work

from cubecloud_cli.view.browser import chromium, screenshot

QUICK = ["--iterations", "200", "--eval-every", "100", "--checkpoint-every", "100", "-q"]


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return tiny_work(tmp_path_factory.mktemp("view") / "work", cunerf_iterations=200, views=16, max_points=3000,
                     novel_directions=0, splat=QUICK)  # fmt: skip


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_bad_input_is_one_line_with_exit_2(work, tmp_path):
    assert_one_line_error(invoke("view", tmp_path / "nowhere"), r"is not a work directory: run `cubecloud run")
    (tmp_path / "empty").mkdir()
    assert_one_line_error(invoke("view", tmp_path / "empty"), r"has no finished splat run: run `cubecloud splat")
    assert_one_line_error(invoke("view", work, "--run", "splat-nothing"), r"no finished run 'splat-nothing'")
    broken = tmp_path / "broken"
    shutil.copytree(work, broken)
    (broken / "splat" / "point_cloud.ply").write_bytes(b"ply\nformat ascii 1.0\nend_header\ngarbage")
    assert_one_line_error(invoke("view", broken), r"point_cloud.ply is not")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert_one_line_error(invoke("view", work, "--port", str(port)), rf"cannot listen on 127.0.0.1:{port}.*--port")


@pytest.fixture
def viewer(work):
    from cubecloud_cli.view.server import SceneViewer

    viewer = SceneViewer(work, port=free_port())
    yield viewer
    viewer.stop()


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


def scene_pixels(image: np.ndarray) -> np.ndarray:
    """Where the splats are drawn: brighter than the black background, away from the GUI panels."""
    mask = image.mean(axis=-1) > 40
    mask[:160, :330] = False  # the browser's software-rendering notice
    mask[:260, 560:] = False  # the control panel
    return mask


@pytest.mark.skipif(chromium() is None, reason="needs chromium (.ci/run installs it)")
def test_a_real_browser_draws_the_scene_where_the_volume_projects_and_the_cut_removes_half(viewer, tmp_path):
    time.sleep(1)
    before = scene_pixels(screenshot(viewer.url, tmp_path / "before.png"))
    height, width = before.shape
    assert before.sum() > 0.02 * height * width, "no scene drawn"
    rows, cols = np.nonzero(before)
    # The volume sits at the origin, which the first view looks at: the scene is centred.
    assert abs(cols.mean() - width / 2) < 0.15 * width and abs(rows.mean() - height / 2) < 0.15 * height

    viewer.set_clip("sagittal", 0.0)
    time.sleep(1)
    after = scene_pixels(screenshot(viewer.url, tmp_path / "after.png"))
    assert 0.2 * before.sum() < after.sum() < 0.8 * before.sum()
    removed = before & ~after
    kept_centre = np.array(np.nonzero(after)).mean(axis=1)
    removed_centre = np.array(np.nonzero(removed)).mean(axis=1)
    assert np.linalg.norm(kept_centre - removed_centre) > 0.08 * min(height, width), "the cut took no side away"
