import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from cubecloud_cli.volume.cube_frame import plan_cube, shear_degrees, size_keeping, voxels_across


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


# -- the detail preset's size rule ------------------------------------------------------------


@pytest.mark.parametrize(
    "shape, spacing, fit, expected",
    [
        ((512, 512, 48), (0.5703, 0.5703, 5.0), "pad", 512),  # the shared chest CT: its own in-plane detail
        ((100, 100, 30), (1.0, 1.0, 3.0), "pad", 112),  # 100 mm at 1 mm, rounded up to 16
        ((96, 96, 96), (1.0, 1.0, 1.0), "pad", 96),  # already a multiple of 16
        ((600, 600, 5), (0.7, 0.7, 2.5), "pad", 512),  # a thin slab: 600 voxels wide, capped
        ((64, 64, 300), (2.0, 2.0, 0.5), "pad", 304),  # finest along z: 150 mm at 0.5 mm is 300 voxels
        ((20, 20, 20), (3.0, 3.0, 3.0), "pad", 32),
        ((512, 512, 48), (0.5703, 0.5703, 5.0), "stretch", 512),  # stretch keeps the most samples on any axis
        ((40, 50, 10), (1.0, 1.0, 9.0), "stretch", 64),
    ],
)
def test_the_scan_size_keeps_the_finest_spacing_rounded_to_16_and_capped(shape, spacing, fit, expected):
    from cubecloud_cli.volume.cube_frame import size_for_scan

    assert size_for_scan(shape, spacing, fit) == expected


@given(
    shape=st.tuples(*[st.integers(2, 2000)] * 3),
    spacing=st.tuples(*[st.floats(0.05, 20.0)] * 3),
    fit=st.sampled_from(["pad", "stretch"]),
    cap=st.sampled_from([64, 512]),
)
@settings(max_examples=200, deadline=None)
def test_the_scan_size_is_a_capped_multiple_of_16_that_loses_no_detail_below_the_cap(shape, spacing, fit, cap):
    from cubecloud_cli.volume.cube_frame import size_for_scan

    size = size_for_scan(shape, spacing, fit, cap=cap)
    assert size % 16 == 0 and 16 <= size <= cap
    frame = plan_cube(shape, np.diag([*spacing, 1.0]), size, fit)
    if size < cap:  # below the cap the cube's voxels are at least as fine as the scan's finest
        if fit == "pad":
            assert frame.voxel_size_mm.max() <= min(spacing) * (1 + 1e-6)
        else:
            assert size >= max(shape)


@pytest.mark.parametrize("shape, spacing", [((32, 32, 1), (1, 1, 1)), ((32, 32), (1, 1)), ((8, 8, 8), (1, 0, 1))])
def test_the_scan_size_needs_a_3d_scan_with_positive_spacing(shape, spacing):
    from cubecloud_cli.volume.cube_frame import size_for_scan

    if len(shape) == 3 and min(spacing) > 0:
        assert size_for_scan(shape, spacing, "pad") == 32  # one slice is a 3D array; the reader refuses it
        return
    with pytest.raises(ValueError):
        size_for_scan(shape, spacing, "pad")


@settings(max_examples=80, deadline=None)
@given(
    st.tuples(*[st.integers(1, 700)] * 3),
    st.tuples(*[st.floats(0.05, 10.0)] * 3),
)
@example(shape=(1, 1, 232), spacing=(1.0, 0.05, 0.05))  # a ratio one rounding above 232 once asked for 480, not 464
def test_the_size_that_keeps_a_thin_scan_gives_every_axis_two_voxels_and_no_smaller_one_does(shape, spacing):
    keeping = size_keeping(shape, spacing)
    if keeping is None:  # no cube up to 512 holds it
        assert voxels_across(shape, spacing, 512, "pad").min() < 2.0
        return
    assert voxels_across(shape, spacing, keeping, "pad").min() >= 2.0 - 1e-9
    if keeping > 16:
        assert voxels_across(shape, spacing, keeping - 16, "pad").min() < 2.0
    assert np.allclose(voxels_across(shape, spacing, 32, "stretch"), 32)


def test_a_slab_spans_under_a_voxel_of_a_small_cube():
    across = voxels_across((600, 600, 5), (0.7, 0.7, 2.5), 32, "pad")
    assert across[2] == pytest.approx(32 * 12.5 / 420) and across[0] == pytest.approx(32)
    assert size_keeping((600, 600, 5), (0.7, 0.7, 2.5)) == 80


@pytest.mark.parametrize("degrees", [0.0, 3.0, 20.0])
def test_shear_is_the_largest_departure_from_right_angles_and_rotation_is_none(degrees):
    rotation = np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))[0]
    tilt = np.radians(degrees)  # the slice axis leans towards y, as a tilted gantry's does
    columns = np.array([[0.7, 0.0, 0.0], [0.0, 0.7, 2.5 * np.sin(tilt)], [0.0, 0.0, 2.5 * np.cos(tilt)]])
    affine = np.eye(4)
    affine[:3, :3] = rotation @ columns
    assert shear_degrees(affine) == pytest.approx(degrees, abs=1e-6)
