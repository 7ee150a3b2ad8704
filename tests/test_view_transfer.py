"""A scalar scene in the viewer, without a server: colour maps and the transfer-function choice
(the server and the browser: tests/test_view.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.splat.scalar_gaussians import scalar_gaussians_from_points, transfer_opacities
from cubecloud_cli.transfer.function import TransferFunction
from cubecloud_cli.view.transfer_view import COLOUR_MAPS, CUSTOM, TRAINED_PRESET, DrawnValues, ScalarScene, colour_map

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


def test_the_page_offers_only_presets_the_window_keeps_and_a_band_s_top_moves_up_with_its_rise():
    scene = scalar_scene()  # the abdomen window: no lung
    assert "lung" not in scene.presets and {"bone", "vessels"} <= set(scene.presets)
    wide = ScalarScene(scene.scalar, {"modality": "ct", "low": -1350.0, "high": 150.0})
    assert "lung" in wide.presets and "bone" not in wide.presets
    wide.choose(preset="lung")
    band = wide.chosen.function
    assert wide.choose(high=0.95)
    lifted = wide.chosen.function
    assert (lifted.high, lifted.fall_low) == (0.95, 0.95) and lifted.fall_high == max(band.fall_high, 0.95)
    lifted.validate()


@settings(max_examples=30, deadline=None)
@given(
    ends=st.lists(st.floats(0.0, 1.0), min_size=4, max_size=4),
    density=st.sampled_from([0.0, 1e-30, 4.0, 999_999.0]),
    band=st.booleans(),
)
def test_the_viewer_s_float32_recolour_gives_the_model_s_opacities(ends, density, band):
    """With a 3D filter and a PLY's opacity scale, any window (bands and steps included): the
    numpy recolour the viewer uses against ScalarGaussians.opacities."""
    import torch

    scalar = scalar_scene().scalar
    generator = torch.Generator().manual_seed(2)
    scalar.log_lengths = torch.rand(len(scalar), generator=generator) * 30 - 15  # clear to opaque
    scalar.smoothing = torch.rand(len(scalar), generator=generator) * 1e-3
    scalar.opacity_scale = 0.5 + 0.5 * torch.rand(len(scalar), generator=generator)
    low, high, fall_low, fall_high = sorted(ends)
    transfer = TransferFunction(low, high, density, *((fall_low, fall_high) if band else (None, None)))
    with torch.no_grad():
        expected = scalar.drawn_as(transfer).opacities().numpy()
    got = DrawnValues.of(scalar).opacities(transfer)
    assert got.dtype == np.float32 and np.isfinite(got).all()
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6)
