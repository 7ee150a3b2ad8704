"""The viewer's delivery of Gaussians to each page: the coarse set first, every Gaussian once the
page has drawn it (view/delivery.py), with stand-ins for viser's client handles."""

import numpy as np

from cubecloud_cli.view.delivery import SplatDelivery
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


class FakePage:
    """A browser page as the delivery sees it: its scene receives splat nodes, and a render
    request returns once it has drawn (``on_render`` runs then, or raises)."""

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


def test_a_page_gets_the_coarse_set_first_and_every_gaussian_once_it_has_drawn_it():
    log = []
    delivery = SplatDelivery(splats(100), coarse=10)
    page = FakePage(7, log, on_render=lambda: log.append(("complete?", delivery.pages_complete())))
    assert not delivery.pages_complete()  # no page open
    delivery.open_page(page)
    assert log == [("sent", 7, 10, 0.0), ("drawn?", 7), ("complete?", False), ("sent", 7, 100, 0.0)]
    assert delivery.pages_complete()
    delivery.close_page(page)
    assert not delivery.pages_complete()


def test_a_scene_no_larger_than_the_coarse_set_is_sent_whole_at_once():
    log = []
    delivery = SplatDelivery(splats(10), coarse=10)
    delivery.open_page(FakePage(1, log))
    assert log == [("sent", 1, 10, 0.0)] and delivery.pages_complete()


def test_a_page_that_never_reports_a_frame_still_gets_every_gaussian():
    log = []

    def hidden_tab():
        raise TimeoutError("no frame")

    delivery = SplatDelivery(splats(50), coarse=5)
    delivery.open_page(FakePage(2, log, on_render=hidden_tab))
    assert log[-1] == ("sent", 2, 50, 0.0) and delivery.pages_complete()


def test_a_redraw_while_a_page_has_the_coarse_set_ends_with_the_new_scene_whole():
    log = []
    delivery = SplatDelivery(splats(40), coarse=4)
    other = FakePage(1, log)
    delivery.open_page(other)  # complete before the second page opens
    # The clipping plane moves while the second page draws its coarse set.
    page = FakePage(2, log, on_render=lambda: delivery.show(splats(30, first=1000.0)))
    delivery.open_page(page)
    assert [entry for entry in log if entry[1] == 2] == [
        ("sent", 2, 4, 0.0), ("drawn?", 2), ("sent", 2, 4, 1000.0), ("sent", 2, 30, 1000.0)]  # fmt: skip
    assert other.nodes[-1].centers.shape[0] == 30 and other.nodes[-1].centers[0, 0] == 1000.0


def test_hiding_the_gaussians_reaches_every_page_and_pages_opened_later():
    log = []
    delivery = SplatDelivery(splats(20), coarse=5)
    first = FakePage(1, log)
    delivery.open_page(first)
    delivery.set_visible(False)
    assert not first.nodes[-1].visible
    later = FakePage(2, log)
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
    delivery.open_page(FakePage(3, log, on_render=closed))
    assert log == [("sent", 3, 5, 0.0), ("drawn?", 3)] and not delivery.pages_complete()
