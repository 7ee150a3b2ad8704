"""How the Gaussians reach each page: the few that shape the picture most first, the rest once the
page has drawn those.

Without a GPU a browser draws a frame of 100k Gaussians in seconds, and its first frame (with the
shader to compile) takes longer still; the COARSE_GAUSSIANS that matter most (the splats come in
importance order, splats.py) give a recognisable picture in a fraction of that. With a GPU the
coarse frame lasts a few milliseconds. So each page gets its own splat node: viser replays one
shared scene to every new page, which would send every Gaussian before the page had drawn any.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from typing import Callable

from cubecloud_cli.view.splats import ViewSplats

log = logging.getLogger("cubecloud")

COARSE_GAUSSIANS = 10_000  # a GPU-less browser draws these in about 0.3 s a frame (docs/view.md)
DRAWN_TIMEOUT_S = 30.0  # a page that does not draw (a background tab) gets the rest after this
SPLAT_NODE = "/splats"


@dataclass
class Page:
    """One browser's connection and the Gaussians it has been sent."""

    client: object  # viser.ClientHandle
    complete: bool = False  # sent every Gaussian (else only the coarse set)
    node: object | None = None  # its splat node, for the visibility toggle
    lock: threading.Lock = field(default_factory=threading.Lock)


class SplatDelivery:
    """The Gaussians in view units, sent to each connected page: the first ``coarse`` of them
    until the page has drawn a frame, then all. ``connected(client_id)`` says whether a page is
    still open (viser's server knows; a stopped server has none)."""

    def __init__(
        self, splats: ViewSplats, coarse: int = COARSE_GAUSSIANS, connected: Callable[[int], bool] = lambda _: True
    ):
        self.splats = splats
        self.coarse = coarse
        self.connected = connected
        self.visible = True
        self._pages: dict[int, Page] = {}
        self._pages_lock = threading.Lock()

    def show(self, splats: ViewSplats) -> None:
        """Draw ``splats`` (view units, importance order) instead on every page."""
        self.splats = splats
        for page in self._open_pages():
            self._send(page)

    def set_visible(self, visible: bool) -> None:
        self.visible = visible
        for page in self._open_pages():
            with page.lock:
                if page.node is not None:
                    page.node.visible = visible

    def open_page(self, client) -> None:
        """A new page: the coarse set now, every Gaussian once the page has drawn it (viser's
        render request returns after the page has drawn a frame with the messages before it)."""
        page = Page(client, complete=len(self.splats) <= self.coarse)
        with self._pages_lock:
            self._pages[client.client_id] = page
        self._send(page)
        if page.complete:
            return
        try:
            client.get_render(8, 8, timeout=DRAWN_TIMEOUT_S)
        except Exception as error:  # a hidden page gets the rest all the same; a closed one nothing
            log.debug("page %s did not report its first frame: %s", client.client_id, error)
            if not self.connected(client.client_id):
                self.close_page(client)
                return
        with page.lock:
            page.complete = True
        self._send(page)

    def close_page(self, client) -> None:
        with self._pages_lock:
            self._pages.pop(client.client_id, None)

    def pages_complete(self) -> bool:
        """Whether a page is open and every open one has been sent every Gaussian."""
        pages = self._open_pages()
        return bool(pages) and all(page.complete for page in pages)

    def _open_pages(self) -> list[Page]:
        with self._pages_lock:
            return list(self._pages.values())

    def _send(self, page: Page) -> None:
        # Under the page's lock: a redraw and the coarse set's successor must not cross.
        with page.lock:
            splats = self.splats if page.complete else self.splats.subset(slice(0, self.coarse))
            page.node = page.client.scene.add_gaussian_splats(
                SPLAT_NODE, splats.centers, splats.covariances, splats.rgbs, splats.opacities, visible=self.visible
            )
