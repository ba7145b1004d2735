"""Previews of a raw frame: a quick-look grey PNG, and the alignment view the page shows.

The alignment view (:func:`frame_png`, :func:`frame_summary`) keeps the sensor's full
resolution: each pixel is the signal of its 3x3 neighbourhood weighed so that red, green and
blue count 1:2:1 whatever the CFA (no checker pattern, no shift), on a log scale from 1 DN above the
black level to the white level, so that both a source's bright core and the ball's dim edge
in room light show; photosites at the white level are painted :data:`SATURATED_RGB`. The
summary names the exposure, counts the saturated photosites, gives each colour channel's
histogram on log-spaced bins, and the ball's expected outline from the rig
(:meth:`drivers.contracts.rig.Rig.ball_outline_px`).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from datetime import UTC, datetime

import cv2
import numpy as np

from drivers.camera import RawFrame
from drivers.contracts.rig import Rig

#: The colour of a saturated photosite in the alignment view (RGB).
SATURATED_RGB = (255, 0, 255)
#: A photosite counts as saturated from this share of the range above black
#: (as :func:`acquisition.daemon.bracketing.is_saturated` sees a frame).
SATURATED_FRACTION = 0.98
#: Bins of the histograms (log-spaced from 1 DN above black to the white level, fewer where
#: the low ones would be narrower than 1 DN).
HISTOGRAM_BINS = 48


def preview_png(frame: RawFrame, max_width: int = 640) -> bytes:
    """Grey PNG of ``frame``: the square root of signal over its 99.9th percentile.

    The square root keeps both the bright cores and the faint halo of the mirror ball's
    sources visible; the percentile stops one hot pixel from darkening the whole view.
    """
    h, w = frame.mosaic.shape
    h2, w2 = h - h % 2, w - w % 2
    mosaic = frame.mosaic[:h2, :w2].astype(np.float32) - float(frame.black_level.mean())
    superpixels = mosaic.reshape(h2 // 2, 2, w2 // 2, 2).mean(axis=(1, 3))
    scale = float(np.percentile(superpixels, 99.9))
    if scale <= 0:
        scale = max(float(superpixels.max()), 1.0)
    image = np.sqrt(np.clip(superpixels / scale, 0.0, 1.0))
    if image.shape[1] > max_width:
        size = (max_width, max(1, round(image.shape[0] * max_width / image.shape[1])))
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    return _encode(image * 255.0 + 0.5)


def _encode(image: np.ndarray) -> bytes:
    """PNG of a grey (h, w) or RGB (h, w, 3) image of 0–255 values."""
    pixels = image.astype(np.uint8)
    if pixels.ndim == 3:
        pixels = np.ascontiguousarray(pixels[:, :, ::-1])  # OpenCV writes BGR
    ok, png = cv2.imencode(".png", pixels, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:  # pragma: no cover - OpenCV refuses only impossible images
        raise ValueError("could not encode the preview")
    return png.tobytes()


def _signal(frame: RawFrame) -> np.ndarray:
    """DN above each photosite's black level (float32, the mosaic's shape)."""
    h, w = frame.mosaic.shape
    black = np.tile(np.asarray(frame.black_level, dtype=np.float32), ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    return frame.mosaic.astype(np.float32) - black


def _top(frame: RawFrame) -> float:
    """The range above black, DN (at least 2: the log scale needs a span)."""
    return max(float(frame.white_level) - float(np.max(frame.black_level)), 2.0)


def saturated_mask(frame: RawFrame) -> np.ndarray:
    """The photosites at the white level (:data:`SATURATED_FRACTION` of the range above black)."""
    return _signal(frame) >= SATURATED_FRACTION * _top(frame)


def frame_png(frame: RawFrame) -> bytes:
    """The alignment view of ``frame`` at the sensor's resolution (RGB PNG, see the module)."""
    signal = _signal(frame)
    # Each pixel: its 3x3 neighbourhood weighed [1 2 1]ᵀ[1 2 1] / 16, which takes R, G and B
    # as 1:2:1 at every site of any 2x2 tile and is centred (no checker, no half-pixel shift).
    kernel = np.array([0.25, 0.5, 0.25], dtype=np.float32)
    box = cv2.sepFilter2D(signal, -1, kernel, kernel, borderType=cv2.BORDER_REFLECT)
    top = _top(frame)
    grey = np.log10(np.clip(box, 1.0, top)) * (255.0 / math.log10(top)) + 0.5
    rgb = np.repeat(grey.astype(np.uint8)[:, :, None], 3, axis=2)
    rgb[signal >= SATURATED_FRACTION * top] = SATURATED_RGB
    return _encode(rgb)


def frame_summary(frame: RawFrame, rig: Rig | None) -> dict:
    """What the page says of ``frame`` beside its view: size, exposure, levels, saturation,
    the histograms, the log scale and the ball's expected outline (None without a rig whose
    sensor matches the frame)."""
    signal = _signal(frame)
    top = _top(frame)
    h, w = signal.shape
    saturated = int(np.count_nonzero(signal >= SATURATED_FRACTION * top))
    # Log-spaced, but at least 1 DN wide: the raw values are whole numbers.
    edges = np.unique(np.round(np.geomspace(1.0, top, HISTOGRAM_BINS + 1)))
    channels: dict[str, np.ndarray] = {}
    for k, colour in enumerate(frame.cfa_pattern.upper()):
        site = signal[k // 2 :: 2, k % 2 :: 2].ravel()
        channels[colour] = np.concatenate([channels[colour], site]) if colour in channels else site
    histograms = {
        colour: {
            "below": int(np.count_nonzero(values < 1.0)),
            "counts": np.histogram(np.minimum(values[values >= 1.0], edges[-1]), bins=edges)[0].tolist(),
        }
        for colour, values in sorted(channels.items(), key=lambda item: "RGB".find(item[0]))
    }
    outline = None
    if rig is not None and (rig.camera.width, rig.camera.height) == (w, h):
        outline = np.round(rig.ball_outline_px(), 2).tolist()
    return {
        "width": w,
        "height": h,
        "exposure_s": float(frame.exposure_s),
        "captured_utc": datetime.fromtimestamp(frame.timestamp, UTC).isoformat(timespec="seconds"),
        "camera_id": frame.camera_id,
        "black_level_dn": float(np.mean(frame.black_level)),
        "white_level_dn": int(frame.white_level),
        "peak_dn": round(float(signal.max()), 1),
        "saturated_pixels": saturated,
        "saturated_share": saturated / signal.size,
        "scale": {"kind": "log10", "low_dn": 1.0, "high_dn": top},
        "histogram": {"edges_dn": np.round(edges, 3).tolist(), "channels": histograms},
        "ball_outline_px": outline,
    }


class Previews:
    """The latest frame's previews, each made once per frame (the engine's ``frame_serial``).

    ``latest`` returns ``(serial, frame, run_id)`` of the frame shown last, or a ``None`` frame.
    """

    def __init__(self, latest: Callable[[], tuple[int, RawFrame | None, str | None]], rig: Rig | None):
        self._latest = latest
        self._rig = rig
        self._lock = threading.Lock()
        self._cache: dict[str, tuple[int, object]] = {}

    def _made(self, kind: str, make: Callable[[RawFrame], object]) -> tuple[object, int, str | None] | None:
        serial, frame, run_id = self._latest()
        if frame is None:
            return None
        with self._lock:
            cached = self._cache.get(kind)
            if cached is None or cached[0] != serial:
                cached = (serial, make(frame))
                self._cache[kind] = cached
        return cached[1], serial, run_id

    def quick_look(self) -> tuple[bytes, str | None] | None:
        """The downscaled grey PNG (:func:`preview_png`) and the frame's run, or None."""
        made = self._made("quick", preview_png)
        return None if made is None else (made[0], made[2])  # type: ignore[return-value]

    def view(self) -> bytes | None:
        """The alignment view (:func:`frame_png`), or None before any frame."""
        made = self._made("view", frame_png)
        return None if made is None else made[0]  # type: ignore[return-value]

    def summary(self) -> dict | None:
        """:func:`frame_summary`, with the frame's ``serial`` and ``run_id`` (None: a test shot)."""
        made = self._made("summary", lambda frame: frame_summary(frame, self._rig))
        if made is None:
            return None
        return {**made[0], "serial": made[1], "run_id": made[2]}  # type: ignore[dict-item]
