"""A screenshot of the viewer as a person sees it: headless Chromium with software WebGL, driven over
the DevTools protocol (used by the tests, examples/view_screenshot.py and bench/view.py).

The page is polled in real time until it shows what was asked for and holds still. A fixed
budget of the browser's virtual time is not enough: virtual time runs ahead while the page waits
for the server's messages, so on a busy machine the shot came before the scene's camera did.
"""

from __future__ import annotations

import base64
import contextlib
import io
import json
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from cubecloud_cli.core.errors import CubecloudError

SETTLED_GREY_LEVELS = 1.0  # mean change between two captures below which the page holds still


def chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


def frame_change(image: np.ndarray, other: np.ndarray) -> float:
    """Mean change in grey levels between two captures of the page."""
    return float(np.abs(image.astype(np.int16) - other.astype(np.int16)).mean())


def background_in(image: np.ndarray) -> bool:
    """The viewer's black background has replaced the page's default grey (at the bottom edge,
    away from the controls)."""
    width = image.shape[1]
    return float(image[-10:, width // 3 : 2 * width // 3].mean()) < 10


def received_bytes(message: dict) -> tuple[str, int]:
    """What one DevTools network event says reached the page: ("http", bytes on the wire) for a
    finished load (the viewer's HTML, script and styles), ("websocket", payload bytes) for a
    message from the server (the scene), or ("", 0) for any other event."""
    params = message.get("params", {})
    if message.get("method") == "Network.loadingFinished":
        return "http", int(params.get("encodedDataLength", 0))
    if message.get("method") == "Network.webSocketFrameReceived":
        frame = params.get("response", {})
        payload = frame.get("payloadData", "")
        # DevTools hands binary frames (opcode 2) over in base64 (4 characters per 3 bytes, "="
        # padding), text frames as they are.
        if frame.get("opcode") == 2:
            size = len(payload) // 4 * 3 - len(payload[-2:]) + len(payload[-2:].rstrip("="))
        else:
            size = len(payload.encode())
        return "websocket", size
    return "", 0


class Chromium:
    """One headless Chromium with one page, and the few DevTools calls a screenshot needs.
    ``received`` counts the bytes that reached the page, by kind, since the last ``open``/``frames``
    (while ``count_bytes``: the network events cost the page nothing, but each is one more message)."""

    def __init__(self, size: tuple[int, int] = (900, 700), count_bytes: bool = False):
        from websockets.sync.client import connect  # viser's dependency: present wherever view runs

        browser = chromium()
        if browser is None:
            raise CubecloudError("no chromium found: install it (Debian: apt-get install chromium)")
        self.profile = Path(tempfile.mkdtemp(prefix="cubecloud-chromium-"))
        command = [browser, "--headless", "--no-sandbox", "--use-gl=swiftshader", "--enable-unsafe-swiftshader",
                   "--hide-scrollbars", f"--window-size={size[0]},{size[1]}", "--remote-debugging-port=0",
                   f"--user-data-dir={self.profile}", "about:blank"]  # fmt: skip
        self.process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            port = self._devtools_port()
            targets = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=60).read())
            page = next(target for target in targets if target["type"] == "page")
            self.socket = connect(page["webSocketDebuggerUrl"], max_size=None, open_timeout=60)
            self.next_id = 0
            self.received = dict.fromkeys(("http", "websocket"), 0)
            self.call("Page.enable")
            if count_bytes:
                self.call("Network.enable")
                # viser's page talks to its server from a web worker: its frames are the worker's.
                self.call("Target.setAutoAttach", autoAttach=True, waitForDebuggerOnStart=False, flatten=True)
            self.call("Emulation.setDeviceMetricsOverride", width=size[0], height=size[1], deviceScaleFactor=1,
                      mobile=False)  # fmt: skip
        except BaseException:
            self.close()
            raise

    def _devtools_port(self) -> int:
        port_file = self.profile / "DevToolsActivePort"
        for _ in range(1200):
            if port_file.is_file() and port_file.read_text().strip():
                return int(port_file.read_text().split()[0])
            if self.process.poll() is not None:
                break
            time.sleep(0.05)
        raise CubecloudError("chromium did not open its DevTools port within a minute: is it installed whole?")

    def send(self, method: str, session: str | None = None, **params) -> int:
        """Send a DevTools command (to an attached worker's ``session``, or the page) without
        waiting for its answer; its message id."""
        self.next_id += 1
        message = {"id": self.next_id, "method": method, "params": params}
        if session is not None:
            message["sessionId"] = session
        self.socket.send(json.dumps(message))
        return self.next_id

    def call(self, method: str, **params) -> dict:
        self.send(method, **params)
        while True:
            message = json.loads(self.socket.recv(timeout=300))
            self._tally(message)
            if message.get("id") == self.next_id:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                return message["result"]

    def _tally(self, message: dict) -> None:
        if message.get("method") == "Target.attachedToTarget":  # only while counting bytes
            self.send("Network.enable", session=message["params"]["sessionId"])
        kind, size = received_bytes(message)
        if kind:
            self.received[kind] += size

    def open(self, url: str) -> None:
        """Load ``url`` afresh, as a person opening the page (a blank page first: the same URL
        again would otherwise keep the old page's state)."""
        self.call("Page.navigate", url="about:blank")
        self.received = dict.fromkeys(("http", "websocket"), 0)
        self.call("Page.navigate", url=url)

    def capture(self) -> np.ndarray | None:
        """The page as it is now, (H, W, 3) uint8, or None while a navigation has none to show."""
        import imageio.v3 as iio

        try:
            data = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        except RuntimeError as error:
            if "Not attached" not in str(error):
                raise
            time.sleep(0.05)
            return None
        return iio.imread(io.BytesIO(data))[..., :3]

    def frames(self, url: str, timeout_s: float = 300.0) -> Iterator[tuple[float, np.ndarray]]:
        """Open ``url`` and yield each frame the page shows, (seconds from asking for the page to
        the frame being drawn, (H, W, 3) uint8), until ``timeout_s``. A screencast hands over the
        frames the page draws anyway, where each screenshot would make it draw one more: without
        a GPU a frame of a large scene costs seconds, so polling screenshots slowed the page it
        was timing. Close the generator (``contextlib.closing``) to stop the screencast."""
        import imageio.v3 as iio
        from websockets.exceptions import ConnectionClosed

        self.call("Page.navigate", url="about:blank")
        start = time.monotonic()
        while True:  # the blank page attaches a moment after its navigation answers
            try:
                self.call("Page.startScreencast", format="png")
                break
            except RuntimeError as error:
                if "Not attached" not in str(error) or time.monotonic() - start > 60:
                    raise
                time.sleep(0.05)
        start, start_wall = time.perf_counter(), time.time()
        self.received = dict.fromkeys(("http", "websocket"), 0)
        navigation = self.send("Page.navigate", url=url)
        try:
            while time.perf_counter() - start < timeout_s:
                try:
                    message = json.loads(self.socket.recv(timeout=1.0))
                except TimeoutError:
                    continue
                self._tally(message)
                if message.get("id") == navigation and (message.get("error") or message["result"].get("errorText")):
                    raise CubecloudError(f"chromium could not open {url}: {message.get('error') or message['result']}")
                if message.get("method") != "Page.screencastFrame":
                    continue
                frame = message["params"]
                self.send("Page.screencastFrameAck", sessionId=frame["sessionId"])
                image = iio.imread(io.BytesIO(base64.b64decode(frame["data"])))[..., :3]
                drawn_at = frame.get("metadata", {}).get("timestamp")  # seconds since the epoch
                yield (time.perf_counter() - start if drawn_at is None else drawn_at - start_wall), image
        finally:
            with contextlib.suppress(RuntimeError, OSError, ConnectionError, ConnectionClosed):
                self.call("Page.stopScreencast")  # the browser may be gone already: nothing to stop

    def close(self) -> None:
        if getattr(self, "socket", None) is not None:
            self.socket.close()
        self.process.kill()
        self.process.wait()
        shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self) -> Chromium:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def settled_capture(
    browser: Chromium, ready: Callable[[np.ndarray], bool], timeout_s: float
) -> tuple[np.ndarray | None, bool]:
    """Capture until the page shows the background and ``ready`` holds on two captures in a row
    that differ by less than SETTLED_GREY_LEVELS (a splat sort or a late texture still lands
    between them otherwise). Returns the last capture and whether it settled in time."""
    deadline = time.monotonic() + timeout_s
    last, previous = None, None
    while time.monotonic() < deadline:
        image = browser.capture()
        if image is None:
            continue
        last = image
        if not (background_in(image) and ready(image)):
            previous = None
            continue
        if previous is not None and frame_change(image, previous) < SETTLED_GREY_LEVELS:
            return image, True
        previous = image
    return last, False


def screenshot(
    url: str,
    path: Path,
    size: tuple[int, int] = (900, 700),
    ready: Callable[[np.ndarray], bool] = lambda image: True,
    timeout_s: float = 300.0,
) -> np.ndarray:
    """The page at ``url`` once it has settled with ``ready(image)`` True, as an (H, W, 3) int32
    array also written to ``path``."""
    import imageio.v3 as iio

    with Chromium(size) as browser:
        browser.open(url)
        image, settled = settled_capture(browser, ready, timeout_s)
    if image is not None:
        iio.imwrite(path, image)
    if not settled:
        raise CubecloudError(f"the viewer's page at {url} did not settle within {timeout_s:.0f} s: see {path}")
    return image.astype(np.int32)
