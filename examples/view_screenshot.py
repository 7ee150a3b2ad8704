"""A picture of `cubecloud view` as the browser draws it: cut by the clipping plane, with slices of
the scan, the Cube-Cloud points or the export's cameras, as the page's controls would set them.

python examples/view_screenshot.py work docs/view.png
python examples/view_screenshot.py work docs/view_cut.png --cut coronal --position 0
python examples/view_screenshot.py work docs/view_slices.png --cut coronal --slice axial:70 --slice sagittal
python examples/view_screenshot.py work points.png --no-gaussians --points
"""

from __future__ import annotations

import argparse
import socket
import time
from pathlib import Path

from cubecloud_cli.view.browser import screenshot
from cubecloud_cli.view.layers import SLICE_AXES
from cubecloud_cli.view.server import CLIP_CHOICES, SceneViewer


def slice_choice(text: str) -> tuple[str, int | None]:
    axis, _, index = text.partition(":")
    if axis not in SLICE_AXES:
        raise argparse.ArgumentTypeError(f"{axis!r} is not one of {', '.join(SLICE_AXES)}")
    return axis, int(index) if index else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("work", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--run", default=None)
    parser.add_argument("--cut", choices=CLIP_CHOICES, default="off")
    parser.add_argument("--position", type=float, default=0.0)
    parser.add_argument("--keep-other-side", action="store_true")
    parser.add_argument("--slice", type=slice_choice, action="append", default=[], metavar="AXIS[:INDEX]",
                        help="show a slice of the scan (default index: the middle); repeatable")  # fmt: skip
    parser.add_argument("--opacity", type=float, default=1.0, help="of the slices")
    parser.add_argument("--no-gaussians", action="store_true")
    parser.add_argument("--points", action="store_true", help="show the Cube-Cloud points")
    parser.add_argument("--cameras", action="store_true", help="show the export's cameras")
    args = parser.parse_args()
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    viewer = SceneViewer(args.work, port=port, run=args.run)
    try:
        viewer.set_clip(args.cut, args.position, "above" if args.keep_other_side else "below")
        for axis, index in args.slice:
            viewer.show_slice(axis, index, visible=True)
        viewer.set_slice_opacity(args.opacity)
        viewer.show_splats(not args.no_gaussians)
        viewer.show_points(args.points)
        viewer.show_cameras(args.cameras)
        started = time.perf_counter()
        screenshot(viewer.url, args.out, ready=lambda image: viewer.browsers_at_home())
        print(f"wrote {args.out}: {viewer.visible_count()} of {len(viewer.splats)} Gaussians drawn, "
              f"page shot in {time.perf_counter() - started:.1f} s")  # fmt: skip
    finally:
        viewer.stop()


if __name__ == "__main__":
    main()
