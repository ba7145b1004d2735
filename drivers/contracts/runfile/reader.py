"""Reading a run file: the header, and every complete position."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from drivers.camera import RawFrame
from drivers.contracts.runfile.check import CorruptFrame, FrameCorruptError, frame_fault, is_checksummed
from drivers.contracts.runfile.header import read_header_once
from drivers.contracts.runfile.layout import (
    CALIBRATION_DATASETS,
    CALIBRATION_SETS,
    DATASETS,
    CalibrationFrames,
    PositionTimes,
    RunFileError,
    RunHeader,
    as_text,
    calibration_slot,
    h5_cause,
    is_whole,
)
from drivers.pose import Pose

_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def _truncated_size(path: Path, f: h5py.File) -> tuple[int, int] | None:
    """(actual, expected) size of a cleanly closed file shorter than HDF5 says, else None.

    A SWMR reader skips HDF5's own end-of-file check (a live file grows). A file closed
    cleanly (superblock version >= 2 with no "open for write" flags) must still reach
    the end of its allocated space.
    """
    with open(path, "rb") as stream:
        head = stream.read(12)
    if len(head) < 12 or head[:8] != _HDF5_SIGNATURE or head[8] < 2 or head[11] != 0:
        return None
    actual, expected = os.path.getsize(path), int(f.id.get_filesize())
    return (actual, expected) if actual < expected else None


class RunFile:
    """Reads a run file: the header, and every complete position.

    Open it with :meth:`open`. Works on a finished run, on one still being written (call
    :meth:`refresh` to see new positions) and on one whose writer was killed. Only
    positions whose ``complete`` flag is set are read; asking for another one raises a
    :class:`RunFileError`.

    Attributes
    ----------
    path : Path
        The run file.
    header : RunHeader
        The run's header.
    """

    def __init__(self, path: Path, f: h5py.File, header: RunHeader):
        self.path = path
        self.header = header
        self._f = f

    @classmethod
    def open(cls, path: str | os.PathLike[str]) -> RunFile:
        """Open a run file for reading.

        Raises
        ------
        RunFileError
            Missing file, not HDF5, not a mirrorgonio run file, a newer format version,
            or a truncated or corrupt file.
        """
        path = Path(path)
        if not path.exists():
            raise RunFileError(f"{path}: run file not found")
        if not path.is_file():
            raise RunFileError(f"{path}: not a file")
        try:
            is_hdf5 = h5py.is_hdf5(path)
        except OSError as exc:
            raise RunFileError(f"{path}: cannot read the run file: {h5_cause(exc)}") from None
        if not is_hdf5:
            raise RunFileError(f"{path}: not an HDF5 file")
        try:
            f = h5py.File(path, "r", swmr=True)
        except OSError as exc:
            cause = h5_cause(exc)
            if "unable to lock file" in cause:
                raise RunFileError(f"{path}: the run file is being opened for writing by another process") from None
            if "not already open for SWMR writing" in cause:
                raise RunFileError(
                    f"{path}: the file was left open for writing outside SWMR mode and cannot be read "
                    "(`h5clear -s` may recover it)"
                ) from None
            raise RunFileError(f"{path}: truncated or corrupt HDF5 file ({cause})") from None
        try:
            truncated = _truncated_size(path, f)
            if truncated is not None:
                raise RunFileError(
                    f"{path}: truncated or corrupt HDF5 file (truncated: {truncated[0]} of {truncated[1]} bytes)"
                )
            header = read_header_once(f, path)
        except BaseException:
            f.close()
            raise
        return cls(path, f, header)

    def close(self) -> None:
        """Close the file (idempotent)."""
        if self._f is not None:
            self._f.close()
            self._f = None

    def __enter__(self) -> RunFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def refresh(self) -> None:
        """See what a live writer has written since the file was opened."""
        for name, _ in DATASETS.items():
            if name.startswith(("positions/", "frames/", "status/")):
                self._dset(name).refresh()
        if self.has_calibration_group:
            for name in CALIBRATION_DATASETS:
                self._dset(name).refresh()

    # --- the run ---------------------------------------------------------------------------
    @property
    def n_positions(self) -> int:
        return self.header.n_positions

    @property
    def max_exposures(self) -> int:
        return self.header.max_exposures

    @property
    def frame_shape(self) -> tuple[int, int]:
        return self.header.frame_shape

    @property
    def status(self) -> str:
        """The run's state: created, running, paused, complete, aborted, failed, interrupted."""
        return as_text(self._read("status/state", ())).strip()

    @property
    def status_message(self) -> str:
        """The last error or note the writer recorded."""
        return as_text(self._read("status/message", ()))

    @property
    def complete(self) -> np.ndarray:
        """Which positions are complete (bool, shape (n,))."""
        return self._read("positions/complete", ()) == 1

    def completed_positions(self) -> np.ndarray:
        """Indices of the complete positions."""
        return np.flatnonzero(self.complete)

    # --- one position ----------------------------------------------------------------------
    def measured_pose(self, i: int) -> Pose | None:
        """The tool pose read back at position ``i``; None if not complete."""
        if not self._is_complete(i):
            return None
        return Pose(*(float(v) for v in self._read("positions/measured_pose", i)))

    def times(self, i: int) -> PositionTimes | None:
        """When position ``i`` was taken; None if not complete."""
        if not self._is_complete(i):
            return None
        return PositionTimes(*(float(v) for v in self._read("positions/times", i)))

    def frame_count(self, i: int) -> int:
        """How many frames position ``i`` holds."""
        return self._count(i)

    def exposures(self, i: int) -> np.ndarray:
        """Exposure times (s) of position ``i``'s frames, shape (k,)."""
        k = self._count(i)
        return self._read("frames/exposure_s", (i, slice(0, k)))

    def frames(self, i: int) -> np.ndarray:
        """Raw mosaics of position ``i``, uint16, shape (k, height, width).

        Raises
        ------
        FrameCorruptError
            A frame fails its checksum or cannot be decoded (naming the position and frame).
        """
        k = self._count(i)
        return self._read_raw("frames", i, f"position {i}", range(k))

    def black_level(self, i: int) -> np.ndarray:
        """Black levels of position ``i``'s frames, shape (k, 2, 2)."""
        k = self._count(i)
        return self._read("frames/black_level", (i, slice(0, k))).astype(np.float64)

    def white_level(self, i: int) -> np.ndarray:
        """White levels of position ``i``'s frames, shape (k,)."""
        k = self._count(i)
        return self._read("frames/white_level", (i, slice(0, k))).astype(np.int64)

    def cfa_pattern(self, i: int) -> list[str]:
        """CFA patterns of position ``i``'s frames."""
        k = self._count(i)
        return [as_text(v) for v in self._read("frames/cfa_pattern", (i, slice(0, k)))]

    def timestamps(self, i: int) -> np.ndarray:
        """Capture times (unix s) of position ``i``'s frames, shape (k,)."""
        k = self._count(i)
        return self._read("frames/timestamp", (i, slice(0, k)))

    def frame(self, i: int, k: int) -> RawFrame:
        """Frame ``k`` of position ``i`` as a :class:`RawFrame`, with its metadata."""
        count = self._count(i)
        if not is_whole(k) or not 0 <= k < count:
            raise RunFileError(f"{self.path}: position {i} has no frame {k!r} ({count} frames)")
        camera = self.header.devices.get("camera", "") if isinstance(self.header.devices, dict) else ""
        return RawFrame(
            mosaic=self._read_raw("frames", i, f"position {i}", k),
            black_level=self._read("frames/black_level", (i, k)).astype(np.float64),
            white_level=int(self._read("frames/white_level", (i, k))),
            cfa_pattern=as_text(self._read("frames/cfa_pattern", (i, k))),
            exposure_s=float(self._read("frames/exposure_s", (i, k))),
            timestamp=float(self._read("frames/timestamp", (i, k))),
            camera_id=str(camera),
            source=f"{self.path}:/frames/raw[{i},{k}]",
        )

    # --- calibration frames -----------------------------------------------------------------
    @property
    def has_calibration_group(self) -> bool:
        """Whether the file has room for calibration frames (format version 2 and later)."""
        if self._f is None:
            raise RunFileError(f"{self.path}: the run file is closed")
        return "calibration" in self._f

    def calibration_sets(self) -> list[tuple[str, str]]:
        """The complete calibration sets, as ``(role, when)``, in the file's order."""
        if not self.has_calibration_group:
            return []
        complete = self._read("calibration/complete", ()) == 1
        return [pair for pair, done in zip(CALIBRATION_SETS, complete, strict=True) if done]

    def calibration_frames(self, role: str, when: str = "before") -> CalibrationFrames | None:
        """One calibration set: the frames of ``role`` taken ``when``.

        Parameters
        ----------
        role : str
            ``ambient`` (the light off, the room lit) or ``dark`` (the light off, the room
            dark; see ``calibration`` in the header for how the run took them).
        when : str
            ``before`` the first position or ``after`` the last.

        Returns
        -------
        CalibrationFrames or None
            The set; None when the run has no complete set of that role and time (always for
            a file of format version 1).

        Raises
        ------
        RunFileError
            An unknown role or time, or a set that cannot be read.
        """
        try:
            slot = calibration_slot(role, when)
        except RunFileError as exc:
            raise RunFileError(f"{self.path}: {exc}") from None
        if not self.has_calibration_group or self._read("calibration/complete", slot) != 1:
            return None
        k = self._set_count(slot, role, when)
        frames = slice(0, k)
        patterns = {as_text(v) for v in self._read("calibration/cfa_pattern", (slot, frames))}
        if len(patterns) != 1:
            raise RunFileError(f"{self.path}: corrupt run file: calibration {role} {when} mixes CFA patterns")
        black = self._read("calibration/black_level", (slot, frames)).astype(np.float64)
        return CalibrationFrames(
            frames=self._read_raw("calibration", slot, f"calibration {role} {when}", range(k)),
            exposures_s=self._read("calibration/exposure_s", (slot, frames)).astype(np.float64),
            black_level=black.mean(axis=0),
            white_level=int(self._read("calibration/white_level", (slot, frames)).min()),
            cfa_pattern=patterns.pop(),
            timestamps=self._read("calibration/timestamp", (slot, frames)).astype(np.float64),
        )

    # --- checksums -------------------------------------------------------------------------
    @property
    def checksummed(self) -> bool:
        """Whether the file's frames carry checksums (Fletcher32; ``docs/run-file.md``)."""
        raws = ["frames/raw"] + (["calibration/raw"] if self.has_calibration_group else [])
        return all(is_checksummed(self._dset(name)) for name in raws)

    def corrupt_frames(
        self,
        positions: Iterable[int] | None = None,
        sets: Iterable[tuple[str, str]] | None = None,
        progress: Callable[[int, int], None] | None = None,
    ) -> list[CorruptFrame]:
        """The frames that do not read back as written: each read whole, through its checksum.

        Parameters
        ----------
        positions : iterable of int, optional
            Complete positions to check (default: every complete position).
        sets : iterable of (role, when), optional
            Complete calibration sets to check (default: every complete set).
        progress : callable, optional
            ``progress(frames_done, frames_total)`` after each position or set.

        Returns
        -------
        list of CorruptFrame
            In the order of the file: positions, then calibration sets.

        Raises
        ------
        RunFileError
            A position or set that is not complete, or whose frame count is out of range.
        """
        chosen = self.completed_positions() if positions is None else positions
        slots = [("frames", int(i), f"position {int(i)}", self._count(int(i))) for i in chosen]
        for role, when in self.calibration_sets() if sets is None else sets:
            slot = calibration_slot(role, when)
            slots.append(("calibration", slot, f"calibration {role} {when}", self._set_count(slot, role, when)))
        total, done = sum(count for *_, count in slots), 0
        buffer = np.empty(self.frame_shape, dtype=np.uint16)
        found = []
        for group, slot, label, count in slots:
            raw = self._dset(f"{group}/raw")
            for k in range(count):
                cause = frame_fault(raw, slot, k, buffer)
                if cause is not None:
                    found.append(self._corrupt(group, slot, label, k, cause))
            done += count
            if progress is not None:
                progress(done, total)
        return found

    def structure_problems(self) -> list[str]:
        """What is wrong with the file's structure, one line each (empty when nothing is): every
        dataset read whole (HDF5 checks the checksums of its own metadata), and each complete
        position's and calibration set's frame count and per-frame records."""
        names = list(DATASETS) + (list(CALIBRATION_DATASETS) if self.has_calibration_group else [])
        problems, values = [], {}
        for name in names:
            if name.endswith("/raw"):
                continue  # the frames: corrupt_frames
            try:
                values[name] = self._dset(name)[()]
            except (OSError, RuntimeError, KeyError) as exc:
                problems.append(f"/{name} cannot be read ({h5_cause(exc)})")
        groups = [("frames", "positions", [f"position {i}" for i in range(self.n_positions)])]
        if self.has_calibration_group:
            groups.append(("calibration", "calibration", [f"calibration {r} {w}" for r, w in CALIBRATION_SETS]))
        for frames, flags, labels in groups:
            needed = [f"{flags}/complete", f"{flags}/frame_count", f"{frames}/exposure_s", f"{frames}/white_level"]
            if any(name not in values for name in needed):
                continue
            complete, counts = values[f"{flags}/complete"], values[f"{flags}/frame_count"]
            for slot in np.flatnonzero(complete == 1):
                k = int(counts[slot])
                if not 1 <= k <= self._dset(f"{frames}/raw").shape[1]:
                    problems.append(f"{labels[slot]} is complete with frame_count {k}")
                    continue
                exposures, whites = values[f"{frames}/exposure_s"][slot, :k], values[f"{frames}/white_level"][slot, :k]
                bad = np.flatnonzero(~(np.isfinite(exposures) & (exposures > 0)) | (whites <= 0))
                if bad.size:
                    problems.append(f"{labels[slot]} frame {int(bad[0])} has no valid exposure or white level")
        return problems

    def _read_raw(self, group: str, slot: int, label: str, frames: range | int) -> np.ndarray:
        """Frames ``frames`` (a range, or one index) of ``slot`` in ``group``; a corrupt one raises
        a :class:`FrameCorruptError` naming it."""
        raw = self._dset(f"{group}/raw")
        try:
            if isinstance(frames, range):
                return raw[slot, frames.start : frames.stop]
            return raw[slot, frames]
        except (OSError, RuntimeError) as exc:
            for k in frames if isinstance(frames, range) else [frames]:
                cause = frame_fault(raw, slot, k)
                if cause is not None:
                    raise FrameCorruptError(self._corrupt(group, slot, label, k, cause)) from None
            raise RunFileError(f"{self.path}: cannot read {label} frames: {h5_cause(exc)}") from None

    def _corrupt(self, group: str, slot: int, label: str, k: int, cause: str) -> CorruptFrame:
        try:
            exposure = float(self._dset(f"{group}/exposure_s")[slot, k])
        except (OSError, RuntimeError):
            exposure = float("nan")
        position = slot if group == "frames" else None
        return CorruptFrame(self.path, label, position, k, exposure, cause)

    def _set_count(self, slot: int, role: str, when: str) -> int:
        if not self.has_calibration_group or self._read("calibration/complete", slot) != 1:
            raise RunFileError(f"{self.path}: calibration {role} {when} is not complete")
        k = int(self._read("calibration/frame_count", slot))
        if not 1 <= k <= self._dset("calibration/raw").shape[1]:
            raise RunFileError(f"{self.path}: corrupt run file: calibration {role} {when} has frame_count {k}")
        return k

    # --- internals -------------------------------------------------------------------------
    def _dset(self, name: str) -> h5py.Dataset:
        if self._f is None:
            raise RunFileError(f"{self.path}: the run file is closed")
        return self._f[name]

    def _read(self, name: str, selection: Any, what: str | None = None) -> Any:
        dset = self._dset(name)
        try:
            return dset[selection]
        except (OSError, RuntimeError) as exc:
            raise RunFileError(f"{self.path}: cannot read {what or '/' + name}: {h5_cause(exc)}") from None

    def _check_index(self, i: int) -> None:
        if not is_whole(i) or not 0 <= i < self.n_positions:
            raise RunFileError(f"{self.path}: position {i!r} out of range (0 to {self.n_positions - 1})")

    def _is_complete(self, i: int) -> bool:
        self._check_index(i)
        return bool(self._read("positions/complete", i) == 1)

    def _count(self, i: int) -> int:
        if not self._is_complete(i):
            raise RunFileError(f"{self.path}: position {i} is not complete")
        k = int(self._read("positions/frame_count", i))
        if not 1 <= k <= self.max_exposures:
            raise RunFileError(f"{self.path}: corrupt run file: position {i} has frame_count {k}")
        return k
