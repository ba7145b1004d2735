"""A zero-latency camera that hands back frames prepared in advance.

For benchmarks of the acquisition software alone: capture costs nothing, so whatever time
a run takes is the daemon's own.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import replace

from drivers.camera import Camera, RawFrame


class ReplayCamera(Camera):
    """Returns ``frames`` in turn, stamped with the requested exposure and the time."""

    def __init__(self, frames: list[RawFrame], name: str = "replay camera"):
        if not frames:
            raise ValueError("a replay camera needs at least one frame")
        self._frames = itertools.cycle(frames)
        self.name = name

    def capture(self, exposure_s: float) -> RawFrame:
        return replace(next(self._frames), exposure_s=exposure_s, timestamp=time.time(), source="")
