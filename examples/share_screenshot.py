"""A picture of a shared page (`cubecloud share`) as a person sees it, opened from file:// in headless
Chromium: the README's picture of `cubecloud share`.

    cubecloud run -o work && cubecloud share work
    python examples/share_screenshot.py work/share/index.html docs/share.png --cut coronal --position 0.1 \\
        --measure 0.45,0.1,0.2 -0.45,0.1,0.2
    python examples/share_screenshot.py page/index.html shot.png --transfer bone    # a scalar scene

``--measure A B`` clicks the two world points (x,y,z in the cube [-1, 1]^3) with the ruler on, as
a person would; the page places each end where the ray under the click loses half its light.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import imageio.v3 as iio

from cubecloud_cli.share.page_browser import evaluate, settled_page
from cubecloud_cli.view.browser import Chromium


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("page", type=Path)
    parser.add_argument("output", type=Path)
    parser.add_argument("--size", default="900x700", help="window WIDTHxHEIGHT")
    parser.add_argument("--cut", choices=("none", "axial", "coronal", "sagittal"), default="none")
    parser.add_argument("--position", type=float, default=0.0, help="the cut's position in the cube, -1 … 1")
    parser.add_argument("--measure", nargs=2, metavar="X,Y,Z", help="two world points to measure between")
    parser.add_argument("--transfer", help="a transfer-function preset of a scalar scene's page")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    with Chromium((width, height)) as browser:
        browser.open(args.page.resolve().as_uri())
        settled_page(browser)
        if args.transfer:
            evaluate(browser, f"window.cubecloud.setTransfer({json.dumps({'preset': args.transfer})})")
        evaluate(browser, f"window.cubecloud.setCut({json.dumps(args.cut)}, {args.position})")
        if args.measure:
            evaluate(browser, "document.getElementById('measure').click()")
            for point in args.measure:
                x, y, _ = evaluate(browser, f"window.cubecloud.project([{point}])")
                for kind in ("mousePressed", "mouseReleased"):
                    browser.call("Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left", clickCount=1)
        image = settled_page(browser)
        print("ruler:", evaluate(browser, "document.getElementById('distance').textContent").strip() or "-")
    iio.imwrite(args.output, image)
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
