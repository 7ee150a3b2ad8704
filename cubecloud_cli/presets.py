"""Preset values per stage (docs/design.md §6). An option given on the command line wins, then
the preset's value, then the settings class's default; a settings field the presets set takes
its default from the default preset (:func:`preset_default`), so each value is written here only.

``paper`` is the paper's setting; ``fast`` and ``balanced`` are for a 2-core CPU. The preprocess
sizes follow the scans: the bundled 3 mm abdomen CT is 366 mm across, so 128³ (2.9 mm voxels)
keeps its full resolution. ``balanced`` is sized for scans finer than that (192³: 1.5 mm voxels
over a 300 mm field of view) and chosen to finish the bundled CT in well under 45 minutes on 2
cores; README "Presets" gives the measured stage times.
"""

from __future__ import annotations

from typing import Any, Mapping

PRESET_NAMES = ("fast", "balanced", "detail", "paper")
DEFAULT_PRESET = "fast"

PRESETS: dict[str, dict[str, dict[str, Any]]] = {
    "preprocess": {
        "fast": {"size": 128, "fit": "pad", "window": "abdomen", "interpolation": "linear"},
        "balanced": {"size": 192, "fit": "pad", "window": "abdomen", "interpolation": "linear"},
        # detail: the scan's own resolution (volume/cube_frame.size_for_scan), up to 512³.
        "detail": {"size": "scan", "fit": "pad", "window": "abdomen", "interpolation": "linear"},
        # The paper resized every CT to 512³ with nearest neighbour and min-max scaled it
        # (docs/cunerf.md §3.4-3.5).
        "paper": {"size": 512, "fit": "stretch", "window": "full", "interpolation": "nearest"},
    },
    # export: images as large as the volume is wide, 60 views as in the paper. The paper renders
    # CuNeRF slices on an orbit about the sagittal (ap) axis; the CPU presets render volume
    # images (dvr) from cameras spread over the whole sphere, since a scene is looked at from
    # every side (a ring loses up to 11 dB off its plane), with the long (si) axis up. The
    # paper states no point budget nor points per cube.
    "export": {
        "fast": {
            "resolution": 128,
            "cameras": "sphere",
            "views": 120,
            "axis": "si",
            "view": "dvr",
            "points_per_cube": 512,
            "max_points": 100_000,
        },
        "balanced": {
            "resolution": 192,
            "cameras": "sphere",
            "views": 60,
            "axis": "si",
            "view": "dvr",
            "points_per_cube": 512,
            "max_points": 150_000,
        },
        # detail: views as large as the volume is wide, up to 512² (ExportSettings.for_volume).
        "detail": {
            "resolution": "volume",
            "cameras": "sphere",
            "views": 60,
            "axis": "si",
            "view": "dvr",
            "points_per_cube": 512,
            "max_points": 200_000,
        },
        "paper": {
            "resolution": 512,
            "cameras": "orbit",
            "views": 60,
            "axis": "ap",
            "view": "slice",
            "points_per_cube": 64,
            "max_points": 0,
        },
    },
    # splat: the paper trains 30 000 iterations (the reference's length) on a GPU; the CPU
    # presets train shorter, with the reference schedule scaled to their length. The paper's
    # 3DGS is plain; the CPU presets anti-alias (Mip-Splatting), so a zoomed view holds. fast's
    # budget: 75k Gaussians kept the bundled CT's novel-view score (46.44 against 46.34 dB as
    # grown to 90k) and trained in 52 s instead of 80; 60k lost 0.16 dB more (docs/results.md, "Model only what the scene requires").
    # fast trains 1500 iterations on 120 views: more views of the scene generalise better than
    # more passes over fewer (novel PSNR 46.55 / 45.64 dB against 46.39 / 45.38 for 2000 on 60,
    # seeds 46.51–46.61), in three quarters of the time; docs/history/pipeline-speed.md, "Views for iterations".
    "splat": {
        "fast": {"iterations": 1500, "max_gaussians": 75_000, "antialias": True},
        "balanced": {"iterations": 7000, "max_gaussians": 300_000, "antialias": True},
        # detail: on the chest CT at 256³, 2000 / 1500 / 1000 iterations scored 44.89 / 44.43 / 43.39 dB
        # novel (foreground 38.48 / 38.03 / 36.99); 1500 runs the 512³ chest CT in 16–17 of its 20 minutes.
        "detail": {"iterations": 1500, "max_gaussians": 200_000, "antialias": True},
        "paper": {"iterations": 30_000, "max_gaussians": None, "antialias": False},
    },
}

# cunerf presets hold one column per model, so `--model cunerf --preset fast` gets settings
# meant for the MLP rather than the grid's learning rate. See docs/results.md, "Speed of each stage", for the figures.
# `fast` trains no iteration: its grid is solved to render the training voxels exactly
# (--grid-init volume, cunerf/grid_init.py), which beats 3000 iterations from random features on
# every measure of the field (3D PSNR 42.3 against 32.7 dB, held-out slices 30.3 against 29.1 dB,
# renders against the volume's 58.1 against 52.2 dB) in 8 s instead of 79, and the splats trained
# on its renders score as before (docs/history/cunerf-start.md). `balanced` and `detail` start
# there too (docs/results.md, "Presets"); `paper` trains its MLP from random weights. Measured earlier on the bundled CT at 128³ (bench/cunerf.py):
# 2³ points per cube for 4000 iterations beat 3³ for 2000 in the same time (37.3 vs 35.4 dB 3D
# PSNR); a batch of 2048 cubes costs the splats 0.07 dB against 4096 (docs/history/cunerf-speed.md "The
# CuNeRF batch").
_GRID = {
    "lr": 0.05,
    "lr_final": 5e-4,
    "warmup": 100,
    "cube_radius": 0.5,
    "samples_per_axis": 2,
    "importance": 0,
    "grid_init": "random",
}
# The paper's network and schedule (docs/cunerf.md §8); CPU presets cut the batch and samples.
_MLP = {"lr": 2e-3, "lr_final": 2e-5, "cube_radius": 1.0, "grid_init": "random"}
# The paper's network on a CPU budget, for --model cunerf with balanced or detail.
_MLP_CPU_LONG = {
    **_MLP,
    "warmup": 1000,
    "iterations": 10000,
    "batch_size": 1024,
    "samples_per_axis": 4,
    "importance": 64,
    "val_every": 1000,
    "checkpoint_every": 250,
}
# The fitted start with the large batch its held-out validation renders in.
_GRID_FITTED_LARGE = {
    **_GRID,
    "grid_init": "volume",
    "iterations": 0,
    "batch_size": 8192,
    "val_every": 1000,
    "checkpoint_every": 500,
}
CUNERF_DEFAULT_MODEL = {"fast": "fast", "balanced": "fast", "detail": "fast", "paper": "cunerf"}
CUNERF_PRESETS: dict[str, dict[str, dict[str, Any]]] = {
    "fast": {
        "fast": {
            **_GRID,
            "grid_init": "volume",
            "iterations": 0,
            "batch_size": 2048,
            "val_every": 1000,
            "checkpoint_every": 500,
        },
        "cunerf": {
            **_MLP,
            "warmup": 100,
            "iterations": 2000,
            "batch_size": 512,
            "samples_per_axis": 3,
            "importance": 32,
            "val_every": 500,
            "checkpoint_every": 100,
        },
    },
    # balanced and detail: the fitted start, as fast (its grid has one vertex per voxel at any size).
    "balanced": {"fast": _GRID_FITTED_LARGE, "cunerf": _MLP_CPU_LONG},
    "detail": {"fast": _GRID_FITTED_LARGE, "cunerf": _MLP_CPU_LONG},
    "paper": {
        "fast": {**_GRID, "iterations": 20000, "batch_size": 8192, "val_every": 2000, "checkpoint_every": 1000},
        "cunerf": {
            **_MLP,
            "warmup": 1000,
            "iterations": 200000,
            "batch_size": 1024,
            "samples_per_axis": 4,
            "importance": 64,
            "val_every": 10000,
            "checkpoint_every": 10000,
        },
    },
}


def resolve_cunerf(preset: str, model: str | None, overrides: Mapping[str, Any]) -> dict[str, Any]:
    """The cunerf preset's values for the chosen model (the preset's own by default), with every
    non-None override applied."""
    if preset not in PRESET_NAMES:
        raise ValueError(f"unknown preset {preset!r}")
    model = model or CUNERF_DEFAULT_MODEL[preset]
    if model not in CUNERF_PRESETS[preset]:
        raise ValueError(f"unknown model {model!r}")
    values = {"model": model, **CUNERF_PRESETS[preset][model]}
    values.update({key: value for key, value in overrides.items() if value is not None and key != "model"})
    return values


# `run --scalar`: the export's set of transfer functions and the scalar scene's training, over
# the preset's values. Measured at fast only (docs/results.md, "Scalar scenes"): 41 members at
# one view in 6 covered the transfer functions held out as 721 at one view each did; 50,000
# Gaussians generalised better than 75,000; 4500 iterations gained 0.3-1.3 dB over 3000 in the
# time 3000 took before the scan was read by a kernel. Chord lengths (the default) cost about 4 ms
# a step; a 3D filter of 0.01 px² (the values are held to the scan, which knows detail finer than a
# training pixel) another 12-16 %: 4300 iterations keep the pipeline within 2x one baked one
# (3500 until the export marched a view's transfer functions together, 7 s sooner; 3700 until the
# scalar appearance became one numba pass, 15 % off each step).
SCALAR_RUN: dict[str, dict[str, dict[str, Any]]] = {
    "fast": {
        "export": {"transfer_set": 41, "transfer_stride": 6},
        "splat": {"scalar": True, "iterations": 4300, "max_gaussians": 50_000, "filter_scale": 0.01, "rmse_share": 0.5},
    },
}


def scalar_run_note() -> str:
    """What ``run --scalar`` sets, for its --help."""
    return (
        " ".join(
            f"{preset}: --transfer-set {run['export']['transfer_set']} --transfer-stride {run['export']['transfer_stride']}, "
            f"{run['splat']['iterations']} splat iterations, at most {run['splat']['max_gaussians']:,} Gaussians, "
            f"--filter-scale {run['splat']['filter_scale']:g}, --rmse-share {run['splat']['rmse_share']:g}."
            for preset, run in SCALAR_RUN.items()
        )
        + f" ({', '.join(SCALAR_RUN)} only: the settings were measured there.)"
    )


def resolve_scalar_run(preset: str, stage: str, overrides: Mapping[str, Any]) -> dict[str, Any]:
    """``run --scalar``'s options for ``stage`` (export or splat): those given, then the scalar
    run's, as overrides of the preset's."""
    if preset not in SCALAR_RUN:
        raise ValueError(
            f"run --scalar has settings measured for the {', '.join(SCALAR_RUN)} preset only, not {preset!r}"
        )
    chosen = dict(SCALAR_RUN[preset][stage])
    chosen.update({key: value for key, value in overrides.items() if value is not None})
    return chosen


# The paper's 3DGS baseline looks at sagittal slices, whatever the preset's orbit axis.
STACK_AXIS = "lr"


def resolve(stage: str, preset: str, overrides: Mapping[str, Any]) -> dict[str, Any]:
    """The preset's values for ``stage`` with every non-None override applied."""
    if stage == "cunerf":
        return resolve_cunerf(preset, overrides.get("model"), overrides)
    if preset not in PRESET_NAMES:
        raise ValueError(f"unknown preset {preset!r}")
    values = dict(PRESETS[stage][preset])
    if stage == "export" and overrides.get("cameras") == "stack" and overrides.get("axis") is None:
        values["axis"] = STACK_AXIS
    values.update({key: value for key, value in overrides.items() if value is not None})
    return values


def preset_default(stage: str, key: str) -> Any:
    """The default preset's value of one option: the default of its settings field."""
    return _columns(stage)[DEFAULT_PRESET][key]


def _columns(stage: str) -> dict[str, dict[str, Any]]:
    """Each preset's values for ``stage`` (cunerf: the preset's own model)."""
    if stage == "cunerf":
        return {
            name: {"model": CUNERF_DEFAULT_MODEL[name], **CUNERF_PRESETS[name][CUNERF_DEFAULT_MODEL[name]]}
            for name in PRESET_NAMES
        }
    return PRESETS[stage]


def is_preset_key(stage: str, key: str) -> bool:
    return any(key in column for column in _columns(stage).values())


def preset_note(stage: str, key: str) -> str:
    """The presets' values of one option for --help, e.g. "(preset: fast 128, balanced 192, paper 512)";
    for cunerf, also the values the other model gets with --model."""
    table = _columns(stage)
    note = "(preset: " + ", ".join(f"{name} {shown(key, table[name][key])}" for name in PRESET_NAMES)
    if stage == "cunerf" and key != "model":
        others = [
            (name, model, values[key])
            for name in PRESET_NAMES
            for model, values in CUNERF_PRESETS[name].items()
            if model != CUNERF_DEFAULT_MODEL[name] and key in values
        ]
        by_model: dict[str, list[str]] = {}
        for name, model, value in others:
            by_model.setdefault(model, []).append(f"{name} {shown(key, value)}")
        note += "".join(f"; with --model {model}: {', '.join(values)}" for model, values in by_model.items())
    return note + ")"


def shown(key: str, value: Any) -> str:
    """A value as --help shows it."""
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, tuple):
        return ",".join(f"{v:g}" if isinstance(v, float) else str(v) for v in value)
    # A budget of None or 0 means no budget.
    return "none" if value is None or (value == 0 and key.startswith("max_")) else str(value)
