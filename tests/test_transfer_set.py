"""Training under many transfer functions: the set (transfer/training_set.py), the export's views
under each (--transfer-set) and a scalar splat run that trains under all of them."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cli_helpers import assert_one_line_error, invoke, tiny_work

from cubecloud_cli.splat.gaussian_ply import read_scalar_properties
from cubecloud_cli.transfer.function import TransferFunction
from cubecloud_cli.transfer.tissue_presets import resolve_transfer
from cubecloud_cli.transfer.training_set import (
    HELD_OUT_PRESETS,
    RAMP_DENSITY,
    NamedTransfer,
    held_out_transfers,
    random_ramps,
    random_windows,
    training_transfers,
)

CT_WINDOW = {"modality": "ct", "low": -160.0, "high": 240.0}


def test_the_set_starts_with_the_exports_own_and_never_holds_out_what_eval_tests():
    primary = NamedTransfer("tissue", resolve_transfer("tissue", CT_WINDOW))
    chosen = training_transfers(primary, 8, CT_WINDOW, seed=0)
    assert len(chosen) == 8 and chosen[0] == primary
    names = [t.name for t in chosen]
    assert len(set(names)) == 8 and not set(names) & set(HELD_OUT_PRESETS)
    assert names[1:3] == ["soft", "glow"] and names[3:5] == ["band-0", "ramp-1"]
    assert all(n.startswith(("band-", "ramp-")) for n in names[3:])
    held = held_out_transfers(CT_WINDOW, seed=0, trained=chosen)
    assert {t.function for t in held.transfers}.isdisjoint({t.function for t in chosen})
    assert training_transfers(primary, 1, CT_WINDOW, seed=0) == [primary]
    assert training_transfers(primary, 8, CT_WINDOW, seed=0) == chosen  # seeded: the same set again
    with pytest.raises(ValueError):
        training_transfers(primary, 0, CT_WINDOW, seed=0)


def test_random_windows_are_valid_bands_and_ramps_by_turns():
    windows = random_windows(200, seed=5)
    for index, window in enumerate(windows):
        window.function.validate()
        assert window.function.is_band == (index % 2 == 0)
        assert RAMP_DENSITY[0] <= window.function.density <= RAMP_DENSITY[1]
    tops = np.array([w.function.fall_low - w.function.high for w in windows[::2]])
    assert tops.min() < 0.05 and tops.max() > 0.2  # narrow and wide alike


def test_random_ramps_are_valid_transfer_functions_over_the_value_range():
    ramps = random_ramps(200, seed=5)
    for ramp in ramps:
        ramp.function.validate()
        assert RAMP_DENSITY[0] <= ramp.function.density <= RAMP_DENSITY[1]
    widths = np.array([r.function.high - r.function.low for r in ramps])
    assert widths.min() < 0.05 and widths.max() > 0.4  # narrow and wide alike


@pytest.fixture(scope="module")
def exported_under_three(tmp_path_factory):
    return tiny_work(tmp_path_factory.mktemp("transfer_set") / "work", cunerf_iterations=60, views=12,
                     max_points=1500, novel_directions=2, splat=None, export=("--transfer-set", "3"))  # fmt: skip


def test_export_renders_the_training_views_under_each_transfer_function(exported_under_three):
    export = exported_under_three / "export"
    manifest = json.loads((export / "manifest.json").read_text())
    listed = manifest["transfers"]
    assert [t["name"] for t in listed] == ["tissue", "soft", "glow"]
    assert listed[0] == {"name": "tissue", **manifest["image_model"]["transfer"]}
    stack = np.load(export / "transfer_images.npy")
    assert stack.shape == (3, 12, 32, 32)
    np.testing.assert_array_equal(stack[0], np.load(export / "images.npy"))
    # Other transfer functions show other images (glow shows every non-air voxel).
    assert not np.allclose(stack[0], stack[1]) and not np.allclose(stack[0], stack[2])
    assert "render_transfers" in manifest["timings_s"]


def test_a_scalar_run_trains_under_the_whole_set(exported_under_three):
    work = exported_under_three
    result = invoke("splat", work, "--scalar", "--iterations", "40", "--eval-every", "40", "--device", "cpu", "-q")
    assert result.exit_code == 0, result.output
    properties = read_scalar_properties(work / "splat" / "point_cloud.ply")
    listed = json.loads((work / "export" / "manifest.json").read_text())["transfers"]
    assert properties.trained_under == [TransferFunction.from_dict(t) for t in listed]
    assert properties.drawn_under == properties.trained_under[0]
    manifest = json.loads((work / "splat" / "manifest.json").read_text())
    assert "export/transfer_images.npy" in manifest["inputs"] and manifest["metrics"]["test_psnr"] > 15


def test_export_renders_the_novel_views_under_the_held_out_transfer_functions(exported_under_three):
    novel = exported_under_three / "export" / "novel"
    listed = json.loads((novel / "transfers.json").read_text())
    held = listed["held_out"]
    # The abdomen window (-160..240 HU) keeps nothing of the lung band (-950..-300 HU).
    assert [t["name"] for t in held] == ["bone", "vessels", "held-out-ramp-0"]
    assert list(listed["not_scored"]) == ["lung"] and "--window" in listed["not_scored"]["lung"]
    assert held[1]["fall_low"] == 1.0 and held[1]["fall_high"] == 1.0  # the band's fall lies above the window
    trained = json.loads((exported_under_three / "export" / "manifest.json").read_text())["transfers"]
    assert {(t["low"], t["high"], t["density"]) for t in held}.isdisjoint(
        {(t["low"], t["high"], t["density"]) for t in trained}
    )
    main = np.load(novel / "reference.npy")
    for entry in held:
        reference = np.load(novel / entry["file"])
        assert reference.shape == main.shape and np.isfinite(reference).all() and not np.allclose(reference, main)


def test_eval_scores_a_scalar_run_under_the_held_out_transfer_functions_and_a_baked_one_not(
    exported_under_three, tmp_path
):
    import shutil

    work = tmp_path / "work"
    for stage in ("preprocess", "cunerf", "export"):
        shutil.copytree(exported_under_three / stage, work / stage)
    quick = ["--iterations", "40", "--eval-every", "40", "--device", "cpu", "-q"]
    for extra in (["--scalar"], ["--name", "baked"]):
        assert invoke("splat", work, *quick, *extra).exit_code == 0
    result = invoke("eval", work, "--turntable-frames", "0", "--device", "cpu", "-q")
    assert result.exit_code == 0, result.output
    results = json.loads((work / "eval" / "metrics.json").read_text())["results"]
    held = results["splat"]["held_out_transfers"]
    assert list(held) == ["bone", "vessels", "held-out-ramp-0"]
    for summary in held.values():
        assert summary["views"] == 2 * 3 and 5 < summary["psnr"] < 100  # 2 directions × 0.75, 1, 1.33
    assert "held_out_transfers" not in results["splat-baked"]
    report = (work / "eval" / "report.md").read_text()
    assert "## Transfer functions held out of training" in report and "| splat | bone |" in report
    assert "Not scored: lung shows -950..-300 HU, which the window -160..240 HU clips away" in report
    rows = (work / "eval" / "per_view.csv").read_text()
    assert "held-out transfer function bone" in rows


@pytest.mark.parametrize(
    "args, pattern",
    [
        (["--transfer-set", "0"], r"--transfer-set 0 must be within 1\.\.64"),
        (["--transfer-set", "2", "--view", "mip"], r"only --view dvr has"),
        (["--transfer", "lung"], r"--transfer lung shows -950\.\.-300 HU, which the window .* clips away"),
    ],
)
def test_bad_transfer_sets_are_refused(exported_under_three, tmp_path, args, pattern):
    assert_one_line_error(invoke("export", exported_under_three, "--force", *args), pattern)
    assert (exported_under_three / "export" / "manifest.json").is_file()  # nothing lost
