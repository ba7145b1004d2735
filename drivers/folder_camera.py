"""A camera seen through the folder its tethering software saves raw files into.

Any camera whose vendor or third-party software can shoot tethered (EOS Utility,
Capture One, digiCamControl, ``gphoto2 --capture-tethered``, a simulated camera) works
this way: something triggers the shutter, the software writes a new raw file into a
folder, and this driver picks it up once it has stopped growing.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable
from pathlib import Path

from drivers.camera import Camera, RawFrame
from drivers.errors import DeviceError, DeviceTimeoutError, RawFileError
from drivers.raw_decode import RAW_EXTENSIONS, decode_raw

# (size in bytes, modification time in ns): a file that keeps both is no longer written.
_Signature = tuple[int, int]


class FolderCamera(Camera):
    """Take a raw exposure by triggering tethering software and watching its folder.

    ``capture(exposure_s)`` notes the files already in the folder, calls
    ``trigger(exposure_s)`` if there is one (the tethering software's remote shutter,
    for instance), then waits for a *new* raw file whose size and modification time
    stay the same for ``settle_s``, decodes it with :func:`~drivers.raw_decode.decode_raw`
    and returns it. Files of other types (the JPEG of RAW+JPEG), hidden files (temporary
    files, macOS ``._`` companions) and files already present are ignored. The tethering
    software must give every capture a new file name, as they all do by numbering them.

    ``exposure_s`` is only a request passed to the trigger: the returned frame's
    ``exposure_s`` is the one recorded in the file, which is what the camera did (a
    trigger may round it to a shutter step, or have no way to set it at all).

    Parameters
    ----------
    folder : str or path-like
        The folder the tethering software saves into.
    trigger : callable, optional
        Called as ``trigger(exposure_s)`` to start the exposure. Without one, someone
        or something else presses the shutter and the capture only waits for the file.
        A :class:`~drivers.errors.DeviceError` it raises passes through; any other
        exception becomes one.
    timeout_s : float
        How long to wait for the new file, from the trigger on.
    settle_s : float
        How long a new file must stay unchanged before it is read.
    extensions : iterable of str
        Suffixes of the raw files to wait for, case-insensitive.
    name : str
        Device name used in every error message.
    clock, sleep : callable
        Monotonic clock (seconds) and sleep, replaceable in tests.
    poll_s : float
        Interval between two looks at the folder.
    """

    def __init__(
        self,
        folder: str | os.PathLike,
        *,
        trigger: Callable[[float], None] | None = None,
        timeout_s: float = 30.0,
        settle_s: float = 0.2,
        extensions: Iterable[str] = RAW_EXTENSIONS,
        name: str = "folder camera",
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
        poll_s: float = 0.05,
    ):
        self.folder = Path(folder)
        self.trigger = trigger
        self.timeout_s = float(timeout_s)
        self.settle_s = float(settle_s)
        self.extensions = frozenset(ext.lower() if ext.startswith(".") else f".{ext.lower()}" for ext in extensions)
        self.name = name
        self._clock = clock
        self._sleep = sleep
        self.poll_s = float(poll_s)
        self._last_camera_id = ""

    @property
    def identity(self) -> str:
        """The camera named in the last file read, else this driver and its folder."""
        return self._last_camera_id or f"{self.name} ({self.folder})"

    def problem(self) -> str | None:
        """The watched folder has gone (unmounted share, deleted)."""
        return None if self.folder.is_dir() else f"{self.folder} is not a folder"

    def connect(self) -> None:
        """Check that the folder exists."""
        if not self.folder.is_dir():
            raise DeviceError(self.name, "connect", f"{self.folder} is not a folder")

    def capture(self, exposure_s: float) -> RawFrame:
        """Trigger, wait for the new raw file, decode it.

        Raises
        ------
        DeviceTimeoutError
            No new raw file settled in the folder within ``timeout_s``.
        RawFileError
            The new file stayed undecodable until the timeout.
        DeviceError
            The folder cannot be read, or the trigger failed.
        """
        if not exposure_s > 0:
            raise ValueError(f"exposure_s must be positive, not {exposure_s}")
        present = set(self._scan(raw_only=False))
        self._fire(exposure_s)
        frame = self._wait_for_new_frame(present)
        frame.extra["requested_exposure_s"] = float(exposure_s)
        self._last_camera_id = frame.camera_id
        return frame

    def _fire(self, exposure_s: float) -> None:
        if self.trigger is None:
            return
        try:
            self.trigger(exposure_s)
        except DeviceError:
            raise
        except Exception as exc:
            cause = " ".join(f"trigger failed: {type(exc).__name__}: {exc}".split())
            raise DeviceError(self.name, "capture", cause) from exc

    def _wait_for_new_frame(self, present: set[str]) -> RawFrame:
        deadline = self._clock() + self.timeout_s
        # name -> (signature last seen, when it was first seen with that signature)
        watched: dict[str, tuple[_Signature, float]] = {}
        # name -> (signature that failed to decode, the error): retried once it changes,
        # since a writer may pause for longer than settle_s in the middle of a file.
        failed: dict[str, tuple[_Signature, RawFileError]] = {}
        while True:
            now = self._clock()
            files = self._scan(raw_only=True)
            new = sorted((sig[1], name) for name, sig in files.items() if name not in present)
            for _, name in new:
                signature = files[name]
                seen = watched.get(name)
                if seen is None or seen[0] != signature:
                    watched[name] = (signature, now)
                    continue
                if signature[0] == 0 or now - seen[1] < self.settle_s:
                    continue
                if name in failed and failed[name][0] == signature:
                    continue
                try:
                    return decode_raw(self.folder / name)
                except RawFileError as exc:
                    failed[name] = (signature, exc)
            if now >= deadline:
                if failed:
                    raise next(reversed(failed.values()))[1]
                raise DeviceTimeoutError(self.name, "capture", self._timeout_cause(present))
            self._sleep(min(self.poll_s, max(deadline - now, 0.0)))

    def _timeout_cause(self, present: set[str]) -> str:
        cause = f"no new raw file appeared in {self.folder} within {self.timeout_s:g} s"
        others = sorted(set(self._scan(raw_only=False)) - present)
        if others:
            shown = ", ".join(others[:3]) + (", ..." if len(others) > 3 else "")
            cause += f" (new files of other types ignored: {shown}; is the camera saving raw?)"
        return cause

    def _scan(self, *, raw_only: bool) -> dict[str, _Signature]:
        """Visible regular files of the folder (raw ones only, if asked) by name."""
        files: dict[str, _Signature] = {}
        try:
            with os.scandir(self.folder) as entries:
                for entry in entries:
                    if entry.name.startswith("."):
                        continue
                    if raw_only and os.path.splitext(entry.name)[1].lower() not in self.extensions:
                        continue
                    try:
                        if not entry.is_file():
                            continue
                        stat = entry.stat()
                    except FileNotFoundError:
                        continue  # renamed or removed while listing
                    files[entry.name] = (stat.st_size, stat.st_mtime_ns)
        except OSError as exc:
            cause = f"cannot read {self.folder}: {exc.strerror or type(exc).__name__}"
            raise DeviceError(self.name, "capture", cause) from None
        return files
