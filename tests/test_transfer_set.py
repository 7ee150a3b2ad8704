"""Training under many transfer functions: the set (transfer/training_set.py), the export's views
under each (--transfer-set) and a scalar splat run that trains under all of them."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cli_helpers import assert_one_line_error, invoke, tiny_export_options, tiny_work
from hypothesis import given
from hypothesis import strategies as st
from PIL import Image

from cubecloud_cli.eval.figures import LABEL_HEIGHT, enlargement, grey_to_rgb
from cubecloud_cli.splat.gaussian_ply import read_scalar_properties
from cubecloud_cli.transfer.function import TransferFunction
from cubecloud_cli.transfer.tissue_presets import resolve_transfer
from cubecloud_cli.transfer.training_set import (
    HELD_OUT_PRESETS,
    RAMP_DENSITY,
    RAMP_START,
    TILE_DENSITIES,
    TILE_SIDES,
    NamedTransfer,
    held_out_transfers,
    member_slot,
    member_views,
    random_ramps,
    random_windows,
    tiled_bands,
    training_transfers,
)

CT_WINDOW = {"modality": "ct", "low": -160.0, "high": 240.0}
WINDOWS = ["held-out-window-band-0", "held-out-window-ramp-1"]  # --held-out-windows 2


def test_the_set_starts_with_the_exports_own_and_never_holds_out_what_eval_tests():
    primary = NamedTransfer("tissue", resolve_transfer("tissue", CT_WINDOW))
    chosen = training_transfers(primary, 8, CT_WINDOW, seed=0)
    assert len(chosen) == 8 and chosen[0] == primary
    names = [t.name for t in chosen]
    assert len(set(names)) == 8 and not set(names) & set(HELD_OUT_PRESETS)
    assert names[1:3] == ["soft", "glow"] and names[3:5] == ["tiled-band-0", "tiled-band-1"]
    assert names[5:] == ["band-0", "ramp-1", "band-2"]  # half the rest tiled (rounded down), then drawn
    held = held_out_transfers(CT_WINDOW, seed=0, trained=chosen)
    assert {t.function for t in held.transfers}.isdisjoint({t.function for t in chosen})
    assert training_transfers(primary, 1, CT_WINDOW, seed=0) == [primary]
    assert training_transfers(primary, 8, CT_WINDOW, seed=0) == chosen  # seeded: the same set again
    with pytest.raises(ValueError):
        training_transfers(primary, 0, CT_WINDOW, seed=0)


def test_held_out_windows_come_after_the_four_from_a_stream_no_training_set_draws():
    primary = NamedTransfer("tissue", resolve_transfer("tissue", CT_WINDOW))
    for seed in (0, 1, 7):
        trained = training_transfers(primary, 64, CT_WINDOW, seed=seed)
        four = held_out_transfers(CT_WINDOW, seed=seed, trained=trained)
        wider = held_out_transfers(CT_WINDOW, seed=seed, trained=trained, windows=12)
        assert wider.transfers[: len(four.transfers)] == four.transfers and wider.not_scored == four.not_scored
        windows = wider.transfers[len(four.transfers) :]
        assert [w.name for w in windows][:2] == WINDOWS and len({w.name for w in windows}) == 12
        assert {w.function for w in windows}.isdisjoint({t.function for t in trained})
        assert {w.function for w in windows}.isdisjoint({t.function for t in four.transfers})


def test_the_tiled_bands_are_the_same_at_every_seed_and_the_drawn_ones_are_not():
    primary = NamedTransfer("tissue", resolve_transfer("tissue", CT_WINDOW))
    sets = [training_transfers(primary, 41, CT_WINDOW, seed=seed) for seed in (0, 1)]
    tiled = [[t for t in chosen if t.name.startswith("tiled-band-")] for chosen in sets]
    assert len(tiled[0]) == 19 and tiled[0] == tiled[1]
    assert sets[0][22:] != sets[1][22:]


def test_tiled_bands_start_evenly_over_the_value_range_and_cycle_their_shapes():
    bands = tiled_bands(19)
    for band in bands:
        band.function.validate()
        assert band.function.is_band
    lows = np.array([b.function.low for b in bands])
    assert lows[0] == RAMP_START[0] and lows[-1] == pytest.approx(RAMP_START[1])
    np.testing.assert_allclose(np.diff(lows), (RAMP_START[1] - RAMP_START[0]) / 18)
    assert {b.function.density for b in bands[:3]} == set(TILE_DENSITIES)
    assert {round(b.function.high - b.function.low, 9) for b in bands[:2]} == set(TILE_SIDES)
    assert [b.function.low for b in tiled_bands(1)] == [RAMP_START[0]] and tiled_bands(0) == []


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
                     max_points=1500, novel_directions=2, splat=None,
                     export=("--transfer-set", "3", "--held-out-windows", "2"))  # fmt: skip


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
    assert [t["name"] for t in held] == ["bone", "vessels", "held-out-ramp-0", *WINDOWS]
    assert list(listed["not_scored"]) == ["lung"] and "--window" in listed["not_scored"]["lung"]
    assert held[1]["fall_low"] == 1.0 and held[1]["fall_high"] == 1.0  # the band's fall lies above the window
    trained = json.loads((exported_under_three / "export" / "manifest.json").read_text())["transfers"]
    assert {(t["low"], t["high"], t["density"]) for t in held}.isdisjoint(
        {(t["low"], t["high"], t["density"]) for t in trained}
    )
    main = np.load(novel / "reference.npy")
    views = json.loads((novel / "views.json").read_text())
    # Eval scores them at the headline magnifications only, so only those are rendered.
    headline = [i for i, v in enumerate(views["views"]) if v["magnification"] in (0.75, 1.0, 1.33)]
    for entry in held:
        assert entry["magnifications"] == [0.75, 1.0, 1.33]
        reference = np.load(novel / entry["file"])
        assert reference.shape == main[headline].shape and np.isfinite(reference).all()
        assert not np.allclose(reference, main[headline])


def _panel_of(picture: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """An error grid's first reference panel (row one, column one), back at its own size."""
    factor = enlargement(shape)
    top = 2 * LABEL_HEIGHT  # the title, then the row's label
    return picture[top : top + shape[0] * factor : factor, : shape[1] * factor : factor]


def test_eval_scores_a_scalar_run_under_the_held_out_transfer_functions_and_a_baked_one_not(
    exported_under_three, tmp_path
):
    import shutil

    work = tmp_path / "work"
    for stage in ("preprocess", "cunerf", "export"):
        shutil.copytree(exported_under_three / stage, work / stage)
    quick = ["--iterations", "40", "--eval-every", "40", "--device", "cpu", "-q"]
    for extra in (["--scalar", "--chord-lengths"], ["--name", "baked"]):
        assert invoke("splat", work, *quick, *extra).exit_code == 0
    result = invoke("eval", work, "--turntable-frames", "0", "--device", "cpu", "-q")
    assert result.exit_code == 0, result.output
    results = json.loads((work / "eval" / "metrics.json").read_text())["results"]
    held = results["splat"]["held_out_transfers"]
    assert list(held) == ["bone", "vessels", "held-out-ramp-0", *WINDOWS]
    for summary in held.values():
        assert summary["views"] == 2 * 3 and 5 < summary["psnr"] < 100  # 2 directions × 0.75, 1, 1.33
    assert "held_out_transfers" not in results["splat-baked"]
    # Its optical lengths follow the ray, so eval also scores the PLY's one opacity per Gaussian.
    fixed = results["splat"]["novel_fixed_opacity"]
    assert fixed["views"] == 2 * 3 and 5 < fixed["psnr"] < 100 and fixed["psnr"] != results["splat"]["novel_psnr"]
    assert "novel_fixed_opacity" not in results["splat-baked"]
    report = (work / "eval" / "report.md").read_text()
    assert "## Transfer functions held out of training" in report and "| splat | bone |" in report
    assert "Drawn with one opacity per Gaussian, as its PLY's reference columns" in report
    assert "Not scored: lung shows -950..-300 HU, which the window -160..240 HU clips away" in report
    rows = (work / "eval" / "per_view.csv").read_text()
    assert "held-out transfer function bone" in rows
    # Each held out is pictured at the first novel view at 1x: its reference panel is the volume
    # rendered under that transfer function there, so the pictures differ.
    pictures = {}
    for name in held:
        assert f"](views/held_out_{name}.png)" in report
        pictures[name] = np.asarray(Image.open(work / "eval" / "views" / f"held_out_{name}.png").convert("L"))
    novel = work / "export" / "novel"
    listed = {e["name"]: e for e in json.loads((novel / "transfers.json").read_text())["held_out"]}
    for name in ("bone", "vessels"):
        entry = listed[name]
        reference = np.load(novel / entry["file"])[entry["magnifications"].index(1.0) * 2]
        panel = grey_to_rgb(reference)[..., 0]
        assert _panel_of(pictures[name], panel.shape) == pytest.approx(panel, abs=1)
    assert not np.array_equal(pictures["bone"], pictures["vessels"])


@pytest.mark.parametrize(
    "args, pattern",
    [
        (["--transfer-set", "0"], r"--transfer-set 0 must be within 1\.\.64"),
        (["--transfer-set", "2", "--view", "mip"], r"only --view dvr has"),
        (["--held-out-windows", "3", "--transfer-set", "1"], r"--held-out-windows .* needs --transfer-set 2 or more"),
        (["--transfer-stride", "0"], r"--transfer-stride 0 must be within 1\.\.\d+ \(the views\)"),
        (["--transfer-stride", "2", "--transfer-set", "1"], r"--transfer-stride .* needs --transfer-set 2 or more"),
        (["--held-out-windows", "65"], r"--held-out-windows 65 must be within 0\.\.64"),
        (["--transfer", "lung"], r"--transfer lung shows -950\.\.-300 HU, which the window .* clips away"),
    ],
)
def test_bad_transfer_sets_are_refused(exported_under_three, tmp_path, args, pattern):
    assert_one_line_error(invoke("export", exported_under_three, "--force", *args), pattern)
    assert (exported_under_three / "export" / "manifest.json").is_file()  # nothing lost


@given(views=st.integers(1, 200), stride=st.integers(1, 200), member=st.integers(0, 100))
def test_member_views_share_the_views_out_evenly(views, stride, member):
    if stride > views:
        with pytest.raises(ValueError):
            member_views(member, stride, views)
        return
    chosen = member_views(member, stride, views)
    assert len(chosen) == views // stride and chosen[0] == member % stride and chosen[-1] < views
    assert all(b - a == stride for a, b in zip(chosen, chosen[1:]))
    assert [member_slot(member, view, stride) for view in chosen] == list(range(len(chosen)))
    shared = sorted(v for k in range(stride) for v in member_views(k, stride, views))
    assert shared == list(range((views // stride) * stride))  # a stride's members take each view once
    assert member_views(member, 1, views) == list(range(views))


@pytest.fixture(scope="module")
def strided(exported_under_three):
    """The same work directory exported again with the set spread over the views (--transfer-stride 2)."""
    result = invoke("export", exported_under_three, "--name", "strided", "--transfer-set", "3",
                    "--transfer-stride", "2", *tiny_export_options(12, 1500, 2), "-q")  # fmt: skip
    assert result.exit_code == 0, result.output
    return exported_under_three / "export-strided"


def test_a_strided_set_renders_each_member_at_its_share_of_the_views(exported_under_three, strided):
    every_view = np.load(exported_under_three / "export" / "transfer_images.npy")
    stack = np.load(strided / "transfer_images.npy")
    assert stack.shape == (3, 6, 32, 32)
    for member in range(3):
        np.testing.assert_array_equal(stack[member], every_view[member, member_views(member, 2, 12)])
    manifest = json.loads((strided / "manifest.json").read_text())
    assert manifest["transfer_stride"] == 2 and manifest["params"]["transfer_stride"] == 2


def test_a_scalar_run_draws_only_the_images_a_strided_set_rendered(exported_under_three, strided):
    import torch

    from cubecloud_cli.splat.densify import strategy_for
    from cubecloud_cli.splat.scalar_gaussians import scalar_gaussians_from_points
    from cubecloud_cli.splat.settings import SplatSettings
    from cubecloud_cli.splat.trainer import SplatTrainer
    from cubecloud_cli.splat.training_views import load_scene

    every_view = np.load(exported_under_three / "export" / "transfer_images.npy")
    scene = load_scene(strided, every_transfer=True)
    assert scene.transfer_stride == 2
    pairs = scene.transfer_pairs()
    assert pairs and all(view in scene.train and view in member_views(k, 2, 12) for k, view in pairs)
    rng = np.random.default_rng(0)
    model = scalar_gaussians_from_points(rng.uniform(-1, 1, (50, 3)), rng.uniform(0, 1, 50), scene.transfers)
    settings = SplatSettings(iterations=10, scalar=True)
    trainer = SplatTrainer(model, scene, settings, torch.device("cpu"), strategy_for(settings, scene.extent))
    own = 0
    for _ in range(400):
        view, image = trainer._target(trainer.next_view())
        member = scene.transfers.index(trainer.gaussians.transfer)
        assert view in scene.train
        np.testing.assert_array_equal(image[..., 0].numpy(), every_view[member, view])
        own += member == 0
    # Every image rendered is drawn alike: the export's own at each training view, each other member at its share.
    expected = len(scene.train) / (len(scene.train) + len(pairs))
    assert abs(own / 400 - expected) < 0.1


def test_a_scalar_run_trains_on_a_strided_set(exported_under_three, strided):
    work = exported_under_three
    result = invoke("splat", work, "--scene", strided, "--scalar", "--name", "strided", "--iterations", "40",
                    "--eval-every", "40", "--device", "cpu", "-q")  # fmt: skip
    assert result.exit_code == 0, result.output
    manifest = json.loads((work / "splat-strided" / "manifest.json").read_text())
    assert "transfer_images.npy" in " ".join(manifest["inputs"]) and manifest["metrics"]["test_psnr"] > 15


def test_held_out_references_are_found_at_the_headline_views_in_either_layout():
    """Exports from before 2026-11-29 rendered the held-out references at every magnification."""
    from cubecloud_cli.eval.novel_scores import HeldOutTransfer

    every = HeldOutTransfer("bone", TransferFunction(0.7, 0.9, 12.0), np.zeros((10, 4, 4)), (0.5, 0.75, 1.0, 1.33, 2.0))
    headline = HeldOutTransfer("bone", TransferFunction(0.7, 0.9, 12.0), np.zeros((6, 4, 4)), (0.75, 1.0, 1.33))
    assert every.views_at([0.75, 1.0, 1.33], 2) == [2, 3, 4, 5, 6, 7]
    assert headline.views_at([0.75, 1.0, 1.33], 2) == [0, 1, 2, 3, 4, 5]


def test_an_export_interrupted_among_the_set_s_views_continues_where_it_stopped(
    exported_under_three, strided, tmp_path
):
    """Ctrl-C while the set's members are drawn view by view: the same command draws only the
    members' views not yet saved, and the stack is the uninterrupted export's to the bit."""
    import os
    import shutil
    import signal

    import cubecloud_cli.export.renders as renders

    work = tmp_path / "work"
    for stage in ("preprocess", "cunerf"):
        shutil.copytree(exported_under_three / stage, work / stage)
    original, members_drawn, interrupts = renders.render_view_under, [], []

    def interrupted(field, cameras, view, models, *args, **kwargs):
        members_drawn.append(len(models))
        if len(members_drawn) == 3 and not interrupts:
            interrupts.append(view)
            os.kill(os.getpid(), signal.SIGINT)
        return original(field, cameras, view, models, *args, **kwargs)

    arguments = ("export", work, "--transfer-set", "3", "--transfer-stride", "2", *tiny_export_options(12, 1500, 2))
    with pytest.MonkeyPatch.context() as patched:
        patched.setattr(renders, "render_view_under", interrupted)
        assert invoke(*arguments).exit_code == 130
        assert members_drawn == [1, 1, 1]  # stride 2, 3 members: one other member at each view
        members_drawn.clear()
        result = invoke(*arguments, "-q")
    assert result.exit_code == 0, result.output
    assert sum(members_drawn) == 2 * 6 - 2  # two members after the first at 6 views each; the 3rd was cut short
    np.testing.assert_array_equal(
        np.load(work / "export" / "transfer_images.npy"), np.load(strided / "transfer_images.npy")
    )
