"""A picture of `cubecloud view` as the browser draws it, optionally cut by the clipping plane.

python examples/view_screenshot.py work docs/view.png
python examples/view_screenshot.py work docs/view_cut.png --cut sagittal --position 0
"""

from __future__ import annotations

import argparse
import socket
import time
from pathlib import Path

from cubecloud_cli.view.browser import screenshot
from cubecloud_cli.view.server import CLIP_CHOICES, SceneViewer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("work", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--run", default=None)
    parser.add_argument("--cut", choices=CLIP_CHOICES, default="off")
    parser.add_argument("--position", type=float, default=0.0)
    args = parser.parse_args()
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    viewer = SceneViewer(args.work, port=port, run=args.run)
    try:
        viewer.set_clip(args.cut, args.position)
        started = time.perf_counter()
        screenshot(viewer.url, args.out)
        print(f"wrote {args.out}: {viewer.visible_count()} of {len(viewer.splats)} Gaussians drawn, "
              f"page shot in {time.perf_counter() - started:.1f} s")  # fmt: skip
    finally:
        viewer.stop()


if __name__ == "__main__":
    main()
