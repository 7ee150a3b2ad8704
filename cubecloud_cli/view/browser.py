"""A screenshot of the viewer as a person sees it: headless Chromium with software WebGL (used
by the tests and by examples/view_screenshot.py)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path
from typing import Callable

import numpy as np

from cubecloud_cli.errors import CubecloudError


def chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


def screenshot(
    url: str,
    path: Path,
    size: tuple[int, int] = (900, 700),
    attempts: int = 4,
    ready: Callable[[np.ndarray], bool] = lambda image: True,
) -> np.ndarray:
    """The page once the scene has arrived, as an (H, W, 3) array also written to ``path``. Until the
    viewer's black background is in, the page shows its default grey, and the shot is taken again;
    so it is while ``ready(image)`` is False (the background can arrive before the scene does, on a
    busy machine)."""
    import imageio.v3 as iio

    browser = chromium()
    if browser is None:
        raise CubecloudError("no chromium found: install it (Debian: apt-get install chromium)")
    command = [browser, "--headless", "--no-sandbox", "--use-gl=swiftshader", "--enable-unsafe-swiftshader",
               "--hide-scrollbars", f"--window-size={size[0]},{size[1]}", "--virtual-time-budget=15000",
               f"--screenshot={path}", url]  # fmt: skip
    for _ in range(attempts):
        subprocess.run(command, capture_output=True, timeout=180, check=False)
        if Path(path).is_file():
            image = iio.imread(path)[..., :3].astype(np.int32)
            width = image.shape[1]
            background_in = image[-10:, width // 3 : 2 * width // 3].mean() < 10  # the bottom edge
            if background_in and ready(image):
                return image
    raise CubecloudError(f"the viewer's page at {url} never finished loading: see {path}")
