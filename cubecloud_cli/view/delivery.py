"""How the Gaussians reach each page: the few that shape the picture most first, the rest once the
page has drawn those.

Without a GPU a browser draws a frame of 100k Gaussians in about 2 s, and its first frame (with the
shader to compile) takes longer still; the COARSE_GAUSSIANS that matter most (the splats come in
importance order, splats.py) give a recognisable picture in a fraction of that (docs/view.md).
So each page gets its own splat node: viser replays one shared scene to every new page, which
would send every Gaussian before the page had drawn any.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from typing import Callable, Iterable

from cubecloud_cli.view.splats import ViewSplats

log = logging.getLogger("cubecloud")

COARSE_GAUSSIANS = 10_000  # a GPU-less browser draws these in 0.2–0.3 s a frame (docs/view.md)
# A page that does not draw (a background tab) gets the rest after this. The wait holds one of
# viser's callback threads (it has 32) per such page.
DRAWN_TIMEOUT_S = 30.0
SPLAT_NODE = "/splats"
FENCE_SIZE = 8  # pixels a side of the render that tells when a page has drawn


@dataclass
class Page:
    """One browser's connection and what it has of the Gaussians."""

    client: object  # viser.ClientHandle
    sent_all: bool = False  # every Gaussian sent (else only the coarse set)
    sends: int = 0  # sets sent so far, to tell whether a frame came after the latest
    drawn_after: int = 0  # the sends that a frame of the page is known to have followed
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
        page = Page(client)
        with self._pages_lock:
            self._pages[client.client_id] = page
        if not self.connected(client.client_id):  # closed before this callback ran
            self.close_page(client)
            return
        self._send(page, everything=len(self.splats) <= self.coarse)
        if page.sent_all:
            return
        if not self._wait_until_drawn(client):
            self.close_page(client)
            return
        self._send(page, everything=True)

    def close_page(self, client) -> None:
        with self._pages_lock:
            self._pages.pop(client.client_id, None)

    def pages_sent_all(self) -> bool:
        """Whether a page is open and every open one has been sent every Gaussian (asks the pages
        nothing: the bench's check, which must not make them draw)."""
        pages = self._open_pages()
        return bool(pages) and all(page.sent_all for page in pages)

    def pages_drawn(self, client_ids: Iterable[int]) -> bool:
        """Whether each of these pages has been sent every Gaussian and has drawn a frame since.
        Asks each page that has not said so yet to draw: for screenshots, not for viewing (without
        a GPU the request costs the page a frame)."""
        with self._pages_lock:
            pages = [self._pages.get(client_id) for client_id in client_ids]
        if not pages or any(page is None or not page.sent_all for page in pages):
            return False
        for page in pages:
            sends = page.sends  # read before the request: a set sent after it is not covered
            if page.drawn_after < sends and self._wait_until_drawn(page.client):
                page.drawn_after = max(page.drawn_after, sends)
        return all(page.drawn_after == page.sends for page in pages)

    def _open_pages(self) -> list[Page]:
        with self._pages_lock:
            return list(self._pages.values())

    def _wait_until_drawn(self, client) -> bool:
        """Block until ``client`` has drawn a frame with what it was sent; False if it has closed.
        A page that does not answer in time counts as drawn: it gets the rest all the same."""
        try:
            client.get_render(FENCE_SIZE, FENCE_SIZE, timeout=DRAWN_TIMEOUT_S)
        except (TimeoutError, RuntimeError) as error:  # viser: no frame in time; closed; capture failed
            log.debug("page %s did not report a frame: %s", client.client_id, error)
        except Exception as error:  # not viser's: say so, and do not hold the page back
            log.warning("page %s: its render request failed (%s); sending every Gaussian", client.client_id, error)
        return self.connected(client.client_id)

    def _send(self, page: Page, everything: bool | None = None) -> None:
        # Under the page's lock: a redraw and the coarse set's successor must not cross.
        with page.lock:
            sent_all = page.sent_all if everything is None else everything
            splats = self.splats if sent_all else self.splats.subset(slice(0, self.coarse))
            page.node = page.client.scene.add_gaussian_splats(
                SPLAT_NODE, splats.centers, splats.covariances, splats.rgbs, splats.opacities, visible=self.visible
            )
            # Counted once queued, so a render request that reads them comes after the set.
            page.sends += 1
            page.sent_all = sent_all
