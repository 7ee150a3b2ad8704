"""bench/scaling.py's arithmetic and its merge of earlier runs (the runs themselves are benchmarks)."""

import importlib.util
import json
import math
import sys
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

SCRIPT = Path(__file__).resolve().parents[1] / "bench" / "scaling.py"
spec = importlib.util.spec_from_file_location("bench_scaling", SCRIPT)
scaling = importlib.util.module_from_spec(spec)
spec.loader.exec_module(scaling)


@settings(max_examples=60, deadline=None)
@given(
    st.floats(-4.0, 6.0),
    st.floats(1e-6, 1e6),
    st.lists(st.integers(1, 4096), min_size=2, max_size=6, unique=True),
)
def test_growth_exponent_recovers_a_power_law(k, scale, sizes):
    assert scaling.growth_exponent(sizes, [scale * s**k for s in sizes]) == pytest.approx(k, abs=1e-6)


def test_growth_exponent_skips_what_a_logarithm_cannot_take_and_needs_two_sizes():
    assert scaling.growth_exponent([128, 256, 512], [1.0, None, 4.0]) == pytest.approx(1.0)
    assert math.isnan(scaling.growth_exponent([128, 256, 512], [0.0, -1.0, 4.0]))  # one usable point
    assert scaling.growth_exponent([128, 256, 512, 1024], [0.0, 2.0, -1.0, 8.0]) == pytest.approx(1.0)
    assert math.isnan(scaling.growth_exponent([256, 256], [2.0, 3.0]))  # no spread in size
    assert math.isnan(scaling.growth_exponent([1.0, 1.0 + 2e-16], [6.0, 12.0]))  # rounding, not growth
    assert math.isnan(scaling.growth_exponent([], []))


def row(size: int, seconds: float) -> dict:
    stages = {stage: seconds for stage in scaling.STAGES}
    result = {"gaussians": 1000, "iterations": 10, "novel_psnr": 40.0, "novel_psnr_foreground": 35.0}
    return {
        "size": size,
        "resolution": size,
        "views": 4,
        "wall_s": 6 * seconds,
        "seconds": stages,
        "peak_mb": dict(stages, preprocess=None),
        "files_mb": {stage: 1.0 for stage in scaling.STAGES},
        "splat": result,
        "splat-random": result,
        "export_rays_x_steps": size**3,
        "splat_pixels_x_gaussians": size**2,
    }


def test_from_json_merges_runs_in_size_order_and_draws_both_charts(tmp_path, monkeypatch, capsys):
    (tmp_path / "big").mkdir()
    (tmp_path / "small").mkdir()
    (tmp_path / "big" / "scaling.json").write_text(json.dumps({"rows": [row(512, 800.0)]}))
    (tmp_path / "small" / "scaling.json").write_text(json.dumps({"rows": [row(256, 100.0), row(128, 12.5)]}))
    out = tmp_path / "merged"
    argv = [
        "scaling.py",
        "--from-json",
        str(tmp_path / "big" / "scaling.json"),
        str(tmp_path / "small" / "scaling.json"),
    ]
    monkeypatch.setattr(sys, "argv", argv + ["--out", str(out)])
    scaling.main()
    merged = json.loads((out / "scaling.json").read_text())
    assert [r["size"] for r in merged["rows"]] == [128, 256, 512]
    assert merged["exponents"]["cunerf"] == pytest.approx(3.0)  # 12.5, 100, 800: ×8 per doubling
    assert merged["exponents"]["export rays × steps"] == pytest.approx(3.0)
    assert "growth exponents" in capsys.readouterr().out
    for chart in ("time.svg", "psnr.svg"):
        texts = {e.text for e in ElementTree.parse(out / chart).iter() if e.tag.endswith("text")}
        assert {"128", "256", "512"} <= texts  # the measured sizes are the ticks
