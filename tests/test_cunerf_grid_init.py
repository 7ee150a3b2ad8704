import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.cunerf.data import TrainingVoxels, voxel_centres
from cubecloud_cli.cunerf.grid_init import initialise_from_volume, linear_interpolation_matrix, logit
from cubecloud_cli.cunerf.model import CubeModel
from cubecloud_cli.cunerf.settings import CunerfSettings

coordinates = st.lists(st.floats(-50, 50, allow_nan=False), min_size=2, max_size=6, unique=True).map(sorted)


@settings(max_examples=60, deadline=None)
@given(coordinates, st.floats(-3, 3), st.floats(-3, 3))
def test_interpolation_reproduces_a_linear_function_inside_and_holds_the_border_outside(xs, slope, offset):
    known = np.array(xs)
    values = slope * known + offset
    inside = np.linspace(known[0], known[-1], 7)
    with np.errstate(
        over="raise", divide="raise", invalid="raise"
    ):  # subnormal spans must not overflow (an underflow to 0 is right)
        matrix = linear_interpolation_matrix(known, inside)
        outside = linear_interpolation_matrix(known, np.array([known[0] - 100.0, known[-1] + 100.0]))
    assert (matrix >= 0).all() and np.allclose(matrix.sum(axis=1), 1.0)
    np.testing.assert_allclose(matrix @ values, slope * inside + offset, atol=1e-4 * (1 + abs(slope) * 50))
    np.testing.assert_allclose(outside @ values, values[[0, -1]], atol=1e-5)


def test_one_known_coordinate_is_held_everywhere():
    assert linear_interpolation_matrix(np.array([3.0]), np.arange(3.0)).tolist() == [[1.0], [1.0], [1.0]]


def test_logit_is_finite_at_the_extremes_and_inverts_the_sigmoid_inside():
    values = logit(np.array([0.0, 1.0, np.nan, -np.inf, np.inf, 1e-300, 0.25]))
    assert np.isfinite(values).all()
    assert values[0] == values[2] == values[3] == values[5] < -6.8 and values[1] == values[4] > 6.8
    assert 1 / (1 + np.exp(-values[6])) == pytest.approx(0.25)


def _field_at_voxels(model: CubeModel, size: int) -> np.ndarray:
    grid = torch.stack(torch.meshgrid(*[torch.arange(size)] * 3, indexing="ij"), -1).reshape(-1, 3)
    with torch.no_grad():
        values = model.render(voxel_centres(grid, size), train=False).value
    return values.reshape(size, size, size).numpy()


def test_a_volume_start_renders_the_training_voxels_and_never_reads_a_held_out_slice():
    size = 16
    x = np.linspace(0, 1, size)
    volume = (0.2 + 0.6 * x[:, None, None] * x[None, :, None] * np.ones((1, 1, size))).astype(np.float32)
    held_out = [5, 10]
    volume[:, :, held_out] = 1.0  # a value no training voxel has
    settings = CunerfSettings(grid_init="volume", grid_levels=2, grid_base=4)
    model = CubeModel(settings.field_config(size), settings.render_config(size))
    random_start = _field_at_voxels(model, size)
    voxels = TrainingVoxels(torch.from_numpy(volume), 1, held_out, 0.8)
    initialise_from_volume(model.coarse, voxels)
    start = _field_at_voxels(model, size)

    training = [k for k in range(size) if k not in held_out]
    error = np.abs(start[:, :, training] - volume[:, :, training])
    # The cube's samples sit a quarter voxel off the centre: within a small fraction of the range.
    assert error.mean() < 0.01 and error.max() < 0.05
    assert np.abs(random_start[:, :, training] - volume[:, :, training]).mean() > 0.1
    # Held-out slices come from their neighbours, not from the 1.0 they hold.
    np.testing.assert_allclose(start[:, :, held_out], volume[:, :, [4, 9]], atol=0.05)


def test_grid_init_volume_needs_the_grid_model():
    from cubecloud_cli.errors import CubecloudError

    with pytest.raises(CubecloudError, match="--model fast"):
        CunerfSettings(model="cunerf", grid_init="volume").validate()
    with pytest.raises(CubecloudError, match="random or volume"):
        CunerfSettings(grid_init="zeros").validate()  # type: ignore[arg-type]
