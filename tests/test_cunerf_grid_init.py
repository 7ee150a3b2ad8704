import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.cunerf import banded, grid_init
from cubecloud_cli.cunerf.banded import (
    interpolation_taps,
    preconditioner,
    read_along,
    render,
    render_plan,
    solve_along,
    tap_runs,
)
from cubecloud_cli.cunerf.grid_init import (
    FIT_STEPS,
    FIT_TOLERANCE,
    INVERSE_DAMPING,
    LOGIT_EPSILON,
    LOGIT_LIMIT,
    damped_inverse,
    fit_vertex_logits,
    initialise_from_volume,
    linear_interpolation_matrix,
    logit,
    sample_weights,
    shifted_interpolation,
    training_volume_at,
)
from cubecloud_cli.cunerf.model import CubeModel
from cubecloud_cli.cunerf.settings import CunerfSettings
from cubecloud_cli.cunerf.supervision import TrainingVoxels, voxel_centres
from cubecloud_cli.volume.resample import resample_axes

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


# The dense path the banded one replaced (O(r⁴): one r×r matrix product per axis), kept here as
# the reference the banded reads, solve and fit must equal to float32 rounding.


def _dense_logit(values):
    p = np.clip(np.nan_to_num(values, nan=LOGIT_EPSILON), LOGIT_EPSILON, 1.0 - LOGIT_EPSILON)
    return np.log(p) - np.log1p(-p)


def _dense_inverses(size, shifts, weights):
    total = max(float(weights.sum()), 1e-12)
    inverses = []
    for axis in range(3):
        values = np.unique(shifts[:, axis])
        mean = sum(weights[shifts[:, axis] == s].sum() / total * shifted_interpolation(size, s) for s in values)
        inverses.append(damped_inverse(mean.astype(np.float64)).astype(np.float32))
    return inverses


def _dense_render(logits, shifts, weights):
    out = np.zeros_like(logits)
    for (sx, sy, sz), w in zip(shifts, weights):
        matrices = [shifted_interpolation(logits.shape[0], s) for s in (sx, sy, sz)]
        out += np.float32(w) / (1.0 + np.exp(-resample_axes(logits, matrices)))
    return out


def _dense_fit(target, shifts, weights):
    goal = _dense_logit(target)
    inverses = _dense_inverses(target.shape[0], shifts, weights)
    logits = goal.copy()
    rendered = _dense_render(logits, shifts, weights)
    cost = float(np.sqrt(np.mean((target - rendered) ** 2)))
    for _ in range(FIT_STEPS):
        error = goal - _dense_logit(rendered)
        if float(np.abs(error).max()) < FIT_TOLERANCE:
            break
        direction = resample_axes(error, inverses)
        for scale in (1.0, 0.5, 0.25, 0.125):
            trial = np.clip(logits + np.float32(scale) * direction, -LOGIT_LIMIT, LOGIT_LIMIT)
            trial_rendered = _dense_render(trial, shifts, weights)
            trial_cost = float(np.sqrt(np.mean((target - trial_rendered) ** 2)))
            if trial_cost < cost:
                logits, rendered, cost = trial, trial_rendered, trial_cost
                break
        else:
            break
    return logits, cost


def _along(matrix, values, axis):
    return np.moveaxis(np.tensordot(matrix, np.moveaxis(values, axis, 0), axes=1), 0, axis)


def _shifts_and_weights(size, radius, per_axis=2):
    offsets, weights = sample_weights(CunerfSettings(cube_radius=radius, samples_per_axis=per_axis).render_config(size))
    return offsets * size / 2.0, weights


SHIFTS = [0.0, 0.25, -0.25, 0.5, -0.5, 1.0, -1.0, 1.75, -2.3, 7.0, -40.0, 40.0]


@pytest.mark.parametrize("size", [1, 2, 3, 16, 29])
def test_a_shifted_read_by_slicing_equals_the_dense_matrix_up_to_the_borders(size):
    rng = np.random.default_rng(size)
    values = rng.normal(size=(size, size + 1, size + 2)).astype(np.float32) * 10
    for shift in SHIFTS:
        for axis in range(3):
            count = values.shape[axis]
            runs = tap_runs(interpolation_taps(np.arange(count), np.arange(count) + shift))
            assert len(runs) <= 3  # the held border rows on each side, one sliding run between
            expected = _along(shifted_interpolation(count, shift), values, axis)
            out = torch.full(values.shape, np.nan)
            read_along(torch.from_numpy(values), runs, axis, out)
            np.testing.assert_allclose(out.numpy(), expected, rtol=1e-6, atol=1e-5)
            if axis == 0 and size > 2:  # a window of output rows, as a render block reads it
                window = torch.full(values[1:-1].shape, np.nan)
                read_along(torch.from_numpy(values), runs, 0, window, 1)
                np.testing.assert_allclose(window.numpy(), expected[1:-1], rtol=1e-6, atol=1e-5)


@pytest.mark.parametrize(
    "size, radius, per_axis", [(1, 0.5, 2), (2, 1.0, 3), (17, 0.25, 2), (24, 0.5, 3), (40, 1.0, 2)]
)
def test_the_banded_solve_equals_the_dense_damped_inverse(size, radius, per_axis):
    shifts, weights = _shifts_and_weights(size, radius, per_axis)
    values = np.random.default_rng(size).normal(size=(size,) * 3).astype(np.float32)
    expected = values.astype(np.float64)
    for axis, inverse in enumerate(_dense_inverses(size, shifts, weights)):
        expected = _along(inverse.astype(np.float64), expected, axis)
    out = values.copy()
    for axis, inverse in enumerate(preconditioner(size, shifts, weights, INVERSE_DAMPING)):
        solve_along(out, inverse, axis)
    np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-5 * np.abs(expected).max())


@pytest.mark.parametrize("size, radius", [(16, 0.25), (20, 0.5), (33, 0.5), (24, 1.0)])
def test_the_banded_render_and_fit_equal_the_dense_ones(size, radius):
    shifts, weights = _shifts_and_weights(size, radius)
    rng = np.random.default_rng(size)
    grid = np.indices((size,) * 3).sum(axis=0) / size
    target = (0.5 + 0.3 * np.sin(6 * grid) + 0.1 * rng.uniform(-1, 1, (size,) * 3)).astype(np.float32)
    logits = rng.normal(size=target.shape).astype(np.float32) * 4
    rendered = torch.full(logits.shape, np.nan)
    cost = render(torch.from_numpy(logits), render_plan(size, shifts, weights), torch.from_numpy(target), rendered)
    expected = _dense_render(logits, shifts, weights)
    np.testing.assert_allclose(rendered.numpy(), expected, atol=1e-6)
    assert cost == pytest.approx(np.sqrt(np.mean((target - expected) ** 2)), rel=1e-5)

    kept = target.copy()
    fitted, cost = fit_vertex_logits(target, shifts, weights)
    dense, dense_cost = _dense_fit(target, shifts, weights)
    assert (target == kept).all()  # the target is read, never written
    np.testing.assert_allclose(fitted, dense, rtol=1e-5, atol=1e-5)
    assert cost == pytest.approx(dense_cost, rel=1e-3, abs=1e-7)


def test_blocks_that_do_not_divide_the_grid_change_nothing(monkeypatch):
    """Renders and solves run a block of rows at a time; a grid of 13 in blocks of 5 (render) and
    4 (solve) rows has a short last block, which must read and write only its own rows."""
    size = 13
    shifts, weights = _shifts_and_weights(size, 0.5)
    grid = np.indices((size,) * 3).sum(axis=0) / size
    target = (0.5 + 0.4 * np.sin(5 * grid)).astype(np.float32)
    dense, dense_cost = _dense_fit(target, shifts, weights)
    for module in (banded, grid_init):
        monkeypatch.setattr(module, "BLOCK_ELEMENTS", 5 * size * size)
    monkeypatch.setattr(banded, "SOLVE_ELEMENTS", 4 * size * size)
    fitted, cost = fit_vertex_logits(target, shifts, weights)
    np.testing.assert_allclose(fitted, dense, rtol=1e-5, atol=1e-5)
    assert cost == pytest.approx(dense_cost, rel=1e-3, abs=1e-7)


extreme_volumes = st.sampled_from(["zeros", "ones", "constant", "edge", "checkerboard"])


@settings(max_examples=30, deadline=None)
@given(extreme_volumes, st.integers(1, 4), st.sampled_from([0.25, 0.5, 1.0]), st.sampled_from([2, 3]))
def test_at_the_extremes_the_banded_fit_equals_the_dense_one(kind, size, radius, per_axis):
    """Targets at exactly 0 and 1, constant volumes, and grids of one to four vertices a side."""
    grid = np.indices((size,) * 3).sum(axis=0)
    target = {
        "zeros": np.zeros((size,) * 3),
        "ones": np.ones((size,) * 3),
        "constant": np.full((size,) * 3, 0.3),
        "edge": (np.indices((size,) * 3)[0] >= size / 2).astype(float),  # a 0/1 step
        "checkerboard": (grid % 2).astype(float),
    }[kind].astype(np.float32)
    shifts, weights = _shifts_and_weights(size, radius, per_axis)
    fitted, cost = fit_vertex_logits(target, shifts, weights)
    dense, dense_cost = _dense_fit(target, shifts, weights)
    assert np.isfinite(fitted).all() and np.abs(fitted).max() <= LOGIT_LIMIT
    # A 0/1 target drives the logits into sigmoid's flat tails, where the step taken turns on the
    # last bit of a cost (±18 and ±24 render alike): the intensities are what must agree.
    np.testing.assert_allclose(_sigmoid(fitted), _sigmoid(dense), atol=1e-5)
    assert cost == pytest.approx(dense_cost, abs=1e-6)


@pytest.mark.parametrize(
    "train_scale, held_out, resolution", [(1, [], 12), (1, [0, 5, 13], 20), (2, [4], 9), (3, [], 16)]
)
def test_the_training_volume_by_taps_equals_the_dense_resample(train_scale, held_out, resolution):
    size = 14
    volume = np.random.default_rng(train_scale).uniform(size=(size,) * 3).astype(np.float32)
    voxels = TrainingVoxels(torch.from_numpy(volume), train_scale, held_out, 0.8)
    lattice, slices = voxels.lattice.numpy(), voxels.slices.numpy()
    vertices = (np.arange(resolution) + 0.5) * (size / resolution) - 0.5
    matrices = [linear_interpolation_matrix(axis, vertices) for axis in (lattice, lattice, slices)]
    expected = resample_axes(volume[np.ix_(lattice, lattice, slices)], matrices)
    np.testing.assert_allclose(training_volume_at(voxels, resolution), expected, atol=1e-6)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_logit_in_one_log_equals_the_difference_of_logs(dtype):
    values = np.concatenate([np.linspace(-0.5, 1.5, 2001), [np.nan, np.inf, -np.inf, 1e-300]]).astype(dtype)
    out = logit(values)
    assert out.dtype == dtype and np.isfinite(out).all()
    np.testing.assert_allclose(out, _dense_logit(values), atol=1e-6 if dtype == np.float32 else 1e-12)
    assert logit(np.array([0, 1])).dtype == np.float64  # integers get a float result
