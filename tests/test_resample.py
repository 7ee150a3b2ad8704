import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.volume.resample import interpolation_matrix, resample_axes


@given(
    n_in=st.integers(1, 60),
    n_out=st.integers(1, 60),
    scale=st.floats(1e-3, 1e3),
    offset=st.floats(-100, 100),
    method=st.sampled_from(["linear", "nearest"]),
)
@settings(max_examples=300, deadline=None)
def test_rows_are_convex_or_empty(n_in, n_out, scale, offset, method):
    matrix = interpolation_matrix(n_in, n_out, scale, offset, method)
    assert matrix.shape == (n_out, n_in)
    assert np.all(np.isfinite(matrix)) and np.all(matrix >= 0)
    sums = matrix.sum(axis=1)
    assert np.all((np.abs(sums - 1) < 1e-5) | (sums == 0))


def test_identity_mapping_is_exact():
    assert np.array_equal(interpolation_matrix(7, 7, 1.0, 0.0), np.eye(7, dtype=np.float32))


def test_upsampling_reproduces_a_linear_ramp():
    ramp = np.arange(10, dtype=np.float32)
    matrix = interpolation_matrix(10, 40, 0.25, 0.0)
    centres = 0.25 * (np.arange(40) + 0.5) - 0.5
    inner = (centres >= 0) & (centres <= 9)
    assert np.allclose((matrix @ ramp)[inner], centres[inner], atol=1e-5)
    # Outside the first and last voxel centres the edge value is held, not extrapolated.
    assert np.allclose((matrix @ ramp)[~inner], np.clip(centres[~inner], 0, 9).round(), atol=1e-5)


def test_downsampling_antialiases_a_checkerboard():
    stripes = np.tile([0.0, 1.0], 32).astype(np.float32)
    averaged = interpolation_matrix(64, 16, 4.0, 0.0) @ stripes
    assert np.allclose(averaged[1:-1], 0.5, atol=1e-6)
    picked = interpolation_matrix(64, 16, 4.0, 0.0, "nearest") @ stripes
    assert set(np.unique(picked)) <= {0.0, 1.0}  # nearest aliases, as the paper's resize did


def test_centres_outside_the_input_are_empty():
    matrix = interpolation_matrix(4, 10, 1.0, -3.0)  # output 0..2 lie before the input
    assert np.all(matrix[:2].sum(axis=1) == 0)
    assert np.allclose(matrix[4:7].sum(axis=1), 1)


@given(
    shape=st.tuples(st.integers(2, 9), st.integers(2, 9), st.integers(2, 9)),
    size=st.integers(2, 12),
    seed=st.integers(0, 1000),
)
@settings(max_examples=60, deadline=None)
def test_resample_matches_einsum_and_stays_in_range(shape, size, seed):
    rng = np.random.default_rng(seed)
    volume = rng.uniform(0.2, 0.9, shape).astype(np.float32)
    matrices = [interpolation_matrix(n, size, n / size, 0.0) for n in shape]
    out = resample_axes(volume, matrices)
    expected = np.einsum("ai,bj,ck,ijk->abc", *matrices, volume)
    assert np.allclose(out, expected, atol=1e-5)
    assert out.min() >= 0.2 - 1e-6 and out.max() <= 0.9 + 1e-6


def test_float16_and_views_are_accepted():
    volume = np.linspace(0, 1, 5 * 6 * 7, dtype=np.float16).reshape(5, 6, 7)[::-1, :, ::-1]
    matrices = [interpolation_matrix(n, 3, n / 3, 0.0) for n in volume.shape]
    out = resample_axes(volume, matrices)
    assert out.dtype == np.float32 and np.all(np.isfinite(out))


@pytest.mark.parametrize("bad", [dict(scale=0.0), dict(scale=np.inf), dict(offset=np.nan), dict(n_in=0)])
def test_invalid_axis_mappings_raise(bad):
    args = dict(n_in=4, n_out=4, scale=1.0, offset=0.0) | bad
    with pytest.raises(ValueError):
        interpolation_matrix(**args)
