"""`cubecloud view`: serve a work directory's trained scene to the browser."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Annotated, Optional

import typer

from cubecloud_cli.cli.common import QuietOption, configure_logging, reports_errors

log = logging.getLogger("cubecloud")

LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1")

WorkArgument = Annotated[Path, typer.Argument(help="Work directory with a finished splat run.")]
RunOption = Annotated[
    Optional[str],
    typer.Option(
        "--run", help="The run shown first (splat, splat-random, splat-NAME); default: splat.", show_default=False
    ),
]
PortOption = Annotated[int, typer.Option("--port", help="Port to serve on.")]
HostOption = Annotated[
    str,
    typer.Option(
        "--host", help="Address to listen on; anything but 127.0.0.1 lets others on that network see the scan."
    ),
]

DetailOption = Annotated[
    float,
    typer.Option(
        "--detail",
        help="Percent of the Gaussians drawn at first, those that shape the picture most first (the page has a slider). "
        "A browser without a GPU draws a frame of 100k Gaussians in about 2 s on two cores; 10 draws a tenth of them.",
    ),
]


@reports_errors
def view_command(
    work: WorkArgument = Path("work"),
    run: RunOption = None,
    port: PortOption = 8080,
    host: HostOption = "127.0.0.1",
    detail: DetailOption = 100.0,
    quiet: QuietOption = False,
) -> None:
    """Explore the trained Gaussians in the browser: turn, zoom, and cut into the body.

    Serves the scene with viser (WebGL in the browser, so no GPU is needed here). The page has a selector between the splat runs; a clipping plane (axial, coronal, sagittal or the current view direction) with a position slider; the preprocessed volume's axial, coronal and sagittal slices as planes in the same frame, each with a toggle and a slider, to check that the splat and the scan line up; toggles for the Cube-Cloud points and the export's cameras (click one to look through it); patient-axis labels; and the export's first view, to which "Reset view" returns. Ctrl-C stops the server.

    Examples:

      cubecloud view work                  # then open http://127.0.0.1:8080

      cubecloud view work --run splat-random --port 8090

      cubecloud view work --detail 10      # a browser without a GPU stays responsive
    """
    from cubecloud_cli.view.listening import check_address
    from cubecloud_cli.view.server import SceneViewer

    configure_logging(quiet)
    check_address(host, port)
    if host not in LOCAL_HOSTS:
        log.warning(f"listening on {host}: anyone who can reach this machine on port {port} can see the scan")
    viewer = SceneViewer(work, host=host, port=port, run=run, detail=detail)
    try:  # from the first line that invites Ctrl-C on, Ctrl-C (or SIGTERM) stops the viewer cleanly
        log.info(f"viewing {len(viewer.runs)} run(s) of {work} at {viewer.url} (Ctrl-C stops)")
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        log.info("viewer stopped")
    finally:
        viewer.stop()
