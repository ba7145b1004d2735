"""The camera interface: a capture is a raw Bayer mosaic with the metadata it needs.

The exposure time in a :class:`RawFrame` is the one the camera recorded in the file,
never the one that was asked for: cameras round shutter speeds to their own steps.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field

import numpy as np

#: The exposures a run may ask for, in seconds. The shortest, 1/100000 s, is below any
#: camera's shortest shutter (1/32000 s electronic, 1/8000 s mechanical) and far above the
#: shortest time a raw file holds (a DNG's ExposureTime is a TIFF rational of 32-bit terms,
#: 1/4294967295 s at the least; ``sim_devices.dng``); the longest, an hour, is beyond any
#: timed shutter (30 s) and any bulb exposure a run needs. A camera rounds a time inside
#: these to its own steps (:class:`RawFrame` keeps the time it took).
SHORTEST_EXPOSURE_S = 1e-5
LONGEST_EXPOSURE_S = 3600.0


@dataclass
class RawFrame:
    """One raw capture.

    Attributes
    ----------
    mosaic : ndarray of uint16, shape (height, width)
        The visible raw pixels, before any processing.
    black_level : ndarray of float, shape (2, 2)
        Black level per CFA site, laid out like ``cfa_pattern``.
    white_level : int
        The saturation level the file reports (processing re-measures it).
    cfa_pattern : str
        Colour of the 2x2 CFA tile, row-major, e.g. ``"RGGB"``.
    exposure_s : float
        Exposure time read from the file's metadata.
    timestamp : float
        Capture time, seconds since the epoch.
    camera_id : str
        Make, model and serial number where known.
    source : str
        The file the frame was decoded from.
    """

    mosaic: np.ndarray
    black_level: np.ndarray
    white_level: int
    cfa_pattern: str
    exposure_s: float
    timestamp: float
    camera_id: str
    source: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        return self.mosaic.shape


class Camera(abc.ABC):
    """Anything that can take one raw exposure."""

    name: str = "camera"

    @abc.abstractmethod
    def capture(self, exposure_s: float) -> RawFrame:
        """Expose for ``exposure_s`` seconds and return the decoded raw frame."""

    @property
    def identity(self) -> str:
        return self.name

    def problem(self) -> str | None:
        """Why the camera cannot capture right now, or None when it can (for health)."""
        return None

    def connect(self) -> None:  # noqa: B027 - optional for cameras without a session
        """Open the session with the camera, where there is one."""

    def close(self) -> None:  # noqa: B027
        """Close the session with the camera, where there is one."""

    def __enter__(self) -> Camera:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
