"""The viewer's delivery of Gaussians to each page: the coarse set first, every Gaussian once the
page has drawn it (view/delivery.py), with stand-ins for viser's client handles."""

import inspect
import logging

import numpy as np

from cubecloud_cli.view.delivery import FENCE_SIZE, SplatDelivery
from cubecloud_cli.view.splats import ViewSplats


def splats(count: int, first: float = 0.0) -> ViewSplats:
    """``count`` Gaussians whose first centre coordinate numbers them from ``first``."""
    centers = np.zeros((count, 3), dtype=np.float32)
    centers[:, 0] = first + np.arange(count)
    return ViewSplats(centers, np.tile(np.eye(3, dtype=np.float32), (count, 1, 1)),
                      np.full((count, 3), 0.5, dtype=np.float32), np.full((count, 1), 0.5, dtype=np.float32))  # fmt: skip


class Node:
    def __init__(self, centers: np.ndarray, visible: bool):
        self.centers, self.visible = centers, visible


class FakeClient:
    """A browser page's connection as the delivery sees it: its scene receives splat nodes, and a
    render request returns once the page has drawn (``on_render`` runs then, or raises)."""

    def __init__(self, client_id: int, log: list, on_render=lambda: None):
        self.client_id, self.log, self.on_render = client_id, log, on_render
        self.nodes: list[Node] = []
        self.scene = self

    def add_gaussian_splats(self, name, centers, covariances, rgbs, opacities, visible=True):
        assert name == "/splats" and len(centers) == len(covariances) == len(rgbs) == len(opacities)
        self.nodes.append(Node(centers, visible))
        self.log.append(("sent", self.client_id, len(centers), float(centers[0, 0])))
        return self.nodes[-1]

    def get_render(self, height, width, timeout=None):
        self.log.append(("drawn?", self.client_id))
        self.on_render()


def test_the_render_request_is_called_as_viser_takes_it():
    from viser import ClientHandle

    inspect.signature(ClientHandle.get_render).bind(None, FENCE_SIZE, FENCE_SIZE, timeout=1.0)


def test_a_page_gets_the_coarse_set_first_and_every_gaussian_once_it_has_drawn_it():
    log = []
    delivery = SplatDelivery(splats(100), coarse=10)
    page = FakeClient(7, log, on_render=lambda: log.append(("sent all?", delivery.pages_sent_all())))
    assert not delivery.pages_sent_all() and not delivery.pages_drawn([7])  # no page open
    delivery.open_page(page)
    assert log == [("sent", 7, 10, 0.0), ("drawn?", 7), ("sent all?", False), ("sent", 7, 100, 0.0)]
    assert delivery.pages_sent_all()
    delivery.close_page(page)
    assert not delivery.pages_sent_all()


def test_a_screenshot_waits_for_a_frame_after_the_last_set_and_for_every_connected_page():
    log = []
    delivery = SplatDelivery(splats(100), coarse=10)
    delivery.open_page(FakeClient(1, log))
    log.clear()
    assert not delivery.pages_drawn([1, 2])  # page 2 is connected but its callback has not run
    assert delivery.pages_drawn([1]) and log == [("drawn?", 1)]
    assert delivery.pages_drawn([1]) and log == [("drawn?", 1)]  # known drawn: not asked again
    delivery.show(splats(100, first=500.0))
    assert delivery.pages_drawn([1]) and log[-2:] == [("sent", 1, 100, 500.0), ("drawn?", 1)]

    # A set sent while the page draws is not covered by that frame.
    racing = FakeClient(3, log)
    delivery.open_page(racing)
    racing.on_render = lambda: delivery.show(splats(100, first=900.0))
    assert not delivery.pages_drawn([3])
    racing.on_render = lambda: None
    assert delivery.pages_drawn([3])


def test_a_scene_no_larger_than_the_coarse_set_is_sent_whole_at_once():
    log = []
    delivery = SplatDelivery(splats(10), coarse=10)
    delivery.open_page(FakeClient(1, log))
    assert log == [("sent", 1, 10, 0.0)] and delivery.pages_sent_all()


def test_a_page_that_never_reports_a_frame_still_gets_every_gaussian():
    log = []

    def hidden_tab():
        raise TimeoutError("no frame")

    delivery = SplatDelivery(splats(50), coarse=5)
    delivery.open_page(FakeClient(2, log, on_render=hidden_tab))
    assert log[-1] == ("sent", 2, 50, 0.0) and delivery.pages_sent_all()


def test_an_unexpected_render_error_is_logged_and_the_page_still_gets_every_gaussian(caplog):
    log = []

    def changed_api():
        raise TypeError("get_render() got an unexpected keyword argument")

    delivery = SplatDelivery(splats(50), coarse=5)
    logger = logging.getLogger("cubecloud")  # the CLI's logger may not propagate to caplog's
    logger.addHandler(caplog.handler)
    try:
        delivery.open_page(FakeClient(2, log, on_render=changed_api))
    finally:
        logger.removeHandler(caplog.handler)
    assert log[-1] == ("sent", 2, 50, 0.0)
    assert "render request failed" in caplog.text and "unexpected keyword" in caplog.text


def test_a_redraw_while_a_page_has_the_coarse_set_ends_with_the_new_scene_whole():
    log = []
    delivery = SplatDelivery(splats(40), coarse=4)
    other = FakeClient(1, log)
    delivery.open_page(other)  # complete before the second page opens
    # The clipping plane moves while the second page draws its coarse set.
    page = FakeClient(2, log, on_render=lambda: delivery.show(splats(30, first=1000.0)))
    delivery.open_page(page)
    assert [entry for entry in log if entry[1] == 2] == [
        ("sent", 2, 4, 0.0), ("drawn?", 2), ("sent", 2, 4, 1000.0), ("sent", 2, 30, 1000.0)]  # fmt: skip
    assert other.nodes[-1].centers.shape[0] == 30 and other.nodes[-1].centers[0, 0] == 1000.0


def test_hiding_the_gaussians_reaches_every_page_and_pages_opened_later():
    log = []
    delivery = SplatDelivery(splats(20), coarse=5)
    first = FakeClient(1, log)
    delivery.open_page(first)
    delivery.set_visible(False)
    assert not first.nodes[-1].visible
    later = FakeClient(2, log)
    delivery.open_page(later)
    assert all(not node.visible for node in later.nodes)
    delivery.set_visible(True)
    assert first.nodes[-1].visible and later.nodes[-1].visible


def test_a_page_closed_while_drawing_its_coarse_set_is_sent_nothing_more():
    log, open_pages = [], {3}

    def closed():
        open_pages.discard(3)
        raise RuntimeError("the client disconnected")

    delivery = SplatDelivery(splats(50), coarse=5, connected=lambda client_id: client_id in open_pages)
    delivery.open_page(FakeClient(3, log, on_render=closed))
    assert log == [("sent", 3, 5, 0.0), ("drawn?", 3)] and not delivery.pages_sent_all()


def test_a_page_closed_before_its_connect_callback_ran_is_sent_nothing():
    log = []
    delivery = SplatDelivery(splats(5), coarse=10, connected=lambda client_id: False)
    delivery.open_page(FakeClient(4, log))
    assert log == [] and not delivery.pages_sent_all()
