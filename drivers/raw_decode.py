"""Decode a camera's raw file (DNG, NEF, CR2, ARW...) into a :class:`RawFrame`.

One function for every format that LibRaw (through rawpy) reads. The pixels, the black
and white levels and the CFA layout come from LibRaw. The exposure time, the capture time
and the camera's identity come from the file's metadata: the EXIF tags of TIFF-based raws
(DNG, NEF, CR2, ARW, PEF...) read with tifffile, which keeps ExposureTime as the exact
rational the camera wrote; LibRaw's own parse of them for formats that are not TIFF (CR3,
RAF...). Nothing is ever assumed: a file without an exposure time is refused.
"""

from __future__ import annotations

import math
import os
import re
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any, cast

import numpy as np
import rawpy
import tifffile

from drivers.camera import RawFrame
from drivers.contracts.camera_colour import CameraColourError, checked_camera_colour
from drivers.errors import RawFileError

RAW_EXTENSIONS: frozenset[str] = frozenset(
    {
        ".3fr",
        ".arw",
        ".cr2",
        ".cr3",
        ".crw",
        ".dcr",
        ".dng",
        ".erf",
        ".iiq",
        ".kdc",
        ".mef",
        ".mos",
        ".mrw",
        ".nef",
        ".nrw",
        ".orf",
        ".pef",
        ".raf",
        ".rw2",
        ".rwl",
        ".sr2",
        ".srf",
        ".srw",
        ".x3f",
    }
)
"""Lower-case file suffixes of the raw formats :func:`decode_raw` hands to LibRaw.

Some of these formats can hold sensors that are not a 2x2 Bayer mosaic (Fujifilm's
X-Trans in RAF, Foveon in X3F); :func:`decode_raw` refuses those with a clear message
rather than having a watched folder ignore them.
"""

_BAYER_TILES = frozenset({"RGGB", "BGGR", "GRBG", "GBRG"})

# TIFF tag codes read from IFD0 and from the EXIF sub-IFD.
_MAKE, _MODEL, _UNIQUE_CAMERA_MODEL, _CAMERA_SERIAL = 271, 272, 50708, 50735
_EXIF_IFD = 34665
# The DNG colour tags (DNG 1.4 specification, "Camera Profile Tags").
_COLOUR_TAGS = {
    50721: "color_matrix_1",
    50722: "color_matrix_2",
    50778: "calibration_illuminant_1",
    50779: "calibration_illuminant_2",
    50728: "as_shot_neutral",
    50964: "forward_matrix_1",
    50965: "forward_matrix_2",
}
_EXPOSURE_TIME, _DATETIME_ORIGINAL = 33434, 36867
_OFFSET_TIME_ORIGINAL, _SUBSEC_TIME_ORIGINAL, _BODY_SERIAL = 36881, 37521, 42033
_EXIF_NAMES = {
    _EXPOSURE_TIME: "ExposureTime",
    _DATETIME_ORIGINAL: "DateTimeOriginal",
    _OFFSET_TIME_ORIGINAL: "OffsetTimeOriginal",
    _SUBSEC_TIME_ORIGINAL: "SubsecTimeOriginal",
    _BODY_SERIAL: "BodySerialNumber",
}


def decode_raw(path: str | os.PathLike, camera_id: str | None = None, exposure_s: float | None = None) -> RawFrame:
    """Decode one raw file into its visible Bayer mosaic and the metadata it needs.

    Parameters
    ----------
    path : str or path-like
        The raw file (any format LibRaw reads; see :data:`RAW_EXTENSIONS`).
    camera_id : str, optional
        Identity to record when the file names no camera (no Make, Model or
        UniqueCameraModel tag). A camera named in the file always wins.
    exposure_s : float, optional
        The exposure time known from elsewhere (an import CSV's ``exposure_s``): it is
        the frame's, whatever the file says, and a file without one is then accepted
        (``extra["exposure_source"]`` says "given"; the file's own, if any, is kept in
        ``extra["file_exposure_s"]``).

    Returns
    -------
    RawFrame
        ``mosaic`` is a copy of LibRaw's visible raw area as uint16; ``black_level`` is
        laid out like the 2x2 CFA tile at the mosaic's origin; ``exposure_s`` and
        ``timestamp`` come from the file. ``extra`` records where the exposure and the
        time were read (``exposure_source``, ``timestamp_source``), and make, model,
        serial number, ISO and aperture where the file has them; ``extra["colour"]`` the
        camera's colour matrices (:mod:`drivers.contracts.camera_colour`): a DNG's
        ColorMatrix1/2 tags, else LibRaw's matrix for the model (D65), absent where neither
        is known.

    Raises
    ------
    RawFileError
        One line naming the file: it is missing, empty, not a raw file, truncated, not
        a 2x2 Bayer mosaic (X-Trans, Foveon, monochrome, linear DNG), or holds no
        exposure time and none is given.
    """
    if exposure_s is not None and not (math.isfinite(exposure_s) and exposure_s > 0):
        raise ValueError(f"exposure_s must be a positive number of seconds, not {exposure_s!r}")
    path = Path(path)
    source = str(path)
    size = _checked_size(path, source)
    tiff = _read_tiff_metadata(path)

    try:
        with rawpy.imread(source) as raw:
            mosaic, black_level, cfa_pattern = _read_mosaic(raw, source)
            white_level = int(raw.white_level)
            libraw_other = raw.other
            libraw_xyz_to_camera = np.array(raw.rgb_xyz_matrix, dtype=float)[:3]
    except rawpy.LibRawError as exc:
        raise RawFileError(source, "decode", _libraw_failure(exc, path, size, tiff)) from None

    file_exposure_s, exposure_source = _exposure_time(tiff, libraw_other.shutter_speed)
    if exposure_s is None:
        if file_exposure_s is None:
            raise RawFileError(source, "decode", "no exposure time in the file's metadata")
        exposure_s = file_exposure_s
    else:
        exposure_source = "given"
    timestamp, timestamp_source = _capture_time(tiff, libraw_other.timestamp, path)
    make, model, serial, unique_model = _camera_tags(tiff)

    sources: dict[str, str | float] = {"exposure_source": exposure_source, "timestamp_source": timestamp_source}
    if exposure_source == "given" and file_exposure_s is not None:
        sources["file_exposure_s"] = file_exposure_s
    extra = _frame_extra(sources, (make, model, serial, unique_model), libraw_other)
    colour = _camera_colour(tiff, libraw_xyz_to_camera)
    if colour:
        extra["colour"] = colour

    return RawFrame(
        mosaic=mosaic,
        black_level=black_level,
        white_level=white_level,
        cfa_pattern=cfa_pattern,
        exposure_s=exposure_s,
        timestamp=timestamp,
        camera_id=_camera_identity(make, model, unique_model, serial) or camera_id or "unknown camera",
        source=source,
        extra=extra,
    )


def _checked_size(path: Path, source: str) -> int:
    """The file's size, or a RawFileError saying why there is no file to decode."""
    try:
        stat = path.stat()
    except FileNotFoundError:
        raise RawFileError(source, "decode", "no such file") from None
    except OSError as exc:
        raise RawFileError(source, "decode", exc.strerror or type(exc).__name__) from None
    if not path.is_file():
        raise RawFileError(source, "decode", "not a regular file")
    if stat.st_size == 0:
        raise RawFileError(source, "decode", "empty file")
    return stat.st_size


def _read_mosaic(raw: rawpy.RawPy, source: str) -> tuple[np.ndarray, np.ndarray, str]:
    """Copy the visible mosaic, and name its CFA tile and black level per tile site."""
    if raw.raw_type != rawpy.RawType.Flat:
        raise RawFileError(source, "decode", "not a CFA mosaic (a linear or demosaiced raw, e.g. linear DNG)")
    try:
        pattern = raw.raw_pattern
    except NotImplementedError as exc:
        raise RawFileError(source, "decode", f"unsupported CFA layout ({exc})") from None
    if pattern is None or pattern.shape != (2, 2):
        n = 0 if pattern is None else pattern.shape[0]
        sensor = {0: "a sensor without CFA", 1: "a monochrome sensor", 6: "an X-Trans sensor"}
        raise RawFileError(
            source,
            "decode",
            f"{sensor.get(n, f'a {n}x{n} CFA')} is not a 2x2 Bayer mosaic",
        )

    sizes = raw.sizes
    # raw_color takes coordinates in the full raw image; asking at the visible area's
    # origin gives the tile of the mosaic returned, whatever the margins' parity.
    color_index = np.array(
        [[raw.raw_color(sizes.top_margin + row, sizes.left_margin + col) for col in (0, 1)] for row in (0, 1)]
    )
    color_desc = raw.color_desc.decode("ascii", "replace")
    tile = "".join(color_desc[index] for index in color_index.flat)
    if tile not in _BAYER_TILES:
        raise RawFileError(source, "decode", f"CFA tile {tile!r} is not an RGB Bayer pattern")
    # LibRaw gives one black level per colour index (the two greens have their own).
    per_channel = np.asarray(raw.black_level_per_channel, dtype=float)
    black_level = per_channel[color_index]

    visible = raw.raw_image_visible
    if visible.ndim != 2:
        raise RawFileError(source, "decode", "not a single-plane CFA mosaic")
    # Copy: the array is a view into LibRaw's buffer, freed when the file is closed.
    mosaic = np.array(visible, dtype=np.uint16, copy=True)
    return mosaic, black_level, tile


class _TiffMetadata:
    """The tags used from IFD0 and the EXIF sub-IFD, keyed by tag code.

    Empty for files that are not TIFF-based (``readable`` false); ``structure_error``
    says why tifffile could not read a file that starts like a TIFF.
    """

    def __init__(self) -> None:
        self.readable = False
        self.ifd0: dict[int, Any] = {}
        self.exif: dict[int, Any] = {}
        self.structure_error: str = ""


def _read_tiff_metadata(path: Path) -> _TiffMetadata:
    metadata = _TiffMetadata()
    try:
        with open(path, "rb") as file:
            header = file.read(4)
    except OSError:
        return metadata
    if header[:2] not in (b"II", b"MM"):
        return metadata  # CR3, RAF, a PNG...: LibRaw reads what it can of these
    try:
        with tifffile.TiffFile(path) as tif:
            page = cast(tifffile.TiffPage, tif.pages[0])  # tifffile loads the first page as a TiffPage
            for code in (_MAKE, _MODEL, _UNIQUE_CAMERA_MODEL, _CAMERA_SERIAL, *_EXIF_NAMES, *_COLOUR_TAGS):
                tag = page.tags.get(code)
                if tag is not None:
                    metadata.ifd0[code] = tag.value
            exif_tag = page.tags.get(_EXIF_IFD)
            if exif_tag is not None and isinstance(exif_tag.value, dict):
                for code, name in _EXIF_NAMES.items():
                    value = exif_tag.value.get(name, exif_tag.value.get(str(code)))
                    if value is not None:
                        metadata.exif[code] = value
            metadata.readable = True
    except Exception as exc:  # noqa: BLE001 - tifffile raises many kinds on odd raws
        # ORF and RW2 start like a TIFF but are not one; a cut file fails here too.
        metadata.structure_error = f"{type(exc).__name__}: {exc}".splitlines()[0]
    return metadata


def _image_data_end(path: Path) -> int:
    """Where the last strip or tile of any IFD or SubIFD ends, in bytes (0 if unknown).

    Only asked once LibRaw has failed: reading every IFD of a healthy NEF is wasted
    time, and tifffile logs warnings about some makers' private IFDs.
    """
    end = 0
    try:
        with tifffile.TiffFile(path) as tif:
            for page in tif.pages:
                for sub in (page, *(getattr(page, "pages", None) or ())):
                    offsets = getattr(sub, "dataoffsets", ()) or ()
                    counts = getattr(sub, "databytecounts", ()) or ()
                    for offset, count in zip(offsets, counts, strict=False):
                        end = max(end, int(offset) + int(count))
    except Exception:  # noqa: BLE001 - the caller then reports the structure error
        return 0
    return end


def _libraw_failure(exc: rawpy.LibRawError, path: Path, size: int, tiff: _TiffMetadata) -> str:
    """One line saying why LibRaw could not decode the file."""
    message = exc.args[0] if exc.args else str(exc)
    if isinstance(message, bytes):
        message = message.decode("utf-8", "replace")
    message = " ".join(str(message).split())
    if isinstance(exc, rawpy.LibRawFileUnsupportedError):
        return f"not a raw file LibRaw can decode (LibRaw: {message})"
    if tiff.readable:
        data_end = _image_data_end(path)
        if data_end > size:
            return (
                f"truncated: its image data ends at byte {data_end} but the file has {size} bytes (LibRaw: {message})"
            )
    if tiff.structure_error:
        return f"truncated or corrupt: its TIFF structure cannot be read ({tiff.structure_error}; LibRaw: {message})"
    return f"unreadable, truncated or not a raw file (LibRaw: {message})"


def _exposure_time(tiff: _TiffMetadata, libraw_shutter: float) -> tuple[float | None, str]:
    """The exposure time in seconds and where it was read, or (None, "")."""
    for where, tags in (("exif", tiff.exif), ("ifd0", tiff.ifd0)):
        seconds = _rational_seconds(tags.get(_EXPOSURE_TIME))
        if seconds is not None:
            return seconds, f"ExposureTime tag ({where})"
    # LibRaw parses ExposureTime (or maker notes) of non-TIFF formats too, but keeps
    # it as float32: round to the ~7 significant digits that float32 carries so 1/250
    # comes back as 0.004, not 0.0040000002.
    if libraw_shutter and libraw_shutter > 0:
        return _float32_to_decimal(libraw_shutter), "LibRaw"
    return None, ""


def _rational_seconds(value: Any) -> float | None:
    """A positive exposure from a TIFF RATIONAL (num, den) or a number, else None."""
    if value is None:
        return None
    if isinstance(value, tuple | list) and len(value) == 2:
        numerator, denominator = value
        if not denominator:
            return None
        seconds = float(numerator) / float(denominator)
    elif isinstance(value, int | float):
        seconds = float(value)
    else:
        return None
    return seconds if np.isfinite(seconds) and seconds > 0 else None


def _float32_to_decimal(value: float) -> float:
    return float(f"{float(value):.7g}")


def _capture_time(tiff: _TiffMetadata, libraw_time: datetime, path: Path) -> tuple[float, str]:
    """Seconds since the epoch from DateTimeOriginal, else the file's mtime."""
    for tags in (tiff.exif, tiff.ifd0):
        stamp = _exif_datetime(
            tags.get(_DATETIME_ORIGINAL),
            tags.get(_SUBSEC_TIME_ORIGINAL),
            tags.get(_OFFSET_TIME_ORIGINAL),
        )
        if stamp is not None:
            return stamp, "DateTimeOriginal"
    # LibRaw leaves the epoch (0) when it found no date; it reads local time like EXIF.
    libraw_seconds = libraw_time.timestamp()
    if libraw_seconds > 0:
        return libraw_seconds, "LibRaw"
    return path.stat().st_mtime, "file mtime"


def _exif_datetime(value: Any, subsec: Any, offset: Any) -> float | None:
    text = _text(value)
    if not text:
        return None
    try:
        moment = datetime.strptime(text[:19], "%Y:%m:%d %H:%M:%S")
    except ValueError:
        return None  # "0000:00:00 00:00:00" and other placeholders cameras write
    digits = re.sub(r"\D", "", _text(subsec))
    if digits:
        moment += timedelta(seconds=int(digits) / 10 ** len(digits))
    zone = re.fullmatch(r"([+-])(\d{2}):(\d{2})", _text(offset))
    if zone:
        sign = 1 if zone.group(1) == "+" else -1
        delta = timedelta(hours=int(zone.group(2)), minutes=int(zone.group(3)))
        moment = moment.replace(tzinfo=timezone(sign * delta))
    # Without OffsetTimeOriginal the time is the camera's local time, taken as ours.
    return moment.timestamp()


def _text(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    return " ".join(str(value).replace("\x00", " ").split())


def _frame_extra(sources: dict[str, Any], camera: tuple[str, str, str, str], libraw_other: Any) -> dict[str, Any]:
    """A frame's ``extra``: where its exposure and time were read (``sources``), then the
    camera's make, model, serial and unique model name, ISO and f-number where known."""
    extra = dict(sources)
    for key, value in zip(("make", "model", "serial", "unique_camera_model"), camera, strict=True):
        if value:
            extra[key] = value
    if libraw_other.iso_speed > 0:
        extra["iso"] = float(libraw_other.iso_speed)
    if libraw_other.aperture > 0:
        extra["f_number"] = _float32_to_decimal(libraw_other.aperture)
    return extra


def _rationals(value: Any) -> list[float]:
    """A TIFF (S)RATIONAL tag's values as floats: tifffile gives them flat, numerator then denominator."""
    flat = [float(v) for v in np.ravel(np.asarray(value, dtype=float))]
    return [n / d for n, d in zip(flat[0::2], flat[1::2], strict=True) if d != 0]


def _camera_colour(tiff: _TiffMetadata, libraw_xyz_to_camera: np.ndarray) -> dict[str, Any]:
    """The camera's colour description: the DNG colour tags, else LibRaw's XYZ → camera matrix
    for the model (Adobe's, under D65), else nothing. A tag that is not what the DNG
    specification says (a matrix of other than nine numbers, say) leaves the colour unknown."""
    tags = {name: tiff.ifd0[code] for code, name in _COLOUR_TAGS.items() if code in tiff.ifd0}
    description: dict[str, Any] = {}
    try:
        if "color_matrix_1" in tags:
            description["source"] = "DNG tags"
            for name, value in tags.items():
                if name.startswith("calibration_illuminant"):
                    description[name] = int(value)
                elif name == "as_shot_neutral":
                    description[name] = _rationals(value)
                else:
                    values = _rationals(value)
                    description[name] = [values[0:3], values[3:6], values[6:9]] if len(values) == 9 else None
        elif libraw_xyz_to_camera.shape == (3, 3) and np.any(libraw_xyz_to_camera):
            description = {
                "source": "LibRaw",
                "color_matrix_1": libraw_xyz_to_camera.tolist(),
                "calibration_illuminant_1": 21,
            }
        return checked_camera_colour(description)
    except (CameraColourError, TypeError, ValueError):
        return {}


def _camera_tags(tiff: _TiffMetadata) -> tuple[str, str, str, str]:
    """The camera's make, model, serial number and unique model name ("" where the file has none)."""
    make = _text(tiff.ifd0.get(_MAKE))
    model = _text(tiff.ifd0.get(_MODEL))
    serials = (
        _text(tiff.exif.get(_BODY_SERIAL)),
        _text(tiff.ifd0.get(_BODY_SERIAL)),
        _text(tiff.ifd0.get(_CAMERA_SERIAL)),
    )
    serial = next((text for text in serials if text), "")
    return make, model, serial, _text(tiff.ifd0.get(_UNIQUE_CAMERA_MODEL))


def _camera_identity(make: str, model: str, unique_model: str, serial: str) -> str:
    """ "Make Model, serial N", without repeating the make that many models start with."""
    if model and make and model.lower().startswith(make.split()[0].lower()):
        name = model
    else:
        name = " ".join(part for part in (make, model) if part) or unique_model
    if not name:
        return ""
    return f"{name}, serial {serial}" if serial else name
