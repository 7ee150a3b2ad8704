"""`cubecloud eval --compare A B …`: one table across work directories (a preset sweep), from each
one's ``eval/metrics.json`` and stage manifests: what was run, how long each stage took, and the
held-out scores."""

from __future__ import annotations

import json
import math
from pathlib import Path

from cubecloud_cli.artifacts import is_complete, read_manifest, to_jsonable
from cubecloud_cli.errors import CubecloudError

STAGES = ("preprocess", "cunerf", "export")


def _stage_seconds(manifest: dict | None) -> float | None:
    return None if manifest is None else manifest.get("timings_s", {}).get("total")


def describe_work(work: Path) -> dict:
    """The setup of a work directory and its eval results, as one comparable record."""
    work = Path(work)
    metrics_file = work / "eval" / "metrics.json"
    if not is_complete(work / "eval") or not metrics_file.is_file():
        raise CubecloudError(f"{work} has no complete eval: run `cubecloud eval {work}` first")
    try:
        metrics = json.loads(metrics_file.read_text())
    except (OSError, ValueError) as exc:
        raise CubecloudError(f"{metrics_file} is unreadable ({exc}): run `cubecloud eval {work} --force`") from None
    manifests = {stage: read_manifest(work / stage) if is_complete(work / stage) else None for stage in STAGES}
    params = {stage: (m or {}).get("params", {}) for stage, m in manifests.items()}
    setup = {
        "volume": params["preprocess"].get("size"),
        "cunerf_iterations": params["cunerf"].get("iterations"),
        "views": params["export"].get("views"),
        "resolution": params["export"].get("resolution"),
        "image_model": params["export"].get("view"),
        "points_per_cube": params["export"].get("points_per_cube"),
        "max_points": params["export"].get("max_points"),
    }
    seconds = {stage: _stage_seconds(m) for stage, m in manifests.items()}
    rows = {}
    for row, result in metrics.get("results", {}).items():
        splat = read_manifest(work / row) if row.startswith("splat") and is_complete(work / row) else None
        rows[row] = {
            "method": result.get("method_name"),
            "psnr": result.get("psnr"), "ssim": result.get("ssim"), "mse": result.get("mse"),
            "psnr_foreground": result.get("psnr_foreground"),
            "gaussians": result.get("gaussians"),
            "iterations": (splat or {}).get("params", {}).get("iterations"),
            "max_gaussians": (splat or {}).get("params", {}).get("max_gaussians"),
            "splat_seconds": _stage_seconds(splat),
            # Everything the row needed, from the scan: the shared stages plus its own training.
            "pipeline_seconds": (sum(s for s in seconds.values() if s) + (_stage_seconds(splat) or 0.0)) if splat else None,
        }
    return {"work": str(work), "setup": setup, "stage_seconds": seconds, "rows": rows}


def _cell(value, digits: int = 2) -> str:
    if value is None or value == "nan":
        return "–"
    if value == "inf":
        return "∞"
    if isinstance(value, float):
        return "∞" if math.isinf(value) else "–" if math.isnan(value) else f"{value:.{digits}f}"
    return str(value)


def comparison_markdown(records: list[dict]) -> str:
    lines = ["| work | row | method | volume | views × res | pts/cube | iterations | budget | PSNR ↑ | SSIM ↑ | PSNR fg | "
             "Gaussians | splat s | pipeline s |", "|" + "---|" * 14]
    for record in records:
        setup = record["setup"]
        for row, values in record["rows"].items():
            lines.append("| " + " | ".join([
                f"`{record['work']}`", f"`{row}`", _cell(values["method"]), _cell(setup["volume"]),
                f"{_cell(setup['views'])} × {_cell(setup['resolution'])}²", _cell(setup["points_per_cube"]),
                _cell(values["iterations"]), _cell(values["max_gaussians"]), _cell(values["psnr"]), _cell(values["ssim"], 4),
                _cell(values["psnr_foreground"]), _cell(values["gaussians"]), _cell(values["splat_seconds"], 0),
                _cell(values["pipeline_seconds"], 0)]) + " |")
    return "\n".join(lines)


def compare_works(works: list[Path], output: Path) -> str:
    """Write ``output/comparison.md`` and ``comparison.json``; return the markdown table."""
    records = [describe_work(work) for work in works]
    table = comparison_markdown(records)
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    header = ("# cubecloud comparison\n\nHeld-out scores (eval/metrics.json of each work directory) against the setup "
              "and wall time of each stage. `pipeline s`: preprocess + cunerf + export + that row's splat.\n\n")
    (output / "comparison.md").write_text(header + table + "\n")
    (output / "comparison.json").write_text(json.dumps(to_jsonable(records), indent=2, allow_nan=False) + "\n")
    return table
