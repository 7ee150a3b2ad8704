"""The numbers and pictures of `cubecloud eval`, against scikit-image and known answers."""

import math
import xml.etree.ElementTree as ElementTree

import imageio.v3 as iio
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from skimage.metrics import mean_squared_error, peak_signal_noise_ratio, structural_similarity

from cubecloud_cli.eval.figures import colour_map, error_grid, line_plot_svg, place_labels, write_turntable
from cubecloud_cli.eval.scoring import score_view, score_views, summarize


def fixed_images():
    rng = np.random.default_rng(7)
    y, x = np.mgrid[0:40, 0:48] / 40.0
    reference = np.clip(0.5 + 0.4 * np.sin(6 * x) * np.cos(4 * y), 0, 1)
    reference[:6] = 0.0  # some background
    estimate = np.clip(reference + rng.normal(0, 0.05, reference.shape), 0, 1)
    return reference, estimate


def test_scores_agree_with_scikit_image():
    reference, estimate = fixed_images()
    scores = score_view(reference, estimate)
    assert scores["psnr"] == pytest.approx(peak_signal_noise_ratio(reference, estimate, data_range=1), abs=1e-6)
    assert scores["mse"] == pytest.approx(mean_squared_error(reference, estimate), abs=1e-9)
    ssim = structural_similarity(
        reference, estimate, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1
    )
    assert scores["ssim"] == pytest.approx(ssim, abs=1e-6)
    foreground = reference > 0
    assert scores["mse_foreground"] == pytest.approx(float(((reference - estimate)[foreground] ** 2).mean()), abs=1e-9)


def test_known_answers_are_not_errors():
    reference, _ = fixed_images()
    identical = score_view(reference, reference.copy())
    assert identical["psnr"] == math.inf and identical["psnr_foreground"] == math.inf
    assert identical["ssim"] == pytest.approx(1.0) and identical["mse"] == 0.0
    constant = score_view(np.full((20, 20), 0.3), np.full((20, 20), 0.5))
    assert constant["mse"] == pytest.approx(0.04) and constant["psnr"] == pytest.approx(10 * math.log10(1 / 0.04))
    assert math.isfinite(constant["ssim"])
    black = score_view(np.zeros((20, 20)), np.full((20, 20), 0.1))  # no foreground at all
    assert (
        math.isnan(black["psnr_foreground"])
        and math.isnan(black["ssim_foreground"])
        and black["psnr"] == pytest.approx(20.0)
    )
    tiny = score_view(np.ones((4, 4)) * 0.5, np.ones((4, 4)) * 0.25)  # below SSIM's 11×11 window
    assert math.isnan(tiny["ssim"]) and tiny["psnr"] == pytest.approx(10 * math.log10(16))


def test_summaries_keep_infinity_and_skip_missing_views():
    reference, estimate = fixed_images()
    rows = score_views(
        np.stack([reference, reference, np.zeros_like(reference)]),
        np.stack([estimate, reference, np.zeros_like(reference) + 0.1]),
    )
    summary = summarize(rows)
    assert summary["views"] == 3 and summary["psnr"] == math.inf and math.isnan(summary["psnr_std"])
    assert summary["psnr_foreground_views"] == 2  # the black view has no foreground
    finite = summarize(rows[:1] + rows[2:])
    assert finite["psnr"] == pytest.approx(np.mean([rows[0]["psnr"], rows[2]["psnr"]]))
    assert finite["psnr_std"] == pytest.approx(np.std([rows[0]["psnr"], rows[2]["psnr"]]))
    assert summarize([])["views"] == 0 and math.isnan(summarize([])["psnr"])


@settings(max_examples=30, deadline=None)
@given(st.floats(0, 1), st.floats(0, 1), st.sampled_from([np.float16, np.float32, np.float64]))
def test_scores_are_finite_or_infinite_never_errors(level, other, dtype):
    reference = np.full((12, 12), level, dtype=dtype)
    estimate = np.full((12, 12), other, dtype=dtype)
    scores = score_view(reference.astype(np.float32), estimate.astype(np.float32))
    assert scores["psnr"] >= 0 and not math.isnan(scores["psnr"])  # 0 dB: every pixel off by the full range
    assert -1.0 <= scores["ssim"] <= 1.0 + 1e-9


def test_colour_map_runs_from_black_to_pale_yellow_and_clips():
    colours = colour_map(np.array([0.0, 0.5, 1.0, 7.0, np.nan]), vmax=1.0)
    assert (
        tuple(colours[0]) == (0, 0, 4) and tuple(colours[2]) == (252, 255, 164) and tuple(colours[3]) == (252, 255, 164)
    )
    assert tuple(colours[4]) == (0, 0, 4) and colours[1].sum() > colours[0].sum()
    assert tuple(colour_map(np.array([1.0]), vmax=0.0)[0]) == (252, 255, 164)  # a zero scale is guarded


def test_error_grid_has_a_row_per_method(tmp_path):
    reference, estimate = fixed_images()
    grid = error_grid(reference, {"a": estimate, "b": reference}, "view")
    single = error_grid(reference, {"a": estimate}, "view")
    assert grid.height > single.height and grid.width == single.width


def test_turntable_and_plot_files(tmp_path):
    write_turntable(tmp_path / "t.gif", np.random.default_rng(0).random((5, 16, 16)))
    assert iio.imread(tmp_path / "t.gif", index=None).shape[0] == 5
    svg = line_plot_svg([("a", [0, 10, 20], [30.0, 35.0, float("nan")]), ("b", [5.0], [32.0])], "t", "x", "y")
    root = ElementTree.fromstring(svg)
    assert root.tag.endswith("svg") and svg.count("<polyline") == 1 and svg.count("<circle") == 3
    ElementTree.fromstring(line_plot_svg([], "empty", "x", "y"))  # no data: still a valid picture


def test_point_labels_never_overlap_each_other_or_a_point_and_stay_in_the_frame():
    rng = np.random.default_rng(3)
    anchors = [(float(x), float(y)) for x, y in rng.uniform((100, 100), (300, 250), size=(30, 2))]
    anchors += [(200.0, 175.0)] * 4  # coincident points: only one spot near them is free each time
    texts = [f"config={i}" for i in range(len(anchors))]
    texts[3] = ""
    bounds = (70.0, 30.0, 420.0, 350.0)
    spots = place_labels(anchors, texts, bounds)
    assert spots[3] is None
    boxes = [spot[3] for spot in spots if spot is not None]
    assert len(boxes) >= 20  # 33 names in a 200 × 150 px crowd: most find a spot
    for i, a in enumerate(boxes):
        assert bounds[0] <= a[0] and a[2] <= bounds[2] and bounds[1] <= a[1] and a[3] <= bounds[3]
        for b in boxes[i + 1 :]:
            assert not (a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3])
        for x, y in anchors:
            assert not (a[0] < x + 3.5 and x - 3.5 < a[2] and a[1] < y + 3.5 and y - 3.5 < a[3])


def _texts(svg: str) -> list[str]:
    return [e.text for e in ElementTree.fromstring(svg).iter() if e.tag.endswith("text")]


def test_log_tick_labels_of_values_beyond_a_float_say_the_power():
    from cubecloud_cli.eval.figures import _tick_label

    assert _tick_label(309.0, True) == "1e+309" and _tick_label(-320.0, True) == "1e-320"
    assert _tick_label(3.0, True) == "1,000" and _tick_label(0.5, False) == "0.5"


def test_log_axes_label_ticks_in_the_data_units_and_place_points_by_ratio():
    sizes, seconds = [128.0, 256.0, 512.0], [2.0, 20.0, 2000.0]
    svg = line_plot_svg([("t", sizes, seconds)], "t", "x", "y", log_axes=(True, True), x_ticks=tuple(sizes))
    texts = _texts(svg)
    assert {"128", "256", "512"} <= set(texts) and {"10", "100", "1,000"} <= set(texts)
    circles = [e for e in ElementTree.fromstring(svg).iter() if e.tag.endswith("circle")]
    xs = [float(c.get("cx")) for c in circles]
    ys = [float(c.get("cy")) for c in circles]
    assert xs[1] - xs[0] == pytest.approx(xs[2] - xs[1], abs=0.2)  # each doubling is the same width
    assert ys[0] - ys[1] == pytest.approx((ys[1] - ys[2]) / 2, abs=0.2)  # ×10 is half of ×100


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=0, max_size=6))
def test_log_axes_leave_out_values_a_log_cannot_show_and_still_draw(values):
    xs = [float(i + 1) for i in range(len(values))]
    svg = line_plot_svg([("v", xs, values)], "t", "x", "y", log_axes=(True, True))
    root = ElementTree.fromstring(svg)
    drawable = [v for v in values if math.isfinite(v) and 0 < v and math.isfinite(math.log10(v))]
    assert sum(1 for e in root.iter() if e.tag.endswith("circle")) == len(drawable)
    for e in root.iter():
        for attribute in ("cx", "cy", "x1", "y1", "x", "y"):
            if e.get(attribute) is not None:
                assert math.isfinite(float(e.get(attribute)))


def test_plot_keeps_every_point_off_the_axes():
    svg = line_plot_svg([("a", [0.0, 50.0, 100.0], [33.61, 40.0, 47.36])], "t", "x", "y", markers_only=True)
    root = ElementTree.fromstring(svg)
    axis_y = max(float(e.get("y1")) for e in root.iter() if e.tag.endswith("line"))
    axis_x = min(float(e.get("x1")) for e in root.iter() if e.tag.endswith("line") and e.get("x1") == e.get("x2"))
    for circle in (e for e in root.iter() if e.tag.endswith("circle")):
        assert float(circle.get("cy")) < axis_y - 5 and float(circle.get("cx")) > axis_x + 5
