import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.cunerf.grid_init import (
    damped_inverse,
    fit_vertex_logits,
    initialise_from_volume,
    linear_interpolation_matrix,
    logit,
    sample_weights,
)
from cubecloud_cli.cunerf.model import CubeModel
from cubecloud_cli.cunerf.settings import CunerfSettings
from cubecloud_cli.cunerf.supervision import TrainingVoxels, voxel_centres

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
    initialise_from_volume(model, voxels)
    start = _field_at_voxels(model, size)

    training = [k for k in range(size) if k not in held_out]
    error = np.abs(start[:, :, training] - volume[:, :, training])
    # The solve undoes the quarter-voxel offsets of the cube's samples: exact to float32 rounding.
    assert error.max() < 2e-3
    assert np.abs(random_start[:, :, training] - volume[:, :, training]).mean() > 0.1
    # Held-out slices come from their neighbours, not from the 1.0 they hold.
    np.testing.assert_allclose(start[:, :, held_out], volume[:, :, [4, 9]], atol=0.05)


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


@pytest.mark.parametrize("radius, per_axis", [(0.5, 2), (0.5, 3), (0.25, 2)])
def test_sample_weights_make_the_start_render_a_mean_of_its_samples(radius, per_axis):
    settings = CunerfSettings(cube_radius=radius, samples_per_axis=per_axis)
    offsets, weights = sample_weights(settings.render_config(16))
    assert offsets.shape == (per_axis**3, 3) and (weights >= 0).all()  # the centre has no shell area
    assert weights.sum() == pytest.approx(1.0)  # the start's density sums the weights past 1
    if per_axis == 2:  # one shell: every sample counts alike
        np.testing.assert_allclose(weights, weights[0])


def test_the_damped_inverse_inverts_a_sound_matrix_and_stays_bounded_on_a_singular_one():
    sound = 0.75 * np.eye(6) + 0.125 * (np.eye(6, k=1) + np.eye(6, k=-1))
    np.testing.assert_allclose(damped_inverse(sound, 1e-12) @ sound, np.eye(6), atol=1e-8)
    singular = np.ones((6, 6)) / 6  # every row the same average: nothing to tell apart
    inverse = damped_inverse(singular)
    assert np.isfinite(inverse).all() and np.abs(inverse).max() < 1 / (2 * np.sqrt(1e-3))


def _plain_cost(target, shifts, weights):
    goal = logit(target)
    rendered = sum(w * _sigmoid(_shift_read(goal, s)) for s, w in zip(shifts, weights))
    return np.sqrt(np.mean((target - rendered) ** 2))


def _shift_read(values, shift):
    for axis in range(3):
        values = np.moveaxis(
            np.tensordot(_interp(values.shape[axis], shift[axis]), np.moveaxis(values, axis, 0), axes=1), 0, axis
        )
    return values


def _interp(n, shift):
    return linear_interpolation_matrix(np.arange(n, dtype=float), np.arange(n) + shift)


volumes = st.sampled_from(["zeros", "ones", "constant", "checkerboard", "noise", "sphere"])


@settings(max_examples=24, deadline=None)
@given(volumes, st.sampled_from([0.5, 1.0, 2.0]), st.integers(0, 3))
def test_the_solve_is_finite_never_worse_than_no_solve_and_exact_where_the_render_allows(kind, radius, seed):
    """Extremes: all air, all bone, a checkerboard (which a one-voxel cube cannot render), noise."""
    size = 8
    rng = np.random.default_rng(seed)
    grid = np.indices((size,) * 3)
    target = {
        "zeros": np.zeros((size,) * 3),
        "ones": np.ones((size,) * 3),
        "constant": np.full((size,) * 3, rng.uniform()),
        "checkerboard": (grid.sum(axis=0) % 2).astype(float),
        "noise": rng.uniform(size=(size,) * 3),
        "sphere": (((grid - 3.5) ** 2).sum(axis=0) < 9).astype(float),
    }[kind].astype(np.float32)
    settings = CunerfSettings(cube_radius=radius * 0.5)  # 0.25, 0.5 or 1 voxel
    offsets, weights = sample_weights(settings.render_config(size))
    shifts = offsets * size / 2.0
    logits, cost = fit_vertex_logits(target, shifts, weights)
    assert np.isfinite(logits).all() and np.abs(logits).max() <= 30.0
    rendered = sum(w * _sigmoid(_shift_read(logits.astype(float), s)) for s, w in zip(shifts, weights))
    assert cost == pytest.approx(np.sqrt(np.mean((target - rendered) ** 2)), abs=1e-5)
    assert cost <= _plain_cost(target, shifts, weights) + 1e-7
    if (radius < 2.0 and kind == "noise") or kind in ("zeros", "ones", "constant"):
        # Samples a half or a quarter voxel off: the render's average can be undone. (A 0/1
        # sphere or checkerboard asks for logits far out in sigmoid's flat tails; the solve
        # only gains there.)
        assert cost < 2e-3


def test_grid_init_volume_needs_the_grid_model():
    from cubecloud_cli.core.errors import CubecloudError

    with pytest.raises(CubecloudError, match="--model fast"):
        CunerfSettings(model="cunerf", grid_init="volume").validate()
    with pytest.raises(CubecloudError, match="random or volume"):
        CunerfSettings(grid_init="zeros").validate()  # type: ignore[arg-type]
