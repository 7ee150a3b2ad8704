"""`cubecloud eval --compare A B …`: one table across work directories (a preset sweep), from each
one's ``eval/metrics.json`` and stage manifests: what was run, how long each stage took, and the
held-out scores."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

from cubecloud_cli.core.artifacts import is_complete, read_manifest, to_jsonable
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.eval.stage import eval_is_current

STAGES = ("preprocess", "cunerf", "export")


def _stage_seconds(manifest: dict | None) -> float | None:
    return None if manifest is None else manifest.get("timings_s", {}).get("total")


def _load_metrics(work: Path) -> dict:
    metrics_file = work / "eval" / "metrics.json"
    if not eval_is_current(work) or not metrics_file.is_file():
        raise CubecloudError(
            f"{work}/eval is missing or older than its splat runs: run `cubecloud eval {work} --force`"
        )
    try:
        metrics = json.loads(metrics_file.read_text())
    except (OSError, ValueError) as exc:
        raise CubecloudError(
            f"{metrics_file} is unreadable ({type(exc).__name__}): run `cubecloud eval {work} --force`"
        ) from None
    results = metrics.get("results") if isinstance(metrics, dict) else None
    if not isinstance(results, dict) or not all(isinstance(r, dict) for r in results.values()):
        raise CubecloudError(
            f'{metrics_file} is not an eval result ({{"results": {{row: scores}}}}): '
            f"run `cubecloud eval {work} --force`"
        )
    return results


def describe_work(work: Path) -> dict:
    """The setup of a work directory and its eval results, as one comparable record."""
    work = Path(work)
    results = _load_metrics(work)
    manifests = {stage: read_manifest(work / stage) if is_complete(work / stage) else None for stage in STAGES}
    params = {stage: (m or {}).get("params", {}) for stage, m in manifests.items()}
    setup = {
        "volume": params["preprocess"].get("size"),
        "cunerf_iterations": params["cunerf"].get("iterations"),
        "views": params["export"].get("views"),
        "resolution": params["export"].get("resolution"),
        "image_model": params["export"].get("view"),
        "cameras": _camera_setup(params["export"]),
        "points_per_cube": params["export"].get("points_per_cube"),
        "max_points": params["export"].get("max_points"),
    }
    seconds = {stage: _stage_seconds(m) for stage, m in manifests.items()}
    upstream = sum(seconds.values()) if all(s is not None for s in seconds.values()) else None
    own_export = str((work / "export").resolve())
    rows = {}
    for row, result in results.items():
        splat = read_manifest(work / row) if row.startswith("splat") and is_complete(work / row) else None
        on_own_export = result.get("scene") == own_export
        splat_seconds = _stage_seconds(splat)
        rows[row] = {
            "method": result.get("method_name"),
            "scene": "this work's export" if on_own_export else result.get("scene"),
            "novel_psnr": result.get("novel_psnr"),
            "novel_ssim": result.get("novel_ssim"),
            "psnr": result.get("psnr"),
            "ssim": result.get("ssim"),
            "mse": result.get("mse"),
            "psnr_foreground": result.get("psnr_foreground"),
            "gaussians": result.get("gaussians"),
            "iterations": (splat or {}).get("params", {}).get("iterations"),
            "max_gaussians": (splat or {}).get("params", {}).get("max_gaussians"),
            "splat_seconds": splat_seconds,
            # From the scan to this row: the shared stages plus its own training (splat rows on
            # this work's export only; others came from elsewhere).
            "pipeline_seconds": upstream + splat_seconds
            if splat and on_own_export and upstream is not None and splat_seconds is not None
            else None,
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
    lines = [
        "| work | row | method | cameras | volume | views × res | pts/cube | iterations | budget | novel PSNR ↑ | "
        "novel SSIM ↑ | held-out PSNR ↑ | SSIM ↑ | PSNR fg | Gaussians | splat s | pipeline s |",
        "|" + "---|" * 17,
    ]
    for record in records:
        setup = record["setup"]
        for row, values in record["rows"].items():
            own = values["scene"] == "this work's export"
            lines.append(
                "| "
                + " | ".join(
                    [
                        f"`{record['work']}`",
                        f"`{row}`",
                        _cell(values["method"]),
                        _cell(setup["cameras"]) if own else "–",
                        _cell(setup["volume"]) if own else "other scene",
                        f"{_cell(setup['views'])} × {_cell(setup['resolution'])}²" if own else "–",
                        _cell(setup["points_per_cube"]) if own else "–",
                        _cell(values["iterations"]),
                        _cell(values["max_gaussians"]),
                        _cell(values.get("novel_psnr")),
                        _cell(values.get("novel_ssim"), 4),
                        _cell(values["psnr"]),
                        _cell(values["ssim"], 4),
                        _cell(values["psnr_foreground"]),
                        _cell(values["gaussians"]),
                        _cell(values["splat_seconds"], 0),
                        _cell(values["pipeline_seconds"], 0),
                    ]
                )
                + " |"
            )
    return "\n".join(lines)


def compare_works(works: list[Path], output: Path) -> str:
    """Write ``output/comparison.md`` and ``comparison.json``; return the markdown table."""
    records = [describe_work(work) for work in works]
    table = comparison_markdown(records)
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    header = (
        "# cubecloud comparison\n\nNovel-view (0.75–1.33×) and held-out scores (eval/metrics.json of each work "
        "directory) against the setup and wall time of each stage. `pipeline s`: preprocess + cunerf + export + "
        "that row's splat.\n\n"
    )
    _write_atomically(output / "comparison.md", header + table + "\n")
    _write_atomically(output / "comparison.json", json.dumps(to_jsonable(records), indent=2, allow_nan=False) + "\n")
    return table


def _write_atomically(path: Path, text: str) -> None:
    temporary = path.with_name(f".{path.name}.partial")
    temporary.write_text(text)
    os.replace(temporary, path)


def _camera_setup(export_params: dict) -> str | None:
    if not export_params:
        return None
    cameras = export_params.get("cameras", "orbit")
    if cameras == "stack":
        return f"one-pose stack of slices across {export_params.get('axis')}"
    if cameras == "sphere":
        return f"sphere, {export_params.get('axis')} up"
    return f"orbit about {export_params.get('axis')}"
