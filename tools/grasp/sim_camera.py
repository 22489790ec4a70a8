"""A camera whose frames a simulation pushes in: what the runtime's frame loop reads for a
simulated fingertip (drivers' camera protocol: read() -> Frame, EndOfStream at the end)."""
from __future__ import annotations

import queue

import numpy as np

from ...contracts.errors import CaptureError
from ...drivers.camera.camera import EndOfStream, Frame


class SimCamera:
    def __init__(self, timeout_s: float = 5.0):
        self._q: queue.Queue = queue.Queue()
        self._n = 0
        self.timeout_s = timeout_s

    def push(self, image_rgb: np.ndarray, t: float) -> None:
        self._q.put((image_rgb, t))

    def end(self) -> None:
        self._q.put(None)

    def read(self) -> Frame:
        try:
            item = self._q.get(timeout=self.timeout_s)
        except queue.Empty:
            raise CaptureError(f"simulated camera: no frame within {self.timeout_s} s") from None
        if item is None:
            raise EndOfStream("simulation ended")
        img, t = item
        f = Frame(img, float(t), self._n)
        self._n += 1
        return f
