import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.volume.cube_frame import plan_cube


def _affine(spacing, origin=(10.0, -20.0, 30.0)):
    affine = np.diag([*spacing, 1.0])
    affine[:3, 3] = origin
    return affine


def test_world_coordinates_of_voxel_centres():
    frame = plan_cube((10, 10, 10), _affine((1, 1, 1)), 8, "pad")
    to_world = frame.voxel_to_world()
    for index in [(0, 0, 0), (7, 3, 5)]:
        world = to_world @ np.array([*index, 1.0])
        assert np.allclose(world[:3], (2 * np.array(index) + 1) / 8 - 1)


def test_pad_keeps_physical_aspect_and_centres_the_scan():
    shape, spacing = (100, 50, 20), (1.0, 2.0, 10.0)  # extents 100, 100, 200 mm
    frame = plan_cube(shape, _affine(spacing), 64, "pad")
    assert np.allclose(frame.voxel_size_mm, 200 / 64)
    assert np.allclose(frame.mm_per_world_unit, 100.0)
    # The centre of the cube maps to the centre of the scan.
    centre_index = frame.voxel_to_source_index() @ np.array([31.5, 31.5, 31.5, 1.0])
    assert np.allclose(centre_index[:3], (np.array(shape) - 1) / 2)


def test_stretch_fills_each_axis():
    frame = plan_cube((100, 50, 20), _affine((1.0, 2.0, 10.0)), 64, "stretch")
    assert np.allclose(frame.voxel_size_mm, [100 / 64, 100 / 64, 200 / 64])
    corner = frame.voxel_to_source_index() @ np.array([-0.5, -0.5, -0.5, 1.0])
    assert np.allclose(corner[:3], -0.5)  # the cube's outer edge is the scan's outer edge


@given(
    shape=st.tuples(st.integers(2, 600), st.integers(2, 600), st.integers(2, 600)),
    spacing=st.tuples(*[st.floats(1e-3, 50.0)] * 3),
    size=st.integers(8, 1024),
    fit=st.sampled_from(["pad", "stretch"]),
)
@settings(max_examples=200, deadline=None)
def test_world_to_scanner_is_consistent(shape, spacing, size, fit):
    frame = plan_cube(shape, _affine(spacing), size, fit)
    world = np.array([0.3, -0.7, 0.9, 1.0])
    via_voxel = frame.voxel_to_scanner() @ np.linalg.inv(frame.voxel_to_world()) @ world
    assert np.allclose(frame.world_to_scanner() @ world, via_voxel, rtol=1e-9, atol=1e-6)
    # The cube covers the whole scan along every axis.
    lo = frame.voxel_to_source_index() @ np.array([-0.5, -0.5, -0.5, 1.0])
    hi = frame.voxel_to_source_index() @ np.array([size - 0.5] * 3 + [1.0])
    assert np.all(lo[:3] <= -0.5 + 1e-6) and np.all(hi[:3] >= np.array(shape) - 0.5 - 1e-6)


def test_bad_fit_raises():
    with pytest.raises(ValueError):
        plan_cube((4, 4, 4), np.eye(4), 8, "squash")
