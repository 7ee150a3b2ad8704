"""`cubecloud view` on a scalar scene: colour maps, the transfer-function choice, the recolouring
server and, in a real browser, the picture under another transfer function."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from cli_helpers import tiny_work
from hypothesis import given
from hypothesis import strategies as st
from test_view import agreement, drawn, free_port

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.splat.scalar_gaussians import scalar_gaussians_from_points, transfer_opacities
from cubecloud_cli.transfer.function import TransferFunction
from cubecloud_cli.view.browser import chromium, screenshot
from cubecloud_cli.view.transfer_view import COLOUR_MAPS, CUSTOM, TRAINED_PRESET, ScalarScene, colour_map

pytestmark = pytest.mark.slow

QUICK = ["--iterations", "200", "--eval-every", "100", "--checkpoint-every", "100", "-q"]
CT_WINDOW = {"modality": "ct", "low": -160.0, "high": 240.0}


@given(
    st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=1, max_size=20),
    st.sampled_from(sorted(COLOUR_MAPS)),
)
def test_colour_maps_give_colours_in_range_for_any_value(values, name):
    colours = colour_map(np.array(values), name)
    assert colours.shape == (len(values), 3) and np.isfinite(colours).all()
    assert colours.min() >= 0.0 and colours.max() <= 1.0


def test_the_grey_map_is_the_value_and_each_map_ends_at_its_anchors():
    values = np.linspace(0, 1, 11)
    np.testing.assert_allclose(colour_map(values, "grey"), np.repeat(values[:, None], 3, axis=1), atol=1e-7)
    for name, anchors in COLOUR_MAPS.items():
        ends = colour_map(np.array([0.0, 1.0, -3.0, 7.0]), name)
        np.testing.assert_allclose(ends, [anchors[0], anchors[-1], anchors[0], anchors[-1]], atol=1e-7)


def scalar_scene() -> ScalarScene:
    xyz = np.random.default_rng(0).uniform(-0.8, 0.8, (200, 3))
    values = np.random.default_rng(1).uniform(0.2, 1.0, 200)
    return ScalarScene(scalar_gaussians_from_points(xyz, values, [TransferFunction(0.3, 0.9, 4.0)]), CT_WINDOW)


def test_a_preset_recolours_only_the_opacities_and_colours_and_the_window_stays_a_window():
    scene = scalar_scene()
    before = scene.splats()
    assert scene.control_values()["transfer preset"] == TRAINED_PRESET
    assert scene.choose(preset="bone") and not scene.choose(preset="bone")  # the same choice twice: no change
    bone = scene.presets["bone"]
    expected = transfer_opacities(scene.scalar.values(), scene.scalar.log_lengths, bone).numpy()
    after = scene.splats()  # importance order changes with the opacities: compare as sets
    np.testing.assert_allclose(
        np.sort(after.opacities[:, 0]), np.sort(expected.astype(np.float32)), rtol=1e-5, atol=1e-7
    )
    assert np.array_equal(np.sort(before.centers, axis=0), np.sort(after.centers, axis=0))
    assert scene.choose(low=0.8, high=0.2)  # a high below the low: the window closes at the low, never inverts
    assert scene.chosen.function.low == 0.8 and scene.chosen.function.high == 0.8
    assert scene.control_values()["transfer preset"] == CUSTOM
    assert scene.choose(opacity=float("nan")) is False and scene.chosen.opacity_scale == 1.0  # NaN: the default
    scene.choose(opacity=1e9)
    assert math.isfinite(scene.chosen.effective().density) and np.isfinite(scene.splats().opacities).all()
    with pytest.raises(CubecloudError, match="must be one of"):
        scene.choose(preset="lungs")
    with pytest.raises(CubecloudError, match="colour map"):
        scene.choose(colour_map="rainbow")


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    work = tiny_work(tmp_path_factory.mktemp("view_transfer") / "work", cunerf_iterations=200, views=16,
                     max_points=3000, novel_directions=0, splat=[*QUICK, "--scalar"])  # fmt: skip
    from cli_helpers import invoke

    assert invoke("splat", work, *QUICK, "--name", "baked").exit_code == 0
    return work


@pytest.fixture(scope="module")
def viewer(work):
    from cubecloud_cli.view.server import SceneViewer

    viewer = SceneViewer(work, port=free_port())
    yield viewer
    viewer.stop()


def test_the_viewer_recolours_a_scalar_run_and_refuses_a_baked_one(viewer):
    assert viewer.current == "splat" and viewer.scalar_scene is not None
    trained = viewer.splats.opacities.copy()
    viewer.set_transfer(preset="bone")
    assert viewer._controls["transfer preset"].value == "bone" and not viewer._controls["window low"].disabled
    assert not np.array_equal(np.sort(trained[:, 0]), np.sort(viewer.splats.opacities[:, 0]))
    viewer.set_transfer(colour_map="hot")
    assert not np.allclose(viewer.splats.rgbs[:, 0], viewer.splats.rgbs[:, 2])  # no longer grey
    viewer.select_run("splat-baked")
    assert viewer._controls["transfer preset"].disabled
    with pytest.raises(CubecloudError, match="not a scalar scene"):
        viewer.set_transfer(preset="bone")
    viewer.select_run("splat")
    assert viewer._controls["transfer preset"].value == TRAINED_PRESET


@pytest.mark.skipif(chromium() is None, reason="needs chromium (.ci/run installs it)")
@pytest.mark.usefixtures("every_core")
def test_a_real_browser_shows_the_scene_under_the_transfer_function_chosen(viewer, work, tmp_path):
    """From the export's first view, the page under the tissue preset and under a narrow dense
    window (0.30–0.45, opacity × 7.5: the soft tissue's surface) agrees with the volume rendered
    under each, and better than with the volume under the other (on the 32³ scene bone shows
    almost nothing: 0.5 % of its voxels)."""
    from cubecloud_cli.render import GridField, ImageModel, render_view

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
