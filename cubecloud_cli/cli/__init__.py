"""The `cubecloud` command: parses options and calls the stage functions, nothing more."""

from __future__ import annotations

from typing import Annotated, Optional

import typer

from cubecloud_cli import __version__
from cubecloud_cli.cli.cohort import cohort_command
from cubecloud_cli.cli.common import stop_on_sigterm
from cubecloud_cli.cli.cunerf import cunerf_command
from cubecloud_cli.cli.eval import eval_command
from cubecloud_cli.cli.export import export_command
from cubecloud_cli.cli.preprocess import preprocess_command
from cubecloud_cli.cli.run import run_command
from cubecloud_cli.cli.share import share_command
from cubecloud_cli.cli.splat import splat_command
from cubecloud_cli.cli.view import view_command

app = typer.Typer(
    name="cubecloud",
    help=(
        "Turn a CT scan into a 3D Gaussian Splatting scene (Cube-Cloud 3DGS).\n\n"
        "Each command reads and writes one stage folder in a work directory "
        "(WORK/preprocess, ...); `run` does them all.\n\n"
        "Quick start:  cubecloud run -o work   (uses the bundled abdomen CT)"
    ),
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)


def _print_version(value: bool) -> None:
    if value:
        typer.echo(f"cubecloud {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        Optional[bool],
        typer.Option("--version", callback=_print_version, is_eager=True, help="Print the version and exit."),
    ] = None,
) -> None:
    pass


app.command("preprocess")(preprocess_command)
app.command("cunerf")(cunerf_command)
app.command("export")(export_command)
app.command("splat")(splat_command)
app.command("eval")(eval_command)
app.command("run")(run_command)
app.command("view")(view_command)
app.command("share")(share_command)
app.command("cohort")(cohort_command)


def main() -> None:
    stop_on_sigterm()
    app()
