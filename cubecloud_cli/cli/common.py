"""What every command shares: error reporting, log printing, option parsers and option types."""

from __future__ import annotations

import functools
import logging
import sys
from enum import Enum
from pathlib import Path
from typing import Annotated, Callable, Optional, TypeVar

import typer

from cubecloud_cli.errors import CubecloudError
from cubecloud_cli.presets import DEFAULT_PRESET

F = TypeVar("F", bound=Callable)

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
        except MemoryError:
            typer.echo("error: out of memory: choose a smaller --size", err=True)
            raise typer.Exit(EXIT_BAD_INPUT) from None
        except KeyboardInterrupt as exc:
            # Stages that checkpoint say how to resume; the others leave nothing behind.
            message = str(exc) or "interrupted: no stage was marked complete; run the command again to redo it"
            typer.echo(message, err=True)
            raise typer.Exit(EXIT_INTERRUPTED) from None

    return wrapper  # type: ignore[return-value]


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


def unset_option(flag: str, help_text: str):
    """An option whose default (None) means "the preset's value": no default is shown, the
    help text names the presets' values instead."""
    return typer.Option(flag, help=help_text, show_default=False)


class Preset(str, Enum):
    fast = "fast"
    balanced = "balanced"
    paper = "paper"


PresetOption = Annotated[
    Preset,
    typer.Option(
        "--preset",
        help="Settings for every option left unset: fast and balanced for a 2-core CPU, paper "
        "for the paper's settings (meant for a GPU).",
    ),
]
ForceOption = Annotated[bool, typer.Option("--force", help="Replace the stage if it is already complete.")]
WorkOption = Annotated[
    Path, typer.Option("--output", "-o", help="Work directory; each stage writes a folder inside it.")
]
QuietOption = Annotated[bool, typer.Option("--quiet", "-q", help="Print warnings and errors only.")]
DEFAULT_PRESET_VALUE = Preset(DEFAULT_PRESET)

ScanArgument = Annotated[
    Optional[Path],
    typer.Argument(
        help="A NIfTI file (.nii/.nii.gz), a DICOM series folder, an NRRD file or a .npy array. "
        "Leave it out to use the bundled abdomen CT.",
        show_default=False,
    ),
]
