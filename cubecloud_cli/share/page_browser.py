"""A shared page in headless Chromium, as tests and pictures open it: its script's state read
through the DevTools protocol, and the page once it holds still."""

from __future__ import annotations

import time

import numpy as np

from cubecloud_cli.view.browser import Chromium, frame_change

SETTLED_GREY_LEVELS = 0.5  # mean change between two captures below which the page holds still


def evaluate(browser: Chromium, expression: str):
    """The value of a JavaScript expression in the page (promises awaited); its error raised."""
    result = browser.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
    if "exceptionDetails" in result:
        raise RuntimeError(f"the page's script failed: {result['exceptionDetails']}")
    return result["result"].get("value")


def settled_page(browser: Chromium, timeout_s: float = 300.0) -> np.ndarray:
    """(H, W, 3) uint8: the page once its scene is drawn, two more frames have passed (a change
    just made has reached the screen) and two captures in a row agree."""
    deadline = time.monotonic() + timeout_s
    while not evaluate(browser, "!!(window.cubecloud && (window.cubecloud.ready || window.cubecloud.error))"):
        if time.monotonic() > deadline:
            raise TimeoutError(f"the page drew no scene within {timeout_s:.0f} s")
        time.sleep(0.2)
    error = evaluate(browser, "window.cubecloud.error")
    if error:
        raise RuntimeError(f"the page could not draw the scene: {error}")
    start, previous = evaluate(browser, "window.cubecloud.frames"), None
    while time.monotonic() < deadline:
        time.sleep(0.2)
        if evaluate(browser, "window.cubecloud.frames") < start + 2:
            continue
        image = browser.capture()
        if image is not None and previous is not None and frame_change(image, previous) < SETTLED_GREY_LEVELS:
            return image
        previous = image
    raise TimeoutError(f"the page did not hold still within {timeout_s:.0f} s")
