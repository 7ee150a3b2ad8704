"""`cubecloud preprocess`: options and the call into cubecloud_cli.preprocess."""

from __future__ import annotations

import inspect
import logging
from enum import Enum
from pathlib import Path
from typing import Annotated, Callable, Optional, Sequence

import typer

from cubecloud_cli.cli.common import (
    DEFAULT_PRESET_VALUE,
    ForceOption,
    PresetOption,
    QuietOption,
    ScanArgument,
    WorkOption,
    configure_logging,
    parse_floats,
    reports_errors,
)
from cubecloud_cli.preprocess import PreprocessSettings, preprocess_scan
from cubecloud_cli.cli.progress import stage_progress
from cubecloud_cli.presets import preset_note, resolve
from cubecloud_cli.sample_data import SAMPLE_CT_ATTRIBUTION, sample_ct_path
from cubecloud_cli.volume.intensity import WINDOW_NAMES

log = logging.getLogger("cubecloud")

Window = Enum("Window", {name.replace("-", "_"): name for name in WINDOW_NAMES}, type=str)  # type: ignore[misc]


class Fit(str, Enum):
    pad = "pad"
    stretch = "stretch"


class Modality(str, Enum):
    auto = "auto"
    ct = "ct"
    mr = "mr"


class Interpolation(str, Enum):
    linear = "linear"
    nearest = "nearest"


SizeOption = Annotated[Optional[int], typer.Option("--size", help=f"Cube side S in voxels (paper: 512). {preset_note('preprocess', 'size')}", show_default=False)]
FitOption = Annotated[Optional[Fit], typer.Option("--fit", help="pad: keep the physical aspect ratio, pad with air. stretch: resize each axis to S (the paper). (preset: pad; paper stretch)", show_default=False)]
WindowOption = Annotated[Optional[Window], typer.Option("--window", help="CT window, W/L in HU: abdomen 400/40, soft-tissue 350/50, liver 150/90, lung 1500/-600, bone 2500/480, brain 80/40; full = the scan's min..max (the paper). (preset: abdomen; paper full)", show_default=False)]  # type: ignore[valid-type]
HuMinOption = Annotated[Optional[float], typer.Option("--hu-min", help="Lower end of a custom HU window (with --hu-max); replaces --window.", show_default=False)]
HuMaxOption = Annotated[Optional[float], typer.Option("--hu-max", help="Upper end of a custom HU window (with --hu-min).", show_default=False)]
ModalityOption = Annotated[Modality, typer.Option("--modality", help="ct, mr, or auto: the DICOM header, else CT when values reach -500 HU (air).")]
PercentilesOption = Annotated[str, typer.Option("--percentiles", help="MR only: the LOW,HIGH percentiles mapped to 0 and 1.")]
InterpolationOption = Annotated[Optional[Interpolation], typer.Option("--interpolation", help="linear (anti-aliased when shrinking) or nearest (the paper's resize). (preset: linear; paper nearest)", show_default=False)]
SpacingOption = Annotated[Optional[str], typer.Option("--spacing", help="Voxel size X,Y,Z in mm: required for .npy (axes in RAS order), overrides a wrong header otherwise.", show_default=False)]
VolumeIndexOption = Annotated[Optional[int], typer.Option("--volume-index", help="Which volume of a 4D file to use (0-based).", show_default=False)]


def settings_from_options(
    preset: str,
    size: Optional[int],
    fit: Optional[Fit],
    window,
    hu_min: Optional[float],
    hu_max: Optional[float],
    modality: Modality,
    percentiles: str,
    interpolation: Optional[Interpolation],
    spacing: Optional[str],
    volume_index: Optional[int],
) -> PreprocessSettings:
    values = resolve(
        "preprocess",
        preset,
        {
            "size": size,
            "fit": fit.value if fit else None,
            "window": window.value if window else None,
            "interpolation": interpolation.value if interpolation else None,
        },
    )
    return PreprocessSettings(
        size=values["size"],
        fit=values["fit"],
        window=values["window"],
        hu_min=hu_min,
        hu_max=hu_max,
        modality=modality.value,
        percentiles=parse_floats(percentiles, 2, "--percentiles"),  # type: ignore[arg-type]
        interpolation=values["interpolation"],
        spacing=parse_floats(spacing, 3, "--spacing"),  # type: ignore[arg-type]
        volume_index=volume_index,
    )


def scan_or_sample(scan: Optional[Path]) -> Path:
    if scan is not None:
        return scan
    path = sample_ct_path()
    log.info(f"no scan given: using the {SAMPLE_CT_ATTRIBUTION}")
    return path


def describe_result(manifest: dict, work: Path) -> str:
    geometry = manifest["geometry"]
    size = geometry["size"]
    voxel = "×".join(f"{v:.3g}" for v in geometry["voxel_size_mm"])
    return (
        f"wrote {work / 'preprocess'}: {size}³ volume, {voxel} mm voxels, "
        f"{manifest['intensity']['method']}, {manifest['timings_s']['total']:.1f} s"
    )


ScanAction = Callable[[Path, Path, PreprocessSettings, bool, str, dict], None]


def _scan_options(
    scan: ScanArgument = None,
    output: WorkOption = Path("work"),
    preset: PresetOption = DEFAULT_PRESET_VALUE,
    size: SizeOption = None,
    fit: FitOption = None,
    window: WindowOption = None,
    hu_min: HuMinOption = None,
    hu_max: HuMaxOption = None,
    modality: ModalityOption = Modality.auto,
    percentiles: PercentilesOption = "0.5,99.5",
    interpolation: InterpolationOption = None,
    spacing: SpacingOption = None,
    volume_index: VolumeIndexOption = None,
    force: ForceOption = False,
    quiet: QuietOption = False,
) -> None:
    """The options every scan-taking command shares (only its signature is used)."""


def scan_command(
    action: ScanAction, help_text: str, extra: Sequence[inspect.Parameter] = ()
) -> Callable[..., None]:
    """A command taking a scan and every preprocess option, handing the settings to ``action``.

    `preprocess` and `run` share this one signature, so their options cannot drift apart;
    ``extra`` parameters (typer options) are appended and reach ``action`` as a dict.
    """
    shared = list(inspect.signature(_scan_options, eval_str=True).parameters.values())
    extra_names = [parameter.name for parameter in extra]

    @reports_errors
    def command(**options) -> None:
        configure_logging(options["quiet"])
        extras = {name: options[name] for name in extra_names}
        preset = options["preset"].value
        settings = settings_from_options(
            preset, options["size"], options["fit"], options["window"], options["hu_min"], options["hu_max"],
            options["modality"], options["percentiles"], options["interpolation"], options["spacing"],
            options["volume_index"],
        )
        action(scan_or_sample(options["scan"]), options["output"], settings, options["force"], preset, extras)

    # Typer reads the signature: the shared options first, then the command's own.
    command.__signature__ = inspect.Signature(shared + list(extra))  # type: ignore[attr-defined]
    command.__doc__ = help_text
    return command


def _preprocess(scan: Path, output: Path, settings: PreprocessSettings, force: bool, preset: str, extras: dict) -> None:
    manifest = run_preprocess_with_progress(scan, output, settings, force)
    log.info(describe_result(manifest, output))


preprocess_command = scan_command(
    _preprocess,
    """Normalize a CT or MR scan into the cube volume every later stage reads.

    Reorients to RAS+, clips to an intensity window, maps it to [0, 1] and resamples to an isotropic S³ cube. Writes WORK/preprocess/: volume.npy (float32), volume.nii.gz (lies over the original scan in 3D Slicer or ITK-SNAP), preview.png and manifest.json.

    Examples:

      cubecloud preprocess -o work                      # the bundled abdomen CT

      cubecloud preprocess scan.nii.gz -o work --size 256 --window bone

      cubecloud preprocess dicom_folder/ -o work --hu-min -1000 --hu-max 1000

      cubecloud preprocess array.npy -o work --spacing 0.7,0.7,2.5
    """,
)


def run_preprocess_with_progress(scan: Path, output: Path, settings: PreprocessSettings, force: bool) -> dict:
    """The stage with a bar on the terminal, each phase weighted by its expected cost."""
    with stage_progress("preprocess", unit=None) as on_progress:
        return preprocess_scan(scan, output, settings, force=force, on_progress=on_progress)
