"""When a page's camera comes to rest: what a chord-length scalar scene redraws on.

A chord-length scene's opacities depend on where it is seen from (splat/chord.py), but a redraw
sends every Gaussian again, and a page that is being dragged reports its camera tens of times a
second. So the viewer redraws once the camera has been still for :data:`REST_S`.
"""

from __future__ import annotations

import threading
from typing import Callable

import numpy as np

REST_S = 0.3  # still this long (seconds) after the last move: the drag has ended


class CameraRest:
    """Calls ``on_rest(position)`` with the last position :meth:`moved` was given, once no
    further move has come for ``rest_s`` seconds."""

    def __init__(self, on_rest: Callable[[np.ndarray], None], rest_s: float = REST_S):
        self.on_rest = on_rest
        self.rest_s = rest_s
        self._lock = threading.Lock()
        self._timer: threading.Timer | None = None
        self._position: np.ndarray | None = None

    def moved(self, position) -> None:
        with self._lock:
            self._position = np.asarray(position, dtype=np.float64).copy()
            if self._timer is not None:
                self._timer.cancel()
            self._timer = threading.Timer(self.rest_s, self.flush)
            self._timer.daemon = True
            self._timer.start()

    def flush(self) -> None:
        """Act on the last move now (and once): what the timer does when it runs out."""
        with self._lock:
            position, self._position = self._position, None
            if self._timer is not None:
                self._timer.cancel()
                self._timer = None
        if position is not None:
            self.on_rest(position)

    def cancel(self) -> None:
        with self._lock:
            self._position = None
            if self._timer is not None:
                self._timer.cancel()
                self._timer = None
