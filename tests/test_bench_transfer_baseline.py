"""bench/transfer_baseline.py's baked runs reproduce each held-out transfer function exactly (the
runs themselves are benchmarks)."""

import importlib.util
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cubecloud_cli.cli import app
from cubecloud_cli.transfer.tissue_presets import resolve_transfer
from cubecloud_cli.transfer.training_set import held_out_transfers

SCRIPT = Path(__file__).resolve().parents[1] / "bench" / "transfer_baseline.py"
spec = importlib.util.spec_from_file_location("bench_transfer_baseline", SCRIPT)
baseline = importlib.util.module_from_spec(spec)
spec.loader.exec_module(baseline)

WIDE = {"modality": "ct", "low": -1000.0, "high": 1000.0}


@pytest.mark.parametrize("seed", [0, 7])
def test_each_held_out_transfer_function_is_exported_as_itself(seed):
    held = held_out_transfers(WIDE, seed, trained=[]).transfers
    assert [t.name for t in held][:3] == ["bone", "lung", "vessels"]
    for named in held:
        arguments = baseline.baked_arguments({"name": named.name, **named.function.as_dict()})
        options = dict(zip(arguments[::2], arguments[1::2]))
        overrides = [float(options[k]) if k in options else None for k in ("--tf-low", "--tf-high", "--tf-density")]
        assert resolve_transfer(options["--transfer"], WIDE, *overrides) == named.function
        # export's command line takes them as they are
        result = CliRunner().invoke(app, ["export", "/nonexistent-work", *arguments])
        assert "No such option" not in result.output and "Invalid value" not in result.output


def test_held_out_scores_are_gathered_by_name_over_the_seeds():
    seeds = [
        {"bone": {"psnr": 41.0}, "vessels": {"psnr": 40.5}, "held-out-ramp-0": {"psnr": 44.0}},
        {"bone": {"psnr": 42.0}, "vessels": {"psnr": 38.5}, "held-out-ramp-0": {"psnr": 42.0}},
    ]
    assert baseline.over_seeds(seeds) == {
        "bone": [41.0, 42.0],
        "vessels": [40.5, 38.5],
        "held-out-ramp-0": [44.0, 42.0],
    }
    assert baseline.over_seeds([]) == {}
