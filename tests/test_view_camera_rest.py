"""The viewer redraws a chord-length scene once the camera rests (view/camera_rest.py)."""

import threading

import numpy as np

from cubecloud_cli.view.camera_rest import CameraRest


def test_a_drag_is_acted_on_once_at_its_last_position():
    seen = []
    rest = CameraRest(seen.append, rest_s=600.0)
    rest.moved([1.0, 0.0, 0.0])
    rest.moved((2.0, 0.0, 0.0))
    assert seen == []  # still moving
    rest.flush()
    rest.flush()
    assert len(seen) == 1 and np.array_equal(seen[0], [2.0, 0.0, 0.0])
    rest.moved([3.0, 0.0, 0.0])
    rest.cancel()
    rest.flush()
    assert len(seen) == 1  # a cancelled move is dropped


def test_the_timer_acts_once_the_camera_has_rested():
    rested = threading.Event()
    positions = []
    rest = CameraRest(lambda p: (positions.append(p), rested.set()), rest_s=0.01)
    rest.moved([0.0, 0.0, 4.0])
    assert rested.wait(timeout=60.0)
    assert len(positions) == 1 and np.array_equal(positions[0], [0.0, 0.0, 4.0])
