"""Slices placed where they were acquired: every output voxel holds the value at its own scanner position.

A linear function of the scanner position is reproduced exactly by linear interpolation, so a
stack whose pixels hold f(position) must come out holding f at each output voxel's position,
whatever the steps, gaps, shared positions or gantry tilt.
"""

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from cubecloud_cli.volume.slice_stack import SAME_POSITION_MM, PlacedSlice, plan_stack, resample_stack

GRADIENT = np.array([0.7, -1.3, 2.1])


def field(points: np.ndarray) -> np.ndarray:
    return points @ GRADIENT + 5.0


def tilted_stack(depths, tilt_deg=0.0, rows=12, columns=10, spacing=(0.8, 0.6), shift=(0.0, 0.0)):
    """Axial-like slices at ``depths`` (mm along z, the table); the gantry tilted by ``tilt_deg``
    about the x axis, so the slice normal leans while the origins move straight along z."""
    angle = math.radians(tilt_deg)
    row_direction = np.array([1.0, 0.0, 0.0])
    column_direction = np.array([0.0, math.cos(angle), math.sin(angle)])
    return [
        PlacedSlice(np.array([-4.0 + shift[0], -5.0 + shift[1], float(z)]), row_direction, column_direction,
                    spacing[0], spacing[1], rows, columns)
        for z in depths
    ]  # fmt: skip


def pixel_values(s: PlacedSlice) -> np.ndarray:
    """The slice as (columns, rows) samples of ``field`` at each pixel's scanner position."""
    column, row = np.meshgrid(np.arange(s.columns), np.arange(s.rows), indexing="ij")
    points = (s.position + column[..., None] * s.column_spacing * s.row_direction
              + row[..., None] * s.row_spacing * s.column_direction)  # fmt: skip
    return field(points)


def voxel_positions(plan) -> np.ndarray:
    index = np.stack(np.meshgrid(*[np.arange(n) for n in plan.shape], indexing="ij"), -1).reshape(-1, 3)
    return (plan.affine() @ np.c_[index, np.ones(len(index))].T).T[:, :3], index


def resampled(slices):
    plan = plan_stack(slices)
    volume = resample_stack(lambda i: pixel_values(slices[i]), slices, plan, fill=np.nan)
    return plan, volume


def assert_holds_the_field(plan, volume):
    points, index = voxel_positions(plan)
    values = volume[index[:, 0], index[:, 1], index[:, 2]]
    inside = np.isfinite(values)  # outside a slice's footprint the fill (NaN) shows
    assert inside.sum() >= 60  # at least a slice's worth of voxels lies inside the footprints
    # An output plane within SAME_POSITION_MM of a slice is that slice, by design: the field moves
    # by up to |gradient| · SAME_POSITION_MM there.
    snap = SAME_POSITION_MM * float(np.linalg.norm(GRADIENT))
    assert np.allclose(values[inside], field(points[inside]), atol=1e-3 + snap)


def test_an_even_series_is_its_own_grid_copied_exactly():
    slices = tilted_stack([10.0, 12.5, 15.0, 17.5])[::-1]  # file order does not matter
    plan, volume = resampled(slices)
    assert plan.regular and plan.shape == (10, 12, 4) and plan.tilt_deg == 0.0 and plan.gaps == []
    for k, s in enumerate(sorted(slices, key=lambda s: s.position[2])):
        assert np.array_equal(volume[:, :, k], pixel_values(s).astype(np.float32))
    assert np.allclose(plan.affine()[:3, 3], [-4.0, -5.0, 10.0])


def test_a_missing_slice_is_a_gap_that_is_interpolated_not_a_longer_step():
    plan, volume = resampled(tilted_stack([0.0, 2.0, 4.0, 8.0, 10.0]))  # 6.0 missing
    assert plan.spacing[2] == pytest.approx(2.0) and plan.shape[2] == 6
    assert plan.gaps == [(4.0, 8.0)] and not plan.regular
    assert_holds_the_field(plan, volume)


def test_a_thin_and_a_thick_slab_keep_each_slice_where_it_was():
    depths = [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 12.0, 19.0]
    plan, volume = resampled(tilted_stack(depths))
    assert plan.spacing[2] == pytest.approx(1.0) and plan.shape[2] == 20
    assert plan.describe()["step_mm"] == {"min": 1.0, "max": 7.0, "output": 1.0}
    assert_holds_the_field(plan, volume)


def test_overlapping_slabs_average_shared_positions():
    depths = [0.0, 2.0, 4.0, 6.0, 4.0, 5.0, 6.0, 7.0]  # the second slab starts inside the first
    plan, volume = resampled(tilted_stack(depths))
    assert plan.describe()["shared_positions"] == 2
    assert_holds_the_field(plan, volume)


@pytest.mark.parametrize("tilt", [-20.0, 20.0, 7.5])
def test_gantry_tilt_is_measured_and_unsheared(tilt):
    plan, volume = resampled(tilted_stack(np.arange(8) * 2.5, tilt_deg=tilt))
    assert plan.tilt_deg == pytest.approx(abs(tilt), abs=1e-6)
    assert not plan.regular
    assert_holds_the_field(plan, volume)
    # Stacking the slices along the normal (what tilt-unaware readers do) would misplace them.
    sheared = plan_stack(tilted_stack(np.arange(8) * 2.5 * math.cos(math.radians(tilt))))
    assert sheared.shape[1] < plan.shape[1]


@settings(max_examples=40, deadline=None)
@given(
    steps=st.lists(st.floats(0.3, 6.0), min_size=1, max_size=8),
    tilt=st.floats(-30.0, 30.0),
    shared=st.integers(0, 2),
)
# A last plane 0.6 µm short of its slice, which the resampler rightly takes as the slice.
@example(steps=[3.0, 1.0205598043276058, 1.5524902285251787, 2.1900196272534247, 1.0], tilt=0.0, shared=0)
def test_any_acquisition_holds_the_value_of_each_voxels_position(steps, tilt, shared):
    depths = list(np.concatenate([[0.0], np.cumsum(steps)]))
    depths += depths[1 : 1 + shared]  # repeated positions, as from overlapping slabs
    plan, volume = resampled(tilted_stack(depths, tilt_deg=tilt))
    assert plan.tilt_deg == pytest.approx(abs(tilt), abs=1e-6)
    assert_holds_the_field(plan, volume)


def test_fewer_than_two_positions_is_refused():
    with pytest.raises(ValueError, match="fewer than two distinct positions"):
        plan_stack(tilted_stack([3.0, 3.0]))


def test_slabs_of_different_pixel_spacing_and_size_share_one_grid():
    fine = tilted_stack([0.0, 1.5, 3.0], rows=16, columns=14, spacing=(0.6, 0.5))
    coarse = tilted_stack([6.0, 9.0], rows=10, columns=9, spacing=(0.9, 0.8), shift=(0.3, -0.2))
    plan, volume = resampled(fine + coarse)
    assert np.allclose(plan.spacing[:2], [0.5, 0.6])  # the median column and row spacing
    assert_holds_the_field(plan, volume)
