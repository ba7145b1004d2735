"""A quick-look PNG of a raw frame: 2x2 superpixels, black removed, tone-mapped, downscaled."""

from __future__ import annotations

import cv2
import numpy as np

from drivers.camera import RawFrame


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
    ok, png = cv2.imencode(".png", (image * 255.0 + 0.5).astype(np.uint8))
    if not ok:  # pragma: no cover - OpenCV refuses only impossible images
        raise ValueError("could not encode the preview")
    return png.tobytes()
