"""Write a real CFA DNG, as a camera would, for the simulated camera and the tests.

The file is built with pidng's TIFF writer (:class:`pidng.dng.DNG`, ``dngIFD``,
``dngTag``, ``DNGTags`` and the ``Tag`` codes) rather than its ``RAW2DNG`` front end,
which cannot do three things needed here: pack 12-bit rows of odd width (its ``pack12``
assumes an even width), put the EXIF tags in an EXIF sub-IFD where cameras put them
(pidng 4.0.9's IFD-typed tag fails on a str/bytes mix-up, worked around below), and
write to memory for an atomic rename. The image is one uncompressed strip.
"""

from __future__ import annotations

import os
import tempfile
import time
from datetime import datetime
from fractions import Fraction
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike
from pidng.defs import (
    CalibrationIlluminant,
    CFAPattern,
    DNGVersion,
    Orientation,
    PhotometricInterpretation,
)
from pidng.dng import DNG, DNGTags, Tag, Type, dngIFD, dngTag

# LibRaw refuses images narrower or shorter than this (dcraw's sanity check).
MIN_SIDE = 22

_COMPRESSION_NONE = 1
_PLANAR_CHUNKY = 1
# Not in pidng's Tag table: EXIF 2.31's time zone of DateTimeOriginal.
_OFFSET_TIME_ORIGINAL = (36881, Type.Ascii)
_U32_MAX = 2**32 - 1


class _SubIFDTag(dngTag):
    """An IFD-pointer tag (here the EXIF IFD) whose value is a nested :class:`dngIFD`.

    pidng 4.0.9's ``dngTag.setValue`` builds the placeholder of an IFD-typed tag as a
    str and then appends bytes to it (TypeError); the rest of its sub-IFD support
    (layout and writing through ``subIFD``) works, so only the value is set here.
    """

    def setValue(self, value: list[dngIFD]) -> None:  # noqa: N802 - pidng's method name
        self.Value = b"\x00\x00\x00\x00"
        self.subIFD = value[0]


def write_dng(
    path: str | os.PathLike,
    mosaic: np.ndarray,
    *,
    cfa_pattern: str = "RGGB",
    black_level: int | np.ndarray = 64,
    white_level: int = 4095,
    bits_per_sample: int = 12,
    exposure_s: float,
    camera_make: str = "mirrorgonio",
    camera_model: str = "simulated pinhole camera",
    serial: str = "SIM-0001",
    timestamp: float | None = None,
    colour: dict | None = None,
) -> Path:
    """Write ``mosaic`` as a CFA DNG, atomically, and return its path.

    Parameters
    ----------
    path : str or path-like
        Where to write; the folder must exist. The file appears complete or not at all
        (written to a hidden temporary file in the same folder, then renamed), so a
        folder watcher never sees half of it.
    mosaic : ndarray of int, shape (height, width)
        Raw values, each within ``[0, 2**bits_per_sample - 1]``; both sides at least
        :data:`MIN_SIDE` (LibRaw's limit), odd sizes allowed.
    cfa_pattern : {"RGGB", "BGGR", "GRBG", "GBRG"}
        Colours of the 2x2 tile at the mosaic's origin, row-major.
    black_level : int or array_like of int, shape (2, 2)
        One level for all sites, or one per site laid out like ``cfa_pattern``.
        Integers only: pidng writes BlackLevel as SHORT.
    white_level : int
        Saturation level, at most ``2**bits_per_sample - 1``.
    bits_per_sample : {12, 16}
        12 packs two pixels in three bytes, big-endian bit order, each row padded to a
        whole byte, as TIFF does; 16 stores little-endian words.
    exposure_s : float
        Written as the EXIF ExposureTime rational (1/250 s stays exactly 1/250).
    camera_make, camera_model, serial : str
        Make, Model and UniqueCameraModel ("make model") in IFD0; the serial number as
        both the DNG CameraSerialNumber and the EXIF BodySerialNumber.
    timestamp : float, optional
        Capture time, seconds since the epoch (default: now). Written as
        DateTimeOriginal in local time with SubsecTimeOriginal (milliseconds) and
        OffsetTimeOriginal, so it reads back to the millisecond.
    colour : dict, optional
        The camera's colour description (:mod:`drivers.contracts.camera_colour`):
        ColorMatrix1/2 with CalibrationIlluminant1/2 and AsShotNeutral, written as signed
        rationals over 10 000 as camera makers write them. Without it, ColorMatrix1 is the
        identity under D65 (camera RGB taken as XYZ) and the neutral (1, 1, 1).

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    ValueError
        For a mosaic, pattern, level or exposure the file could not hold faithfully.
    """
    path = Path(path)
    mosaic = np.asarray(mosaic)
    shape = _checked_mosaic(mosaic, bits_per_sample)
    cfa_code = _cfa_code(cfa_pattern)
    levels = (_black_sites(black_level, white_level, bits_per_sample), white_level)
    exposure = _exposure_rational(exposure_s)
    local = datetime.fromtimestamp(round(time.time() if timestamp is None else timestamp, 3)).astimezone()
    if bits_per_sample == 12:
        strip = _pack12(mosaic.astype(np.uint16)).tobytes()
    else:
        strip = mosaic.astype("<u2").tobytes()
    camera = (camera_make, camera_model, serial)
    tags = _image_tags(shape, bits_per_sample, len(strip), cfa_code, levels, camera, local)
    _colour_tags(tags, colour)
    exif = _exif_tags(exposure, local, serial)
    return _write_atomically(path, _assemble(tags, strip, _SubIFDTag(Tag.EXIF_IFD, [exif])))


def _image_tags(
    shape: tuple[int, int],
    bits_per_sample: int,
    strip_bytes: int,
    cfa_code: list[int],
    levels: tuple[list[int], int],
    camera: tuple[str, str, str],
    local: datetime,
) -> DNGTags:
    """IFD0's tags: the raw image (one strip of ``strip_bytes``), its CFA, black and white
    ``levels``, the ``camera`` (make, model, serial) and the time it was taken, ``local``."""
    height, width = shape
    black_sites, white_level = levels
    camera_make, camera_model, serial = camera
    tags = DNGTags()
    tags.set(Tag.NewSubfileType, 0)  # the full-resolution raw image
    tags.set(Tag.ImageWidth, width)
    tags.set(Tag.ImageLength, height)
    tags.set(Tag.BitsPerSample, bits_per_sample)
    tags.set(Tag.Compression, _COMPRESSION_NONE)
    tags.set(Tag.PhotometricInterpretation, PhotometricInterpretation.Color_Filter_Array)
    tags.set(Tag.Make, camera_make)
    tags.set(Tag.Model, camera_model)
    tags.set(Tag.StripOffsets, 0)  # set once the layout is known
    tags.set(Tag.Orientation, Orientation.Horizontal)
    tags.set(Tag.SamplesPerPixel, 1)
    tags.set(Tag.RowsPerStrip, height)
    tags.set(Tag.StripByteCounts, strip_bytes)
    tags.set(Tag.PlanarConfiguration, _PLANAR_CHUNKY)
    tags.set(Tag.Software, "mirrorgonio sim_devices.dng")
    tags.set(Tag.DateTime, _exif_date(local))
    tags.set(Tag.CFARepeatPatternDim, [2, 2])
    tags.set(Tag.CFAPattern, cfa_code)
    tags.set(Tag.DNGVersion, DNGVersion.V1_4)
    tags.set(Tag.DNGBackwardVersion, DNGVersion.V1_1)
    tags.set(Tag.UniqueCameraModel, f"{camera_make} {camera_model}".strip())
    tags.set(Tag.BlackLevelRepeatDim, [2, 2])
    tags.set(Tag.BlackLevel, black_sites)
    tags.set(Tag.WhiteLevel, white_level)
    if serial:
        tags.set(Tag.CameraSerialNumber, serial)
    return tags


_RATIONAL_DENOMINATOR = 10_000


def _rationals(values: ArrayLike) -> list[list[int]]:
    return [[round(float(v) * _RATIONAL_DENOMINATOR), _RATIONAL_DENOMINATOR] for v in np.ravel(values)]


def _colour_tags(tags: DNGTags, colour: dict | None) -> None:
    """ColorMatrix1/2, CalibrationIlluminant1/2, ForwardMatrix1/2 and AsShotNeutral from ``colour``;
    without one, the identity under D65 and a neutral of (1, 1, 1)."""
    if not colour:
        tags.set(Tag.ColorMatrix1, _rationals(np.eye(3)))
        tags.set(Tag.CalibrationIlluminant1, CalibrationIlluminant.D65)
        tags.set(Tag.AsShotNeutral, _rationals([1.0, 1.0, 1.0]))
        return
    for k, matrix_tag, illuminant_tag, forward_tag in (
        (1, Tag.ColorMatrix1, Tag.CalibrationIlluminant1, Tag.ForwardMatrix1),
        (2, Tag.ColorMatrix2, Tag.CalibrationIlluminant2, Tag.ForwardMatrix2),
    ):
        if colour.get(f"color_matrix_{k}") is not None:
            tags.set(matrix_tag, _rationals(colour[f"color_matrix_{k}"]))
            tags.set(illuminant_tag, int(colour.get(f"calibration_illuminant_{k}", CalibrationIlluminant.D65)))
        if colour.get(f"forward_matrix_{k}") is not None:
            tags.set(forward_tag, _rationals(colour[f"forward_matrix_{k}"]))
    tags.set(Tag.AsShotNeutral, _rationals(colour.get("as_shot_neutral", [1.0, 1.0, 1.0])))


def _exif_tags(exposure: list[int], local: datetime, serial: str) -> dngIFD:
    """The EXIF sub-IFD: the exposure time as a rational, the time taken to the millisecond
    with its UTC offset, and the body's serial number."""
    offset = local.utcoffset()
    if offset is None:
        raise ValueError("the time taken must be timezone-aware")
    offset_minutes = int(offset.total_seconds() // 60)
    sign = "+" if offset_minutes >= 0 else "-"
    offset_text = f"{sign}{abs(offset_minutes) // 60:02d}:{abs(offset_minutes) % 60:02d}"
    exif = dngIFD()
    exif.tags.append(dngTag(Tag.ExposureTime, [exposure]))
    exif.tags.append(dngTag(Tag.DateTimeOriginal, _exif_date(local)))
    exif.tags.append(dngTag(Tag.SubsecTimeOriginal, f"{local.microsecond // 1000:03d}"))
    exif.tags.append(dngTag(_OFFSET_TIME_ORIGINAL, offset_text))
    if serial:
        exif.tags.append(dngTag(Tag.EXIFPhotoBodySerialNumber, serial))
    return exif


def _exif_date(local: datetime) -> str:
    """A time as EXIF writes it (local time, to the second)."""
    return local.strftime("%Y:%m:%d %H:%M:%S")


def _checked_mosaic(mosaic: np.ndarray, bits_per_sample: int) -> tuple[int, int]:
    if bits_per_sample not in (12, 16):
        raise ValueError(f"bits_per_sample must be 12 or 16, not {bits_per_sample}")
    if mosaic.ndim != 2:
        raise ValueError(f"mosaic must be 2-D, not of shape {mosaic.shape}")
    if not np.issubdtype(mosaic.dtype, np.integer):
        raise ValueError(f"mosaic must hold integers, not {mosaic.dtype}")
    height, width = mosaic.shape
    if min(height, width) < MIN_SIDE:
        raise ValueError(f"mosaic {height}x{width} is smaller than LibRaw reads ({MIN_SIDE}px)")
    if mosaic.size and (mosaic.min() < 0 or mosaic.max() > (1 << bits_per_sample) - 1):
        raise ValueError(f"mosaic values [{mosaic.min()}, {mosaic.max()}] do not fit {bits_per_sample} bits")
    return height, width


def _cfa_code(cfa_pattern: str) -> list[int]:
    code = getattr(CFAPattern, cfa_pattern.upper(), None) if cfa_pattern.isalpha() else None
    if code is None:
        raise ValueError(f"cfa_pattern must be one of RGGB, BGGR, GRBG, GBRG, not {cfa_pattern!r}")
    return list(code)


def _black_sites(black_level: int | np.ndarray, white_level: int, bits_per_sample: int) -> list[int]:
    """The BlackLevel tag's four values, row-major over the 2x2 tile, once the white level is
    known to fit ``bits_per_sample``."""
    max_value = (1 << bits_per_sample) - 1
    if not 0 < white_level <= max_value:
        raise ValueError(f"white_level {white_level} outside (0, {max_value}]")
    levels = np.broadcast_to(np.asarray(black_level), (2, 2)).astype(float)
    if not np.all(levels == np.round(levels)):
        raise ValueError(f"black_level must be integers (pidng writes SHORT), not {levels.tolist()}")
    if levels.min() < 0 or levels.max() >= white_level:
        raise ValueError(f"black_level {levels.tolist()} outside [0, white_level={white_level})")
    return [int(level) for level in levels.flat]


def _exposure_rational(exposure_s: float) -> list[int]:
    """The closest rational with 32-bit terms: 0.004 becomes exactly 1/250."""
    if not (np.isfinite(exposure_s) and exposure_s > 0):
        raise ValueError(f"exposure_s must be a positive number of seconds, not {exposure_s}")
    limit = _U32_MAX if exposure_s < 1 else int(_U32_MAX / exposure_s)
    if limit < 1:
        raise ValueError(f"exposure_s {exposure_s} too long for a TIFF rational")
    fraction = Fraction(float(exposure_s)).limit_denominator(limit)
    if fraction.numerator == 0:
        raise ValueError(f"exposure_s {exposure_s} too short for a TIFF rational")
    return [fraction.numerator, fraction.denominator]


def _pack12(mosaic: np.ndarray) -> np.ndarray:
    """Pack 12-bit values two per three bytes, most significant bits first, per row.

    A row of odd width is packed with one zero pixel added, then cut to the
    ``ceil(width * 1.5)`` bytes TIFF gives it: the last byte held only padding.
    """
    height, width = mosaic.shape
    if width % 2:
        mosaic = np.concatenate([mosaic, np.zeros((height, 1), np.uint16)], axis=1)
    first, second = mosaic[:, 0::2], mosaic[:, 1::2]
    packed = np.empty((height, first.shape[1] * 3), dtype=np.uint8)
    packed[:, 0::3] = first >> 4
    packed[:, 1::3] = ((first & 0x0F) << 4) | (second >> 8)
    packed[:, 2::3] = second & 0xFF
    return packed[:, : (width * 12 + 7) // 8]


def _assemble(tags: DNGTags, strip: bytes, exif_pointer: dngTag) -> bytearray:
    """Lay out IFD0, its EXIF sub-IFD and the strip, as pidng's RAW2DNG does."""
    dng = DNG()
    dng.ImageDataStrips.append(strip)
    ifd = dngIFD()
    # Not through DNGTags.set, which would build the pointer with pidng's broken dngTag.
    ifd.tags.extend([*tags.list(), exif_pointer])
    dng.IFDs.append(ifd)
    total_length = dng.dataLen()  # also computes where the strip goes
    tags.get(Tag.StripOffsets).setValue(list(dng.StripOffsets.values()))
    buffer = bytearray(total_length)
    dng.setBuffer(buffer)
    dng.write()
    return buffer


def _write_atomically(path: Path, data: bytes | bytearray) -> Path:
    # A hidden ".tmp" name in the same folder: no raw suffix, so watchers ignore it,
    # and the same file system, so os.replace is an atomic rename.
    descriptor, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(descriptor, "wb") as file:
            file.write(data)
        os.chmod(temporary, 0o644)  # mkstemp's 0600 would hide the file from other users
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    return path
