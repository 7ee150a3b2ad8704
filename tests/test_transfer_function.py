"""Transfer functions and their presets (transfer/): bands, what a window clips away, and the
form files keep them in."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.transfer.function import MIN_RAMP_WIDTH, TransferFunction
from cubecloud_cli.transfer.tissue_presets import TRANSFER_PRESETS, clipped_away, resolve_transfer

ABDOMEN = {"modality": "ct", "low": -160.0, "high": 240.0}
LUNG = {"modality": "ct", "low": -1350.0, "high": 150.0}
MR = {"modality": "mr", "low": 3.0, "high": 900.0}


def test_presets_are_resolved_through_the_window_in_hu():
    lung = resolve_transfer("lung", LUNG)
    expected = [(h + 1350.0) / 1500.0 for h in (-950.0, -800.0, -500.0, -300.0)]
    assert [lung.low, lung.high, lung.fall_low, lung.fall_high] == pytest.approx(expected)
    assert lung.is_band and not resolve_transfer("bone", LUNG).is_band
    # The vessels' fall lies above the abdomen window's top: what is left is a ramp to 1 that stays.
    vessels = resolve_transfer("vessels", ABDOMEN)
    assert (vessels.fall_low, vessels.fall_high) == (1.0, 1.0)
    assert vessels.ramp(np.array([1.0]))[0] == 1.0
    # MR has no HU: the fractions.
    assert resolve_transfer("lung", MR) == TransferFunction(*TRANSFER_PRESETS["lung"].fraction[:2], 2.0,
                                                             *TRANSFER_PRESETS["lung"].fraction[2:])  # fmt: skip


def test_a_preset_outside_the_window_is_named_with_the_fix():
    why = clipped_away("lung", ABDOMEN)
    assert why.startswith("lung shows -950..-300 HU, which the window -160..240 HU clips away") and "--window" in why
    assert clipped_away("bone", LUNG) is not None  # 150..inf HU against a window ending at 150 HU
    assert clipped_away("lung", LUNG) is None and clipped_away("bone", ABDOMEN) is None
    assert clipped_away("lung", MR) is None and clipped_away("lung", None) is None  # no HU: the fractions
    assert all(
        clipped_away(name, {"modality": "ct", "low": -1024.0, "high": 3071.0}) is None for name in TRANSFER_PRESETS
    )


@given(
    values=st.lists(st.floats(-10.0, 10.0), min_size=1, max_size=16),
    ends=st.lists(st.floats(0.0, 1.0), min_size=4, max_size=4),
    density=st.sampled_from([0.0, 1e-30, 2.0, 999_999.0]),
)
def test_a_band_stays_within_its_density_for_any_values_and_any_widths(values, ends, density):
    low, high, fall_low, fall_high = sorted(ends)
    band = TransferFunction(low, high, density, fall_low, fall_high)
    band.validate()
    ramp = band.ramp(np.asarray(values))
    assert np.all((ramp >= 0.0) & (ramp <= 1.0))
    below_or_above = (np.asarray(values) <= low) | (np.asarray(values) >= fall_high + MIN_RAMP_WIDTH)
    assert np.all(ramp[below_or_above] == 0.0)
    assert np.all(np.isfinite(band.extinction(np.asarray(values))))
    parameters = band.march_parameters()
    assert all(math.isfinite(p) for p in parameters) and min(parameters[1], parameters[3]) >= MIN_RAMP_WIDTH


@pytest.mark.parametrize(
    "function, pattern",
    [
        (TransferFunction(0.2, 0.4, 1.0, 0.3, 0.6), "high <= fall_low"),
        (TransferFunction(0.2, 0.4, 1.0, 0.6, 0.5), "fall_low <= fall_high"),
        (TransferFunction(0.2, 0.4, 1.0, 0.6, None), "both fall_low and fall_high"),
        (TransferFunction(0.2, 0.4, 1.0, 0.6, 1.5), "<= 1"),
    ],
)
def test_bands_that_fall_before_they_rise_are_refused(function, pattern):
    with pytest.raises(ValueError, match=pattern):
        function.validate()


def test_a_band_raised_past_its_top_lifts_its_fall_and_bad_overrides_are_one_line_errors():
    lifted = resolve_transfer("lung", LUNG, high=0.65)
    assert lifted.fall_low == pytest.approx(0.65) and lifted.fall_high == pytest.approx(1050.0 / 1500.0)
    with pytest.raises(CubecloudError, match="--tf-low/--tf-high"):
        resolve_transfer("lung", LUNG, low=0.9, high=0.5)


def test_files_keep_the_fall_and_files_written_before_bands_still_read():
    band = TransferFunction(0.1, 0.2, 3.0, 0.5, 0.6)
    assert TransferFunction.from_dict(band.as_dict()) == band
    assert TransferFunction.from_dict({"low": 0.3, "high": 0.9, "density": 4.0}) == TransferFunction()
