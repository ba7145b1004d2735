"""Image outputs: OpenEXR for radiance, tone-mapped PNG for people.

One of each is written per position, inside the position's task (one core), so the
settings are the fast ones. Measured on a 656x1000 mirror-ball preview, one core: the EXR
uncompressed (OpenEXR's NO_COMPRESSION) 13 ms, 7.9 MB — PIZ 42 ms, 1.75 MB; RLE 31 ms,
6.5 MB; ZIP 67 ms, 1.5 MB (``compression=`` picks one).

The PNG is encoded here (:func:`encode_png`: no row filter, the rows deflated by ISA-L,
``isal``, at level 1, in four chunks) rather than by ``cv2.imencode``, because a position's
task writes one and OpenCV's libpng takes 2.4 to 8 times as long. Measured on a
tone-mapped mirror-ball preview, one core, median of 20: 1000x656 (the preview's size),
ISA-L 4.8 ms for 751 kB; ``cv2.imencode`` (OpenCV 5.0) at its fastest (level 1, no row filter, Huffman
coding only) 16 ms for 771 kB, at level 1 with its default filters 37 ms for 832 kB; the
full 2000x1312 frame, 27 ms against 66 ms and 162 ms. A position's task takes about 106 ms,
its images 20 ms of that: OpenCV would add a tenth to every position.

The tone mapping is one compiled pass over the image (4 ms; 16 ms in NumPy's temporaries).
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import cv2
import numba
import numpy as np
import OpenEXR
from isal import isal_zlib

#: The lossless OpenEXR compressions :func:`write_exr` takes.
EXR_COMPRESSIONS = {
    "none": OpenEXR.NO_COMPRESSION,
    "rle": OpenEXR.RLE_COMPRESSION,
    "zips": OpenEXR.ZIPS_COMPRESSION,
    "zip": OpenEXR.ZIP_COMPRESSION,
    "piz": OpenEXR.PIZ_COMPRESSION,
}
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _rgb_float32(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"an RGB image is (H, W, 3), not {rgb.shape}")
    return np.ascontiguousarray(rgb, dtype=np.float32)


def write_exr(
    path: str | Path, rgb: np.ndarray, compression: str = "none", *, attributes: Mapping[str, Any] | None = None
) -> Path:
    """Write a linear float32 RGB image (H, W, 3) as a lossless OpenEXR file.

    Non-finite values (no usable sample) are written as 0. ``compression`` is one of
    :data:`EXR_COMPRESSIONS`; "none" (the default, one file per position) writes in a third
    of PIZ's time for 4.5 times the bytes. ``attributes`` go into the header: str, int,
    float, float arrays (``numpy.float32``: a vector), lists of str, and the standard ones as
    OpenEXR types them (``chromaticities``: 8 floats, the CIE xy of R, G, B and white).
    """
    if compression not in EXR_COMPRESSIONS:
        raise ValueError(f"EXR compression: {compression!r} is not one of {', '.join(EXR_COMPRESSIONS)}")
    path = Path(path)
    data = _rgb_float32(rgb)
    finite = np.isfinite(data)
    if not finite.all():
        data = np.where(finite, data, np.float32(0.0))
    header = {**(attributes or {}), "compression": EXR_COMPRESSIONS[compression], "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"RGB": data}) as exr:
        exr.write(str(path))
    return path


def read_exr(path: str | Path) -> np.ndarray:
    with OpenEXR.File(str(path)) as exr:
        return np.array(exr.channels()["RGB"].pixels, dtype=np.float32)


@numba.njit(cache=True)
def _tonemap_kernel(rows, scale, out):
    """``out = uint8(sqrt(clip(x / scale, 0, 1)) * 255 + 0.5)``, non-finite ``x`` as 0, in
    float32 as NumPy computes it: one pass, no temporaries."""
    s = np.float32(scale)
    zero, one, top = np.float32(0.0), np.float32(1.0), np.float32(3.4028234663852886e38)
    for i in range(rows.shape[0]):
        row, dest = rows[i], out[i]
        for j in range(row.shape[0]):
            v = row[j]
            t = min(max(v / s, zero), one) if abs(v) <= top else zero
            dest[j] = np.uint8(np.sqrt(t) * np.float32(255.0) + np.float32(0.5))


def tone_scale(rgb: np.ndarray, percentile: float = 99.9) -> float:
    """The radiance shown as white: a high percentile of the finite values (non-finite count
    as 0), taken on every fourth row and column of a large image — a sixteenth of the
    pixels, the same statistic for a preview at a quarter of the cost."""
    sample = rgb[::4, ::4] if rgb.shape[0] * rgb.shape[1] > 250_000 else rgb
    sample = np.where(np.isfinite(sample), sample, np.float32(0.0))
    scale = float(np.percentile(sample, percentile)) if sample.size else 0.0
    if scale <= 0:
        finite = np.where(np.isfinite(rgb), rgb, np.float32(0.0))
        scale = max(float(finite.max(initial=0.0)), 1e-30)
    return scale


def tonemap(rgb: np.ndarray, percentile: float = 99.9) -> np.ndarray:
    """8-bit sRGB-ish view of linear radiance: scaled to a high percentile
    (:func:`tone_scale`), then the square root, which keeps a mirror ball's bright sources
    and their faint halo visible. Non-finite values show as 0."""
    data = _rgb_float32(rgb)
    h, w, _ = data.shape
    out = np.empty(data.shape, np.uint8)
    _tonemap_kernel(data.reshape(h, 3 * w), tone_scale(data, percentile), out.reshape(h, 3 * w))
    return out


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(data, zlib.crc32(kind)))


def encode_png(image: np.ndarray, level: int = 1) -> bytes:
    """An 8-bit RGB image (H, W, 3) as PNG bytes (ISO/IEC 15948): no row filter, the rows
    deflated into one zlib stream by ISA-L at ``level`` (0-3)."""
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3 or 0 in image.shape:
        raise ValueError(f"a PNG is written from (H, W, 3) uint8, not {image.shape} {image.dtype}")
    h, w, _ = image.shape
    rows = np.empty((h, 1 + 3 * w), np.uint8)
    rows[:, 0] = 0  # filter type "None" before every row
    rows[:, 1:] = image.reshape(h, 3 * w)
    header = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)  # 8 bits, truecolour, deflate, no interlace
    return b"".join(
        (
            _PNG_SIGNATURE,
            _png_chunk(b"IHDR", header),
            _png_chunk(b"IDAT", isal_zlib.compress(rows, level)),
            _png_chunk(b"IEND", b""),
        )
    )


def write_png(path: str | Path, rgb: np.ndarray, max_width: int = 1000) -> Path:
    """Tone-mapped PNG preview of linear RGB radiance (at most ``max_width`` pixels wide)."""
    path = Path(path)
    image = tonemap(rgb)
    if image.shape[1] > max_width:
        size = (max_width, max(1, round(image.shape[0] * max_width / image.shape[1])))
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    try:
        path.write_bytes(encode_png(image))
    except OSError as exc:
        raise OSError(f"{path}: could not write the PNG: {exc.strerror or exc}") from None
    return path
