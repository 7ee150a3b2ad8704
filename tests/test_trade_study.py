"""examples/trade_study.py at toy sizes: configurations share the stages they have in common,
and every configuration's line carries its stage times and held-out scores."""

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # runs first: pytest-xdist's workers then end together

SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "trade_study.py"


def test_a_toy_trade_study(tmp_path, monkeypatch, capsys):
    out = tmp_path / "trade"
    command = [
        sys.executable,
        str(SCRIPT),
        "--knobs",
        "iterations",
        "--values",
        "iterations=12",
        "--out",
        str(out),
        "--stage-options",
        "preprocess=--size 16",
        "--stage-options",
        "cunerf=--iterations 20 --batch-size 512",
        "--stage-options",
        "export=--views 4 --resolution 16 --cube 8 --points-per-cube 32",
        "--stage-options",
        "splat=--iterations 6 --random-points 300 --eval-every 3 --checkpoint-every 3",
    ]
    result = subprocess.run(command, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-2000:]
    with open(out / "trade.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert [(r["config"], r["method"]) for r in rows] == [
        (config, method)
        for config in ("preset", "iterations=12")
        for method in ("Cube-Cloud 3DGS", "3DGS, random init")
    ]
    for row in rows:
        assert float(row["pipeline_s"]) > float(row["splat_s"]) > 0 and 0 < float(row["psnr"]) < 100
        assert 0 < float(row["novel_psnr"]) < 100 and 0 < float(row["novel_psnr_0.5x"]) < 100
    # The knob only touches splat: the upstream stages are the preset's, hard-linked, not rerun.
    preset, varied = out / "preset", out / "iterations-12"
    for stage in ("preprocess", "cunerf", "export"):
        assert (varied / stage / "manifest.json").stat().st_ino == (preset / stage / "manifest.json").stat().st_ino
    iterations = json.loads((varied / "splat" / "manifest.json").read_text())["params"]["iterations"]
    assert iterations == 12
    assert "<svg" in (out / "time_vs_psnr.svg").read_text() and (out / "trade.md").read_text().count("\n") == 2 + 4
    # Into the same OUT again: nothing is redone; a changed knob value runs only its new stages.
    # The script ran above as a user runs it; the runs below call its main() in this process,
    # which spares each one Python's start and torch's import.
    trade, options = _load_script(), command[2:]
    code, printed, _ = _main(trade, options, monkeypatch, capsys)
    assert code == 0 and "cubecloud " not in printed.replace("trade", "")
    options[options.index("iterations=12")] = "iterations=12,30"
    code, printed, err = _main(trade, options, monkeypatch, capsys)
    assert code == 0, err[-2000:]
    ran = [line for line in printed.splitlines() if ": cubecloud " in line]
    assert ran and all(line.strip().startswith("iterations=30:") for line in ran)
    # A finished work directory from elsewhere (e.g. `cubecloud run --preset balanced`) joins as a line.
    code, _, err = _main(trade, [*options, "--include", f"other={preset}"], monkeypatch, capsys)
    assert code == 0, err[-2000:]
    with open(out / "trade.csv", newline="") as handle:
        other = [r for r in csv.DictReader(handle) if r["config"] == "other"]
    assert [r["method"] for r in other] == ["Cube-Cloud 3DGS", "3DGS, random init"]
    assert float(other[0]["psnr"]) == float(rows[0]["psnr"])
    code, _, err = _main(trade, [*options, "--include", f"broken={tmp_path}"], monkeypatch, capsys)
    assert code == 2 and "every stage complete" in err
    _a_finished_run_seeds_the_base(preset, tmp_path, monkeypatch, capsys)


def _a_finished_run_seeds_the_base(finished: Path, tmp_path, monkeypatch, capsys):
    """--base WORK: a run with the preset's parameters becomes the preset line, hard-linked and
    not rerun; one with other parameters, another scan or extra stage options is refused."""
    base = [
        sys.executable,
        str(SCRIPT),
        "--knobs",
        "iterations",
        "--values",
        "iterations=12",
        "--out",
        str(tmp_path / "b"),
    ]
    trade = _load_script()
    code, _, err = _main(trade, [*base[2:], "--base", str(finished), "--stage-options", "preprocess=--size 16"], monkeypatch, capsys)  # fmt: skip
    assert code == 2 and "--base with --stage-options" in err
    # The toy run is not a `--preset fast` run: the refusal names what differs.
    code, _, err = _main(trade, [*base[2:], "--base", str(finished)], monkeypatch, capsys)
    assert code == 2 and "preprocess size is 16, the preset's is 128" in err
    assert not (tmp_path / "b").exists()

    from cubecloud_cli import presets

    # Make the toy's options the preset's own, so the toy run is a run of the preset.
    monkeypatch.setitem(presets.PRESETS["preprocess"]["fast"], "size", 16)
    for key, value in {"views": 4, "resolution": 16, "points_per_cube": 32}.items():
        monkeypatch.setitem(presets.PRESETS["export"]["fast"], key, value)
    monkeypatch.setitem(presets.PRESETS["splat"]["fast"], "iterations", 6)
    model = presets.CUNERF_DEFAULT_MODEL["fast"]
    for key, value in {"iterations": 20, "batch_size": 512}.items():
        monkeypatch.setitem(presets.CUNERF_PRESETS["fast"][model], key, value)
    assert trade.base_mismatches(finished, None, "fast", None) == []
    (tmp_path / "scan.nii.gz").write_bytes(b"another scan")
    assert any(
        "another scan" in p for p in trade.base_mismatches(finished, str(tmp_path / "scan.nii.gz"), "fast", None)
    )
    assert trade.base_mismatches(finished, None, "fast", "lung") == [
        "preprocess window is 'abdomen', the preset's is 'lung'"
    ]

    work = tmp_path / "seeded" / "preset"
    keys = trade.chain_keys(trade.stage_commands(None, Path("WORK"), "fast", None, {}))
    trade.seed_from_base(finished, work, keys)
    capsys.readouterr()
    commands = trade.stage_commands(None, work, "fast", None, {})
    with trade.JobServerOnDemand(trade.CUBECLOUD_JOBS) as jobs:
        trade.run_configuration("preset", commands, keys, work, {}, jobs)
        assert jobs._command is None  # no server started: nothing was to run
    assert "cubecloud" not in capsys.readouterr().out  # every stage kept, none rerun
    for stage in trade.STAGES:
        assert (work / stage / "manifest.json").stat().st_ino == (finished / stage / "manifest.json").stat().st_ino


def _main(trade, arguments: list[str], monkeypatch, capsys) -> tuple[int, str, str]:
    """The script's main() with these arguments: its exit code, standard output and error."""
    capsys.readouterr()
    monkeypatch.setattr(sys, "argv", [str(SCRIPT), *arguments])
    try:
        trade.main()
        code = 0
    except SystemExit as exit:
        code = exit.code if isinstance(exit.code, int) else 1
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _load_script():
    import importlib.util

    spec = importlib.util.spec_from_file_location("trade_study", SCRIPT)
    trade = importlib.util.module_from_spec(spec)
    sys.modules["trade_study"] = trade  # its dataclasses look their module up there
    spec.loader.exec_module(trade)
    return trade


def test_default_knob_values_follow_the_preset():
    trade = _load_script()
    names = lambda preset: [
        name for name, _ in trade.configurations(list(trade.KNOBS), trade.preset_values(preset, {}))
    ]
    assert names("fast") == [
        "preset",
        "volume=96",
        "volume=192",
        "cunerf_start=random",  # fast trains no CuNeRF iteration: no iterations nor batch to vary
        "cameras=orbit",
        "views=60",
        "views=240",
        "points_per_cube=128",
        "points_per_cube=2048",
        "iterations=750",
        "iterations=3000",
        "budget=9375",  # an eighth and a quarter of the preset's 75k budget
        "budget=18750",
        "antialias=off",
    ]
    balanced = names("balanced")
    assert "volume=144" in balanced and "iterations=14000" in balanced and "budget=37500" in balanced
    assert not [name for name in balanced if name.startswith("cunerf_batch")]  # the fitted start trains no batch
    assert not [name for name in names("paper") if name.startswith("budget")]  # the paper sets no budget to vary


def test_the_camera_antialias_and_cunerf_knobs():
    """Choices take every value but the preset's; CuNeRF's iterations go down from the preset's
    (none where it trains none; the start knob then trains random features);
    a stage option given to every configuration moves the base, as on the command line."""
    study = _load_script()
    base = study.preset_values("fast", {})
    assert (base["cameras"], base["antialias"], base["cunerf_iterations"]) == ("sphere", "on", 0)
    assert study.configurations(["cameras", "antialias", "cunerf_start", "cunerf_iterations"], base) == [
        ("preset", {}),
        ("cameras=orbit", {"export": ["--cameras", "orbit"]}),
        ("antialias=off", {"splat": ["--no-antialias"]}),
        ("cunerf_start=random", {"cunerf": ["--grid-init", "random", "--iterations", "3000"]}),
    ]
    balanced = study.preset_values("balanced", {})  # the fitted start, as fast
    assert study.configurations(["cunerf_start", "cunerf_iterations"], balanced) == [
        ("preset", {}),
        ("cunerf_start=random", {"cunerf": ["--grid-init", "random", "--iterations", "3000"]}),
    ]
    trained = study.preset_values("balanced", {"cunerf": ["--grid-init", "random", "--iterations", "5000"]})
    assert study.configurations(["cunerf_start", "cunerf_iterations"], trained) == [
        ("preset", {}),
        ("cunerf_start=volume", {"cunerf": ["--grid-init", "volume", "--iterations", "0"]}),
        ("cunerf_iterations=625", {"cunerf": ["--iterations", "625"]}),
        ("cunerf_iterations=1250", {"cunerf": ["--iterations", "1250"]}),
        ("cunerf_iterations=2500", {"cunerf": ["--iterations", "2500"]}),
    ]
    moved = study.preset_values("fast", {"splat": ["--antialias", "--no-antialias"], "export": ["--cameras", "orbit"]})
    assert (moved["antialias"], moved["cameras"]) == ("off", "orbit")
    assert study.configurations(["antialias"], moved) == [("preset", {}), ("antialias=on", {"splat": ["--antialias"]})]
    assert (
        study.preset_values("paper", {})["cameras"] == "orbit"
        and study.preset_values("paper", {})["antialias"] == "off"
    )
    commands = study.stage_commands(None, Path("W"), "fast", None, {"cunerf": ["--iterations", "500"]})
    assert commands["cunerf"] == ["cunerf", "W", "--preset", "fast", "--iterations", "500"]


def test_a_value_outside_a_knobs_choices_is_refused(tmp_path):
    result = subprocess.run(
        [sys.executable, str(SCRIPT), "--knobs", "cameras", "--values", "cameras=cube", "--out", str(tmp_path / "t")],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 2 and "cameras=cube" in result.stderr
