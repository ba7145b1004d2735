"""A camera on USB driven through libgphoto2 (python-gphoto2), shooting raw.

libgphoto2 has no portable exposure-bracketing command, so each capture sets the
camera's ``shutterspeed`` to the nearest step it offers, captures, and downloads. With
RAW+JPEG the capture returns one file and announces the other as a
``GP_EVENT_FILE_ADDED`` event; both are downloaded and the raw one is decoded. A camera
busy writing its card answers ``GP_ERROR_CAMERA_BUSY`` for about a second: every call is
retried for a while before that counts as a failure.

python-gphoto2 is an optional dependency (``pip install 'mirrorgonio[gphoto2]'``); it is
imported when the camera connects, so this module imports without it.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import re
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any, TypeVar

from drivers.camera import Camera, RawFrame
from drivers.errors import CommunicationError, DeviceError, DeviceTimeoutError
from drivers.raw_decode import RAW_EXTENSIONS, decode_raw

log = logging.getLogger(__name__)

_T = TypeVar("_T")

# Once the raw file is in, the capture is over when the event queue stays quiet this
# long (the JPEG of RAW+JPEG is announced just before or after the raw), or at the
# latest after _DRAIN_S: some bodies keep sending property-change events for a while.
_QUIET_MS = 250
_DRAIN_S = 1.0

_FRACTION = re.compile(r"(\d+(?:\.\d+)?)\s*/\s*(\d+(?:\.\d+)?)")
_SECONDS_MARK = re.compile(r"(\d+)\"(\d*)")  # Canon and Sony: 1"3 is 1.3 s, 30" is 30 s
_DECIMAL = re.compile(r"\d+(?:\.\d+)?|\.\d+")


def parse_shutter_speed(text: str) -> float | None:
    """Seconds that a camera's ``shutterspeed`` choice stands for, or None.

    Understands ``"1/250"``, ``"0.5"``, ``"2"``, ``"30"``, ``'1"3'`` (1.3 s),
    ``'30"'``, decimal commas and trailing ``s``/``sec``. Choices that are not a
    timed exposure (``"bulb"``, ``"time"``, ``"auto"``, ``"x 1/200"``) give None.

    Examples
    --------
    >>> parse_shutter_speed("1/250")
    0.004
    >>> parse_shutter_speed('1"3')
    1.3
    >>> parse_shutter_speed("bulb") is None
    True
    """
    cleaned = text.strip().lower().replace(",", ".")
    cleaned = re.sub(r"\s*(seconds|second|secs|sec|s)$", "", cleaned)
    seconds: float | None = None
    if match := _FRACTION.fullmatch(cleaned):
        numerator, denominator = float(match.group(1)), float(match.group(2))
        seconds = numerator / denominator if denominator else None
    elif match := _SECONDS_MARK.fullmatch(cleaned):
        seconds = float(f"{match.group(1)}.{match.group(2) or '0'}")
    elif _DECIMAL.fullmatch(cleaned):
        seconds = float(cleaned)
    if seconds is None or not math.isfinite(seconds) or seconds <= 0:
        return None
    return seconds


def nearest_shutter_choice(choices: Iterable[str], exposure_s: float) -> str:
    """The timed choice nearest to ``exposure_s`` in stops (log2 of the time).

    Requests beyond the camera's range get its shortest or longest timed speed; a tie
    goes to the shorter time, which cannot saturate more than asked.

    Raises
    ------
    ValueError
        ``exposure_s`` is not positive, or no choice is a timed exposure.
    """
    if not (math.isfinite(exposure_s) and exposure_s > 0):
        raise ValueError(f"exposure_s must be a positive number of seconds, not {exposure_s}")
    choices = list(choices)
    timed = [(seconds, choice) for choice in choices if (seconds := parse_shutter_speed(choice))]
    if not timed:
        raise ValueError(f"no timed shutter speed among the choices {choices!r}")
    target = math.log2(exposure_s)
    return min(timed, key=lambda item: (abs(math.log2(item[0]) - target), item[0]))[1]


class Gphoto2Camera(Camera):
    """A camera driven over USB with python-gphoto2, capturing raw files.

    Set the camera to manual exposure (M), raw or RAW+JPEG quality, and (for speed)
    capture target to its internal RAM or card as you prefer: files are downloaded
    either way and left on the card.

    Parameters
    ----------
    port : str, optional
        libgphoto2 port such as ``"usb:001,007"`` (``gphoto2 --auto-detect``), to pick
        one of several cameras. Default: the first camera found.
    model : str, optional
        Model name as libgphoto2 spells it (``"Nikon DSC D850"``); with ``port``, skips
        detection; alone, picks the detected camera of that model.
    download_dir : str or path-like
        Where captured files are saved (created if missing); a name the camera reuses
        gets a ``-1``, ``-2``... suffix rather than overwriting.
    busy_retries : int
        How many times a call answered ``GP_ERROR_CAMERA_BUSY`` is retried.
    busy_wait_s : float
        Pause before each of those retries.
    name : str, optional
        Device name for error messages (default: "gphoto2 camera", with the port).
    event_timeout_s : float
        How long to wait for the raw file's ``GP_EVENT_FILE_ADDED`` after a capture.
    clock, sleep : callable
        Monotonic clock and sleep, replaceable in tests.
    """

    def __init__(
        self,
        *,
        port: str | None = None,
        model: str | None = None,
        download_dir: str | os.PathLike,
        busy_retries: int = 10,
        busy_wait_s: float = 0.2,
        name: str | None = None,
        event_timeout_s: float = 10.0,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ):
        self.port = port
        self.model = model
        self.download_dir = Path(download_dir)
        self.busy_retries = int(busy_retries)
        self.busy_wait_s = float(busy_wait_s)
        self.name = name or ("gphoto2 camera" + (f" at {port}" if port else ""))
        self.event_timeout_s = float(event_timeout_s)
        self._clock = clock
        self._sleep = sleep
        self._gp: Any = None
        self._camera: Any = None
        self._identity = ""

    @property
    def identity(self) -> str:
        """Model and serial number from the camera's abilities and summary."""
        return self._identity or self.name

    def problem(self) -> str | None:
        """No session with the camera (never connected, or lost and closed)."""
        return None if self._camera is not None else "no session with the camera"

    def connect(self) -> None:
        """Import python-gphoto2, find the camera and open a session with it."""
        if self._camera is not None:
            return
        try:
            import gphoto2 as gp  # noqa: PLC0415 - optional: the gphoto2 extra
        except ImportError:
            raise DeviceError(
                self.name,
                "connect",
                "python-gphoto2 is not installed (pip install 'mirrorgonio[gphoto2]')",
            ) from None
        self._gp = gp
        try:
            self.download_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            cause = f"cannot create {self.download_dir}: {exc.strerror or type(exc).__name__}"
            raise DeviceError(self.name, "connect", cause) from None
        camera = gp.Camera()
        try:
            if self.port or self.model:
                self._select(camera)
            self._retry_busy(camera.init)
        except gp.GPhoto2Error as exc:
            raise self._error("connect", exc) from None
        self._camera = camera
        try:
            self._identity = self._read_identity()
        except gp.GPhoto2Error as exc:
            self.close()  # do not leave the USB interface claimed
            raise self._error("connect", exc) from None

    def close(self) -> None:
        """End the session; the camera is released even if it no longer answers."""
        camera, self._camera = self._camera, None
        if camera is None:
            return
        try:
            camera.exit()
        except self._gp.GPhoto2Error as exc:
            # Nothing to do about it: the session is gone either way (often unplugged).
            log.warning("%s: close: %s", self.name, exc)

    def capture(self, exposure_s: float) -> RawFrame:
        """Set the nearest shutter speed, capture, download, decode the raw file.

        The returned frame's ``exposure_s`` is the one the camera recorded in the file;
        ``extra`` adds ``requested_exposure_s``, ``shutterspeed_choice`` and the other
        files of the capture (``companion_files``, e.g. the JPEG of RAW+JPEG).
        """
        if not (math.isfinite(exposure_s) and exposure_s > 0):
            raise ValueError(f"exposure_s must be a positive number of seconds, not {exposure_s}")
        camera = self._connected("capture")
        gp = self._gp
        try:
            choice = self._set_shutter_speed(camera, exposure_s)
            captured = self._retry_busy(lambda: camera.capture(gp.GP_CAPTURE_IMAGE))
            on_camera = [(captured.folder, captured.name)]
            on_camera += self._files_added(camera, have_raw=_is_raw(captured.name))
            saved = [self._download(camera, folder, name) for folder, name in on_camera]
        except self._gp.GPhoto2Error as exc:
            raise self._error("capture", exc) from None
        raws = [path for path in saved if _is_raw(path.name)]
        if not raws:
            names = ", ".join(path.name for path in saved)
            raise DeviceError(
                self.name,
                "capture",
                f"the camera saved no raw file (only {names}): set its quality to RAW or RAW+JPEG",
            )
        frame = decode_raw(raws[0], camera_id=self._identity or None)
        frame.extra.update(
            requested_exposure_s=float(exposure_s),
            shutterspeed_choice=choice,
            companion_files=[str(path) for path in saved if path != raws[0]],
        )
        return frame

    # -- session ------------------------------------------------------------------

    def _connected(self, command: str) -> Any:
        if self._camera is None:
            raise DeviceError(self.name, command, "not connected (call connect() first)")
        return self._camera

    def _select(self, camera: Any) -> None:
        """Point the session at the requested port and model, detecting what is missing."""
        gp = self._gp
        port, model = self.port, self.model
        if port is None or model is None:
            detected = gp.Camera.autodetect()
            found = [(detected.get_name(i), detected.get_value(i)) for i in range(detected.count())]
            matches = [
                (found_model, found_port)
                for found_model, found_port in found
                if (model is None or found_model == model) and (port is None or found_port == port)
            ]
            if not matches:
                listing = "; ".join(f"{m} at {p}" for m, p in found) or "none"
                wanted = f"model {model!r}" if model else f"port {port!r}"
                raise DeviceError(self.name, "connect", f"no camera with {wanted} detected (detected: {listing})")
            model, port = matches[0]
        abilities = gp.CameraAbilitiesList()
        abilities.load()
        try:
            model_index = abilities.lookup_model(model)
        except gp.GPhoto2Error:
            cause = f"libgphoto2 knows no model {model!r}"
            raise DeviceError(self.name, "connect", cause) from None
        camera.set_abilities(abilities.get_abilities(model_index))
        ports = gp.PortInfoList()
        ports.load()
        try:
            port_index = ports.lookup_path(port)
        except gp.GPhoto2Error:
            cause = f"no port {port!r} (see gphoto2 --auto-detect)"
            raise DeviceError(self.name, "connect", cause) from None
        camera.set_port_info(ports.get_info(port_index))

    def _read_identity(self) -> str:
        model = str(self._camera.get_abilities().model).strip()
        summary = str(self._camera.get_summary())
        serial = re.search(r"^\s*Serial Number:\s*(\S.*?)\s*$", summary, re.MULTILINE)
        if serial and serial.group(1).strip("0"):
            return f"{model}, serial {serial.group(1)}"
        return model

    # -- capture steps --------------------------------------------------------------

    def _set_shutter_speed(self, camera: Any, exposure_s: float) -> str:
        gp = self._gp
        config = self._retry_busy(camera.get_config)
        try:
            widget = config.get_child_by_name("shutterspeed")
        except gp.GPhoto2Error:
            raise DeviceError(self.name, "capture", "the camera has no 'shutterspeed' setting") from None
        choices: Sequence[str] = [str(choice) for choice in widget.get_choices()]
        try:
            choice = nearest_shutter_choice(choices, exposure_s)
        except ValueError as exc:
            raise DeviceError(self.name, "capture", f"{exc} (is the camera in manual exposure mode?)") from None
        if widget.get_value() == choice:
            return choice
        if widget.get_readonly():
            raise DeviceError(
                self.name,
                "capture",
                "shutterspeed is read-only: set the camera to manual exposure (M)",
            )
        widget.set_value(choice)
        try:
            self._retry_busy(lambda: camera.set_single_config("shutterspeed", widget))
        except gp.GPhoto2Error as exc:
            if exc.code != gp.GP_ERROR_NOT_SUPPORTED:
                raise
            self._retry_busy(lambda: camera.set_config(config))  # libgphoto2 < 2.5.10
        return choice

    def _files_added(self, camera: Any, *, have_raw: bool) -> list[tuple[str, str]]:
        """Files the camera announces after a capture, at least until one is raw."""
        gp = self._gp
        added: list[tuple[str, str]] = []
        deadline = self._clock() + (_DRAIN_S if have_raw else self.event_timeout_s)
        while (remaining := deadline - self._clock()) > 0:
            wait_ms = _QUIET_MS if have_raw else max(1, min(1000, int(remaining * 1000)))
            event_type, data = self._retry_busy(functools.partial(camera.wait_for_event, wait_ms))
            if event_type == gp.GP_EVENT_FILE_ADDED:
                added.append((data.folder, data.name))
                if not have_raw and _is_raw(data.name):
                    have_raw = True
                    deadline = min(deadline, self._clock() + _DRAIN_S)
            elif event_type == gp.GP_EVENT_TIMEOUT and have_raw:
                break
        if not have_raw:
            names = ", ".join(name for _, name in added) or "none"
            raise DeviceTimeoutError(
                self.name,
                "capture",
                f"no raw file announced within {self.event_timeout_s:g} s of the capture "
                f"(other files announced: {names}): set the camera's quality to RAW or RAW+JPEG",
            )
        return added

    def _download(self, camera: Any, folder: str, name: str) -> Path:
        gp = self._gp
        camera_file = self._retry_busy(lambda: camera.file_get(folder, name, gp.GP_FILE_TYPE_NORMAL))
        target = _unused_path(self.download_dir / name)
        partial = target.with_name(f".{target.name}.part")  # hidden from folder watchers
        camera_file.save(str(partial))
        os.replace(partial, target)
        return target

    # -- errors -----------------------------------------------------------------------

    def _retry_busy(self, call: Callable[[], _T]) -> _T:
        """Call, retrying while the camera answers GP_ERROR_CAMERA_BUSY."""
        for attempt in range(self.busy_retries + 1):
            try:
                return call()
            except self._gp.GPhoto2Error as exc:
                if exc.code != self._gp.GP_ERROR_CAMERA_BUSY or attempt == self.busy_retries:
                    raise
            self._sleep(self.busy_wait_s)
        raise AssertionError("unreachable: the last attempt returns or raises")

    def _error(self, command: str, exc: Any) -> DeviceError:
        """The domain error for a GPhoto2Error, in one line with a hint where there is one."""
        gp = self._gp
        code = getattr(exc, "code", 0)
        # GP_ERROR_IO and the GP_ERROR_IO_* family (USB find, claim, read, write...).
        io_errors = {getattr(gp, n) for n in dir(gp) if n.startswith("GP_ERROR_IO")}
        text = " ".join(str(getattr(exc, "string", "") or exc).split())
        if code == gp.GP_ERROR_MODEL_NOT_FOUND:
            return DeviceError(
                self.name,
                command,
                "no camera detected: check the cable, that the camera is on and in PTP mode",
            )
        if code == gp.GP_ERROR_IO_USB_CLAIM:
            return CommunicationError(
                self.name,
                command,
                "another program holds the camera's USB interface "
                "(e.g. gvfs-gphoto2-volume-monitor): close it and retry",
            )
        if code == gp.GP_ERROR_CAMERA_BUSY:
            waited = self.busy_retries * self.busy_wait_s
            return DeviceTimeoutError(self.name, command, f"camera still busy after {waited:g} s of retries")
        if code == gp.GP_ERROR_TIMEOUT:
            return DeviceTimeoutError(self.name, command, f"gphoto2 error {code}: {text}")
        if code in io_errors:
            return CommunicationError(self.name, command, f"gphoto2 error {code}: {text}")
        return DeviceError(self.name, command, f"gphoto2 error {code}: {text}")


def _is_raw(name: str) -> bool:
    return os.path.splitext(name)[1].lower() in RAW_EXTENSIONS


def _unused_path(path: Path) -> Path:
    candidate, counter = path, 0
    while candidate.exists():
        counter += 1
        candidate = path.with_name(f"{path.stem}-{counter}{path.suffix}")
    return candidate
