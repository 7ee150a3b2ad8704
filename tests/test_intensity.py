import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.volume.intensity import (
    CT_WINDOWS,
    IntensityMap,
    detect_modality,
    replace_nonfinite,
    resolve_intensity_map,
)


def test_abdomen_window_maps_its_ends_to_0_and_1():
    hu = np.array([-1000, -160, 40, 240, 3000], dtype=np.float32)
    mapped = resolve_intensity_map(hu, "ct", "abdomen").apply(hu)
    assert np.allclose(mapped, [0, 0, 0.5, 1, 1])


@pytest.mark.parametrize("name", sorted(CT_WINDOWS))
def test_every_window_is_centred_on_its_level(name):
    width, level = CT_WINDOWS[name]
    mapping = resolve_intensity_map(np.zeros(3), "ct", name)
    assert mapping.apply(np.array([level]))[0] == pytest.approx(0.5)
    assert mapping.high - mapping.low == pytest.approx(width)


def test_full_window_is_min_max_and_mr_uses_percentiles():
    data = np.linspace(-50, 950, 1001)
    full = resolve_intensity_map(data, "ct", "full")
    assert (full.low, full.high) == (-50, 950)
    mr = resolve_intensity_map(data, "mr", "abdomen", percentiles=(1, 99))
    assert mr.low == pytest.approx(-40) and mr.high == pytest.approx(940)


def test_constant_volume_gives_zeros_not_nan():
    data = np.full((4, 4, 4), 123.0, dtype=np.float32)
    for modality, window in [("ct", "full"), ("mr", "abdomen")]:
        mapped = resolve_intensity_map(data, modality, window).apply(data)
        assert np.all(mapped == 0)


@given(
    data=arrays(np.float32, st.integers(1, 50), elements=st.floats(width=32, allow_nan=False, allow_infinity=False)),
    modality=st.sampled_from(["ct", "mr"]),
    window=st.sampled_from(["full", "abdomen", "lung"]),
)
@settings(max_examples=200, deadline=None)
def test_any_finite_input_maps_into_unit_interval(data, modality, window):
    with np.errstate(over="ignore"):
        mapped = resolve_intensity_map(data, modality, window).apply(data)
    assert mapped.dtype == np.float32
    assert np.all(np.isfinite(mapped)) and mapped.min() >= 0 and mapped.max() <= 1


def test_tiny_ranges_still_map():
    data = np.array([0.0, 1e-20, 2e-20], dtype=np.float64)
    mapped = resolve_intensity_map(data, "ct", "full").apply(data)
    assert np.allclose(mapped, [0, 0.5, 1], atol=1e-6)


def test_float16_input_maps():
    data = np.array([-1000, 40, 240], dtype=np.float16)
    assert np.allclose(resolve_intensity_map(data, "ct", "abdomen").apply(data), [0, 0.5, 1], atol=1e-3)


def test_inplace_apply_overwrites_float32():
    data = np.array([-160.0, 240.0], dtype=np.float32)
    out = IntensityMap(-160, 240, "ct", "t").apply(data, inplace=True)
    assert out is data and np.allclose(data, [0, 1])
    kept = np.array([-160.0, 240.0], dtype=np.float32)
    IntensityMap(-160, 240, "ct", "t").apply(kept)
    assert kept[0] == -160.0


def test_nonfinite_voxels_are_replaced_and_counted():
    data = np.array([np.nan, -10.0, np.inf, 5.0, -np.inf], dtype=np.float32)
    assert replace_nonfinite(data) == 3
    assert np.array_equal(data, [-10, -10, 5, 5, -10])
    with pytest.raises(CubecloudError, match="every voxel"):
        replace_nonfinite(np.full(3, np.nan))


def test_modality_detection():
    assert detect_modality(np.array([-1024.0, 50.0]), None)[0] == "ct"
    assert detect_modality(np.array([-47.0, 833.0]), None)[0] == "mr"
    assert detect_modality(np.array([-1024.0]), "mr")[0] == "mr"  # the header wins


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(hu_min=100.0, hu_max=-100.0), "below"),
        (dict(hu_min=100.0), "both"),
        (dict(window="kidney"), "unknown --window"),
    ],
)
def test_bad_window_requests(kwargs, message):
    args = dict(data=np.zeros(3), modality="ct", window="abdomen") | kwargs
    with pytest.raises(CubecloudError, match=message):
        resolve_intensity_map(**args)


def test_hu_range_is_refused_for_mr():
    with pytest.raises(CubecloudError, match="Hounsfield"):
        resolve_intensity_map(np.zeros(3), "mr", "abdomen", -100.0, 100.0)
