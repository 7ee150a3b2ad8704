"""The viewer's context layers: each slice pixel lands on the voxel it shows, and the export's
cameras become viewer cameras that see what they saw."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.cameras import OrbitSpec, sphere_cameras
from cubecloud_cli.scene.quaternions import quaternion_to_rotation
from cubecloud_cli.view.context import load_context, thumbnails
from cubecloud_cli.view.layers import (
    SLICE_AXES,
    SliceLayer,
    camera_poses,
    camera_view,
    slice_image,
    slice_index,
    slice_pixel_world,
    slice_pose,
    slice_rotation,
    voxel_centre,
)
from cubecloud_cli.view.splats import CLIP_AXES


@settings(max_examples=60, deadline=None)
@given(
    size=st.integers(1, 9),
    axis=st.sampled_from(SLICE_AXES),
    data=st.data(),
)
def test_every_slice_pixel_is_drawn_on_the_centre_of_the_voxel_it_shows(size, axis, data):
    volume = np.random.default_rng(size).random((size, size, size)).astype(np.float32)
    index = data.draw(st.integers(0, size - 1))
    row, column = data.draw(st.integers(0, size - 1)), data.draw(st.integers(0, size - 1))
    image = slice_image(volume, axis, index)
    world = slice_pixel_world(axis, index, size, row, column)
    voxel = tuple(slice_index(size, coordinate) for coordinate in world)
    assert np.allclose(world, [voxel_centre(i, size) for i in voxel])  # on a voxel centre, not between two
    assert voxel[CLIP_AXES[axis]] == index
    assert image[row, column, 0] == round(float(volume[voxel]) * 255)


@pytest.mark.parametrize("axis", SLICE_AXES)
def test_a_slice_plane_is_a_rotation_across_its_axis(axis):
    rotation = slice_rotation(axis)
    assert np.allclose(rotation @ rotation.T, np.eye(3)) and np.isclose(np.linalg.det(rotation), 1.0)
    assert np.allclose(np.abs(rotation[:, 2]), np.eye(3)[CLIP_AXES[axis]])  # the plane's normal is the axis
    wxyz, centre = slice_pose(axis, 0, 4)
    assert np.allclose(quaternion_to_rotation(wxyz), rotation)
    assert centre[CLIP_AXES[axis]] == pytest.approx(-0.75) and np.count_nonzero(centre) == 1


@settings(max_examples=50, deadline=None)
@given(
    position=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(-1.0, 1.0)), size=st.integers(1, 512)
)
def test_a_slice_index_is_always_inside_the_volume(position, size):
    assert 0 <= slice_index(size, position) < size


def test_slice_images_clamp_stray_values_and_opacity():
    volume = np.array([np.nan, -np.inf, -3.0, 0.5, 2.0, np.inf, 1e30, 0.0], dtype=np.float32).reshape(2, 2, 2)
    image = slice_image(volume, "axial", 0, opacity=7.0)
    assert image.dtype == np.uint8 and image.shape == (2, 2, 4)
    assert set(np.unique(image[..., 0])) <= {0, 128, 255}
    assert np.all(image[..., 3] == 255)
    assert np.all(slice_image(volume, "axial", 1, opacity=-1.0)[..., 3] == 0)
    assert np.all(slice_image(volume, "axial", 1, opacity=float("nan"))[..., 3] == 0)


def test_the_slice_layer_clamps_and_says_when_something_changed():
    layer = SliceLayer(np.zeros((8, 8, 8), dtype=np.float32))
    assert layer.index == {"axial": 4, "coronal": 4, "sagittal": 4} and not any(layer.visible.values())
    assert layer.update("axial", index=100, visible=True) and layer.index["axial"] == 7
    assert not layer.update("axial", index=7)  # the page echoing the change
    assert layer.update("coronal", index=-5) and layer.index["coronal"] == 0
    with pytest.raises(ValueError, match="slice axis 'oblique'"):
        layer.update("oblique", index=1)


def test_an_export_camera_as_a_viewer_camera_sees_the_origin_at_its_image_centre():
    cameras = sphere_cameras(OrbitSpec(views=12, resolution=32, radius=3.0))
    wxyz, centres = camera_poses(cameras)
    assert np.allclose(quaternion_to_rotation(wxyz), cameras.camera_to_world()[:, :3, :3])
    for index in range(len(cameras)):
        pose = camera_view(cameras, index)
        assert np.allclose(pose.position, centres[index])
        assert np.allclose(pose.look_at, 0.0, atol=1e-9)  # our cameras look at the origin
        forward = (pose.look_at - pose.position) / np.linalg.norm(pose.look_at - pose.position)
        assert abs(forward @ pose.up) < 1e-9 and np.isclose(np.linalg.norm(pose.up), 1.0)
        # The image's top row is where the pose's up points.
        top = cameras.project(index, (pose.position + forward + 0.01 * pose.up)[None])[0][0]
        assert top[1] < cameras.cy and abs(top[0] - cameras.cx) < 1e-6
        assert pose.fov == pytest.approx(cameras.fov_y)


def test_thumbnails_keep_every_view_and_shrink_by_a_whole_stride():
    images = np.random.default_rng(0).random((3, 300, 200)).astype(np.float32)
    small = thumbnails(images, side=128)
    assert small.shape == (3, 100, 67) and small.dtype == np.uint8
    assert thumbnails(images[:, :10, :10]).shape == (3, 10, 10)
    assert thumbnails(images, side=0).shape == (3, 1, 1)


def test_a_work_directory_without_preprocess_or_export_leaves_those_layers_out(tmp_path):
    context = load_context(tmp_path)
    assert context.volume is None and context.points is None and context.cameras is None
    assert [line.split(" left out")[0] for line in context.left_out] == ["scan slices", "Cube-Cloud points", "cameras"]
    assert all("run `cubecloud" in line for line in context.left_out)
