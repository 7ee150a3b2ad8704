"""`cubecloud share`: a finished scene as one page that any browser opens, and its SPZ file."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated, Optional

import typer

from cubecloud_cli.cli.common import ForceOption, QuietOption, configure_logging, reports_errors

log = logging.getLogger("cubecloud")

WorkArgument = Annotated[Path, typer.Argument(help="Work directory with a finished splat run.")]
RunOption = Annotated[
    Optional[str],
    typer.Option(
        "--run", help="The run to share (splat, splat-random, splat-NAME); default: splat.", show_default=False
    ),
]
OutputOption = Annotated[
    Optional[Path],
    typer.Option("--output", "-o", help="Folder to write; default: WORK/share.", show_default=False),
]


@reports_errors
def share_command(
    work: WorkArgument = Path("work"),
    run: RunOption = None,
    output: OutputOption = None,
    force: ForceOption = False,
    quiet: QuietOption = False,
) -> None:
    """Write the trained scene as one self-contained web page, to send to someone.

    OUT/index.html holds the viewer (Spark on three.js, bundled with the package), the scene as SPZ and its patient frame: it opens from a double click with no server and no network, in any browser with WebGL2. It opens on the export's first view with the patient's directions labelled, and has an axial, coronal or sagittal cut with a slider, a ruler (click two points for their distance in millimetres, through the scan's voxel-to-scanner map), "Reset view", and marks a scene trained anti-aliased. OUT/scene.spz is the same Gaussians for other splat viewers, in cubecloud's world frame. Nothing from the scan's header goes into the page.

    Examples:

      cubecloud share work                     # writes work/share/index.html

      cubecloud share work --run splat-random -o random_page --force
    """
    from cubecloud_cli.share.shared_scene import PAGE_FILE, share_scene

    configure_logging(quiet)
    out = output if output is not None else Path(work) / "share"
    shared = share_scene(work, run, out, force=force)
    log.info(
        f"wrote {out / PAGE_FILE} ({shared.page_bytes / 1e6:.2f} MB): {shared.gaussians:,} Gaussians, "
        f"{shared.spz_bytes / max(shared.gaussians, 1):.1f} bytes each as SPZ; open it in a browser"
    )
