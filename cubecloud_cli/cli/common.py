"""What every command shares: error reporting, log printing, and the options several commands take."""

from __future__ import annotations

import functools
import logging
import signal
import sys
import threading
from pathlib import Path
from typing import Annotated, Callable, Literal, Optional, TypeVar

import typer

from cubecloud_cli.cli.options import build_settings, settings_option
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.core.runtime import DEVICES, Runtime
from cubecloud_cli.core.writes import describe, fix_for, is_write_failure
from cubecloud_cli.export.settings import ExportSettings
from cubecloud_cli.preprocess.settings import Fit, Interpolation, Modality, PreprocessSettings
from cubecloud_cli.presets import PRESET_NAMES
from cubecloud_cli.render.image_model_names import IMAGE_MODELS
from cubecloud_cli.sample_data import SAMPLE_CT_ATTRIBUTION, sample_ct_path
from cubecloud_cli.volume.intensity import CT_WINDOWS, WINDOW_NAMES

F = TypeVar("F", bound=Callable)
log = logging.getLogger("cubecloud")

EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130


class _TerminalFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        prefix = "warning: " if record.levelno >= logging.WARNING else ""
        return prefix + record.getMessage()


def configure_logging(quiet: bool = False) -> None:
    logger = logging.getLogger("cubecloud")
    logger.handlers.clear()
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_TerminalFormatter())
    logger.addHandler(handler)
    logger.setLevel(logging.WARNING if quiet else logging.INFO)
    logger.propagate = False


def reports_errors(command: F) -> F:
    """Turn a CubecloudError into one line on stderr and exit code 2, Ctrl-C into exit 130."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except CubecloudError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(EXIT_BAD_INPUT) from None
        except OSError as exc:  # a write the stage did not name itself (core/writes.py names most)
            typer.echo(f"error: {exc.filename or 'a file'}: {describe(exc)}: {fix_for(exc)}", err=True)
            raise typer.Exit(EXIT_BAD_INPUT) from None
        except MemoryError:
            typer.echo("error: out of memory: choose a smaller --size", err=True)
            raise typer.Exit(EXIT_BAD_INPUT) from None
        except RuntimeError as exc:
            if is_write_failure(exc):  # torch's writer, where no stage named the file
                typer.echo(f"error: a file could not be written ({describe(exc)}): {fix_for(exc)}", err=True)
                raise typer.Exit(EXIT_BAD_INPUT) from None
            if not is_out_of_memory(exc):
                raise
            typer.echo("error: out of memory (torch could not allocate): choose a smaller --size", err=True)
            raise typer.Exit(EXIT_BAD_INPUT) from None
        except KeyboardInterrupt as exc:
            # Stages that checkpoint say how to resume; the others leave nothing behind.
            message = str(exc) or "interrupted: no stage was marked complete; run the command again to redo it"
            typer.echo(message, err=True)
            raise typer.Exit(EXIT_INTERRUPTED) from None

    return wrapper  # type: ignore[return-value]


def is_out_of_memory(exc: BaseException) -> bool:
    """Whether torch's RuntimeError is an allocation that failed (the CPU's or a GPU's)."""
    text = str(exc)
    return "can't allocate memory" in text or "out of memory" in text.lower()


def parse_floats(text: str | None, count: int, option: str) -> tuple[float, ...] | None:
    """'0.5,0.5,2' -> (0.5, 0.5, 2.0), with a one-line error for anything else."""
    if text is None:
        return None
    parts = [p for p in text.replace("x", ",").replace("×", ",").split(",") if p.strip()]
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != count:
        example = ",".join(["1.0"] * count)
        raise CubecloudError(f"{option} {text!r} must be {count} numbers separated by commas, e.g. {example}")
    return values


PRESET_CHOICES = Literal[PRESET_NAMES]  # type: ignore[valid-type]
DEVICE_CHOICES = Literal[DEVICES]  # type: ignore[valid-type]

PresetOption = Annotated[
    PRESET_CHOICES,
    typer.Option(
        "--preset",
        help="Settings for every option left unset: fast and balanced for a 2-core CPU; detail for the scan's own "
        "resolution (a cube as fine as its finest voxel spacing, up to 512³, with views as large); paper for the "
        "paper's settings (meant for a GPU).",
    ),
]
ForceOption = Annotated[
    bool,
    typer.Option("--force", help="Replace what the command writes (a stage, a shared page) if it is already complete."),
]
ResumeOption = Annotated[bool, typer.Option("--resume", help="Continue an interrupted run from its last checkpoint.")]
WorkOption = Annotated[
    Path, typer.Option("--output", "-o", help="Work directory; each stage writes a folder inside it.")
]
QuietOption = Annotated[bool, typer.Option("--quiet", "-q", help="Print warnings and errors only.")]
DeviceOption = Annotated[Optional[DEVICE_CHOICES], settings_option(Runtime, "device")]
ThreadsOption = Annotated[Optional[int], settings_option(Runtime, "threads")]


def runtime_from_options(device: str | None, threads: int | None) -> Runtime:
    return build_settings(Runtime, None, {"device": device, "threads": threads})


# The scan options: `preprocess` and `run` take all of them (a test checks that they agree).
ScanArgument = Annotated[
    Optional[Path],
    typer.Argument(
        help="A NIfTI file (.nii/.nii.gz), a DICOM series folder, an NRRD file or a .npy array. "
        "Leave it out to use the bundled abdomen CT.",
        show_default=False,
    ),
]
_WINDOWS = ", ".join(f"{name} {width:g}/{level:g}" for name, (width, level) in CT_WINDOWS.items())
SizeOption = Annotated[Optional[int], settings_option(PreprocessSettings, "size")]
FitOption = Annotated[Optional[Fit], settings_option(PreprocessSettings, "fit")]
WindowOption = Annotated[
    Optional[Literal[WINDOW_NAMES]],  # type: ignore[valid-type]
    settings_option(PreprocessSettings, "window", extra=f"({_WINDOWS})"),
]
HuMinOption = Annotated[Optional[float], settings_option(PreprocessSettings, "hu_min")]
HuMaxOption = Annotated[Optional[float], settings_option(PreprocessSettings, "hu_max")]
ModalityOption = Annotated[Optional[Modality], settings_option(PreprocessSettings, "modality")]
PercentilesOption = Annotated[Optional[str], settings_option(PreprocessSettings, "percentiles")]
InterpolationOption = Annotated[Optional[Interpolation], settings_option(PreprocessSettings, "interpolation")]
SpacingOption = Annotated[Optional[str], settings_option(PreprocessSettings, "spacing")]
VolumeIndexOption = Annotated[Optional[int], settings_option(PreprocessSettings, "volume_index")]
SeriesOption = Annotated[Optional[str], settings_option(PreprocessSettings, "series")]


def preprocess_settings(preset: str, *, percentiles: str | None, spacing: str | None, **options) -> PreprocessSettings:
    """The settings the scan options ask for (the lists parsed), the preset filling what they leave unset."""
    parsed = {
        "percentiles": parse_floats(percentiles, 2, "--percentiles"),
        "spacing": parse_floats(spacing, 3, "--spacing"),
    }
    return build_settings(PreprocessSettings, preset, {**options, **parsed})


def scan_or_sample(scan: Optional[Path]) -> Path:
    if scan is not None:
        return scan
    log.info(f"no scan given: using the {SAMPLE_CT_ATTRIBUTION}")
    return sample_ct_path()


# The export options `run` takes too.
ViewsOption = Annotated[Optional[int], settings_option(ExportSettings, "views")]
ResolutionOption = Annotated[Optional[int], settings_option(ExportSettings, "resolution")]
ViewOption = Annotated[Optional[Literal[IMAGE_MODELS]], settings_option(ExportSettings, "view")]  # type: ignore[valid-type]


def stop_on_sigterm() -> None:
    """SIGTERM (what a scheduler sends) outside a training loop stops the command as Ctrl-C does: a
    KeyboardInterrupt, so the stage's partial folder is cleaned up and one line says what to run.
    Inside cunerf's and splat's loops it saves a checkpoint first (core/interrupts.py)."""
    if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        signal.signal(signal.SIGTERM, signal.default_int_handler)
