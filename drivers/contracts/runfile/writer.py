"""Writing a run file, position by position (see :mod:`drivers.contracts.runfile` on crash safety)."""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from drivers.camera import RawFrame
from drivers.contracts.camera_colour import CameraColourError, checked_camera_colour
from drivers.contracts.runfile.check import frame_fault
from drivers.contracts.runfile.disk import (
    drop_unwritten,
    fresh_file,
    fsync_dir,
    fsync_path,
    storage_errno,
    write_error,
)
from drivers.contracts.runfile.header import encode_header, read_header
from drivers.contracts.runfile.layout import (
    CALIBRATION_SETS,
    CAMERA_COLOUR,
    CAMERA_COLOUR_BYTES,
    FRAME_RECORDS,
    STATES,
    PositionTimes,
    RunFileError,
    RunFileWriteError,
    RunHeader,
    build_layout,
    calibration_slot,
    empty_frame_records,
    encode_message,
    h5_cause,
    is_whole,
)
from drivers.contracts.runfile.lock import WriterLock
from drivers.contracts.runfile.reader import RunFile
from drivers.contracts.runfile.salvage import salvage_run
from drivers.pose import Pose

_CFA_SITES = 4

log = logging.getLogger("mirrorgonio.runfile")


def _poses_array(poses: list[Pose]) -> np.ndarray:
    return np.array([p.as_tuple() for p in poses], dtype=np.float64).reshape(len(poses), 6)


def _open_swmr_write(path: Path) -> h5py.File:
    """Open a run file for writing directly in SWMR mode.

    Opening with mode "a" and then setting ``swmr_mode`` leaves a moment when the file is
    marked "open for write" without SWMR; a kill then makes it unreadable even with
    ``swmr=True``. ``H5F_ACC_SWMR_WRITE`` at open marks it SWMR at once.
    """
    fapl = h5py.h5p.create(h5py.h5p.FILE_ACCESS)
    fapl.set_libver_bounds(h5py.h5f.LIBVER_LATEST, h5py.h5f.LIBVER_LATEST)
    fid = h5py.h5f.open(os.fsencode(path), h5py.h5f.ACC_RDWR | h5py.h5f.ACC_SWMR_WRITE, fapl=fapl)
    return h5py.File(fid)


def _float(value: Any) -> float | None:
    if isinstance(value, bool):
        return None
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


class RunFileWriter:
    """Writes one run file, position by position (see :mod:`drivers.contracts.runfile` on crash safety).

    Open it with :meth:`create` or :meth:`reopen`, never directly. Methods may be called
    from more than one thread (each call holds an internal lock).

    Attributes
    ----------
    path : Path
        The run file.
    header : RunHeader
        The run's header, as stored in the file.
    """

    def __init__(self, path: Path, f: h5py.File, header: RunHeader, lock: WriterLock):
        self.path = path
        self.header = header
        self._f = f
        self._lock = lock
        self._mutex = threading.RLock()
        self._sync_fd: int | None = os.open(path, os.O_RDONLY)
        self._n = header.n_positions
        self._failed: RunFileWriteError | None = None

    # --- opening -------------------------------------------------------------------------
    @classmethod
    def create(cls, path: str | os.PathLike[str], header: RunHeader) -> RunFileWriter:
        """Create a new run file and open it for writing.

        Parameters
        ----------
        path : str or Path
            The run file to create; it must not exist.
        header : RunHeader
            The run's header: schedule, frame shape, bracket and metadata.

        Returns
        -------
        RunFileWriter
            The writer, in SWMR mode, status ``created``.

        Raises
        ------
        RunFileError
            The file exists, another process writes it, or the header is invalid.
        """
        path = Path(path)
        rig_json, run_json = encode_header(path, header)
        commanded = _poses_array(header.tool_poses)
        light = _poses_array(header.light_poses)
        lock = WriterLock(path)
        try:
            if path.exists():
                raise RunFileError(f"{path}: run file already exists")
            tmp = Path(str(path) + ".tmp")
            try:
                with fresh_file(tmp) as f:
                    build_layout(
                        f,
                        rig_json,
                        run_json,
                        commanded,
                        light,
                        int(header.max_exposures),
                        (int(header.frame_shape[0]), int(header.frame_shape[1])),
                    )
                fsync_path(tmp)
                os.replace(tmp, path)
            except (OSError, RuntimeError) as exc:
                with contextlib.suppress(OSError):
                    tmp.unlink()
                if storage_errno(exc) is not None:
                    raise write_error(path, "creating the run file", exc) from None
                raise RunFileError(f"{path}: cannot create the run file: {h5_cause(exc)}") from None
            fsync_dir(path)
            return cls._open_for_writing(path, lock)
        except BaseException:
            lock.release()
            raise

    @classmethod
    def reopen(cls, path: str | os.PathLike[str]) -> RunFileWriter:
        """Open an existing run file to go on writing (resume).

        A file whose writer was killed cannot be opened for writing again (HDF5 leaves
        it marked "open for write"); it is salvaged: its header, schedule and complete
        positions (frames copied as their compressed chunks) go into a fresh file that
        replaces it, status ``interrupted``. Incomplete positions are left empty, to be
        taken again. Either way every complete position's and calibration set's frames are read
        through their checksums, and one with a frame that fails it is marked incomplete (a
        warning names it), to be taken again.

        Parameters
        ----------
        path : str or Path
            The run file.

        Returns
        -------
        RunFileWriter
            The writer, in SWMR mode.

        Raises
        ------
        RunFileError
            The file is missing, not a run file, newer than this software, open in
            another process, or too damaged to salvage.
        """
        path = Path(path)
        if not path.exists():
            raise RunFileError(f"{path}: run file not found")
        lock = WriterLock(path)
        try:
            RunFile.open(path).close()  # the reader's checks, before touching the file
            return cls._open_for_writing(path, lock, salvage=True)
        except BaseException:
            lock.release()
            raise

    @classmethod
    def _open_for_writing(cls, path: Path, lock: WriterLock, salvage: bool = False) -> RunFileWriter:
        try:
            f = _open_swmr_write(path)
        except OSError as exc:
            cause = h5_cause(exc)
            if salvage and "already open for write" in cause:
                salvage_run(path)
                return cls._open_for_writing(path, lock, salvage=False)
            if "unable to lock file" in cause:
                raise RunFileError(f"{path}: the run file is open in another process (close it there first)") from None
            if not h5py.is_hdf5(path):
                raise RunFileError(f"{path}: not an HDF5 file") from None
            raise RunFileError(f"{path}: cannot open the run file for writing: {cause}") from None
        try:
            header = read_header(f, path)
        except BaseException:
            f.close()
            raise
        for suffix in (".tmp", ".salvage.tmp"):  # left by a creation or salvage that was killed
            with contextlib.suppress(OSError):
                Path(str(path) + suffix).unlink()
        writer = cls(path, f, header, lock)
        if salvage:  # resumed without a salvage (which checks what it copies): check here
            try:
                writer._drop_corrupt()
            except BaseException:
                writer._f.close()
                raise
        return writer

    def _drop_corrupt(self) -> None:
        """Mark incomplete every complete position and calibration set with a frame that fails
        its checksum or cannot be read, so that it is taken again (a warning for each)."""
        f = self._f
        groups = [("frames", "positions", [f"position {i}" for i in range(self._n)])]
        if "calibration" in f:
            groups.append(("calibration", "calibration", [f"calibration {r} {w}" for r, w in CALIBRATION_SETS]))
        for frames_group, flags_group, labels in groups:
            raw, complete = f[f"{frames_group}/raw"], f[f"{flags_group}/complete"]
            counts = f[f"{flags_group}/frame_count"][()]
            for slot in np.flatnonzero(complete[()] == 1):
                count = int(counts[slot])
                faults = (frame_fault(raw, int(slot), k) for k in range(min(max(count, 0), raw.shape[1])))
                fault = next((f"{k} {why}" for k, why in enumerate(faults) if why is not None), None)
                if fault is None and 1 <= count <= raw.shape[1]:
                    continue
                complete[slot] = 0
                self._flush(complete)
                why = fault or f"count {count} out of range"
                log.warning("%s: %s frame %s: marked incomplete, to be taken again", self.path, labels[slot], why)

    # --- state ---------------------------------------------------------------------------
    @property
    def complete(self) -> np.ndarray:
        """Which positions are complete (bool, shape (n,)), read from the file."""
        with self._mutex:
            self._check_open()
            return self._f["positions/complete"][()] == 1

    def first_incomplete(self) -> int | None:
        """The first position not yet complete, or None when all are."""
        missing = np.flatnonzero(~self.complete)
        return int(missing[0]) if missing.size else None

    # --- writing -------------------------------------------------------------------------
    def write_position(self, index: int, measured: Pose, times: PositionTimes, frames: list[RawFrame]) -> None:
        """Write one position's frames and records, then mark it complete.

        Everything is checked before anything is written: on a RunFileError for bad
        input the file is unchanged. A position already complete is overwritten (its
        complete flag is cleared and flushed first).

        Parameters
        ----------
        index : int
            The position, ``0 <= index < n_positions``.
        measured : Pose
            The tool pose the arm read back.
        times : PositionTimes
            When the move started, ended and the last frame was taken.
        frames : list of RawFrame
            The bracket's frames, 1 to ``max_exposures`` of them, each of ``frame_shape``.

        Raises
        ------
        RunFileError
            Bad input (naming the position, frame and field), or the write failed.
        """
        with self._mutex:
            self._check_open()
            records = self._validate(index, measured, times, frames)
            with self._writing(f"position {index}"):
                self._write(index, records, frames)
                self._keep_camera_colour(frames)

    def _validate(
        self, index: int, measured: Pose, times: PositionTimes, frames: list[RawFrame]
    ) -> dict[str, np.ndarray]:
        where = f"{self.path}: position {index}"
        if not is_whole(index) or not 0 <= index < self._n:
            raise RunFileError(f"{self.path}: position {index!r} out of range (0 to {self._n - 1})")
        if not isinstance(measured, Pose) or not all(math.isfinite(v) for v in measured.as_tuple()):
            raise RunFileError(f"{where}: measured pose must be a Pose of finite numbers (got {measured!r})")
        try:
            time_row = np.array([times.move_started, times.in_position, times.frames_done], dtype=np.float64)
        except (AttributeError, TypeError, ValueError):
            raise RunFileError(f"{where}: times must be a PositionTimes (got {times!r})") from None
        if not np.all(np.isfinite(time_row)):
            raise RunFileError(f"{where}: times must be finite (got {times!r})")
        records = self._frame_records(where, frames, self.header.max_exposures)
        records["measured_pose"] = np.array(measured.as_tuple(), dtype=np.float64)
        records["times"] = time_row
        return records

    def _frame_records(self, where: str, frames: list[RawFrame], maximum: int) -> dict[str, np.ndarray]:
        """The per-frame records of ``frames`` (a slot of ``maximum`` frames), every frame checked.

        Raises
        ------
        RunFileError
            Not a list of 1 to ``maximum`` frames, or a frame whose mosaic or metadata is
            unusable (the message names ``where``, the frame and the field).
        """
        if not isinstance(frames, (list, tuple)):
            raise RunFileError(f"{where}: frames must be a list of RawFrame (got {type(frames).__name__})")
        if not 1 <= len(frames) <= maximum:
            raise RunFileError(f"{where}: {len(frames)} frames, expected 1 to {maximum}")
        height, width = self.header.frame_shape
        records = {name: value[0] for name, value in empty_frame_records(1, maximum).items()}
        for k, frame in enumerate(frames):
            at = f"{where} frame {k}"
            mosaic = getattr(frame, "mosaic", None)
            if not isinstance(mosaic, np.ndarray):
                raise RunFileError(f"{at}: not a RawFrame with an array mosaic")
            if mosaic.shape != (height, width):
                got = "x".join(str(v) for v in mosaic.shape)
                raise RunFileError(f"{at}: shape {got}, expected {height}x{width}")
            if mosaic.dtype != np.uint16:
                raise RunFileError(f"{at}: mosaic dtype {mosaic.dtype}, expected uint16")
            exposure = _float(frame.exposure_s)
            if exposure is None or not exposure > 0.0 or not math.isfinite(exposure):
                raise RunFileError(f"{at}: exposure_s must be finite and > 0 (got {frame.exposure_s!r})")
            timestamp = _float(frame.timestamp)
            if timestamp is None or not math.isfinite(timestamp):
                raise RunFileError(f"{at}: timestamp must be a finite number (got {frame.timestamp!r})")
            try:
                black = np.asarray(frame.black_level, dtype=np.float64)
            except (TypeError, ValueError):
                black = np.zeros(0)
            if black.shape != (2, 2) or not np.all(np.isfinite(black)):
                raise RunFileError(f"{at}: black_level must be 2x2 finite numbers (got {frame.black_level!r})")
            white = frame.white_level
            if not is_whole(white) or not 0 < white < 2**31:
                raise RunFileError(f"{at}: white_level must be a positive whole number (got {white!r})")
            cfa = frame.cfa_pattern
            if not isinstance(cfa, str) or len(cfa) != _CFA_SITES or not cfa.isascii() or not cfa.isalpha():
                raise RunFileError(f"{at}: cfa_pattern must be 4 letters such as 'RGGB' (got {cfa!r})")
            records["exposure_s"][k] = exposure
            records["timestamp"][k] = timestamp
            records["black_level"][k] = black
            records["white_level"][k] = int(white)
            records["cfa_pattern"][k] = cfa.encode("ascii")
        return records

    def _write(self, index: int, records: dict[str, np.ndarray], frames: list[RawFrame]) -> None:
        extra = {"measured_pose": records["measured_pose"], "times": records["times"]}
        self._commit("frames", "positions", index, records, frames, extra)

    def _commit(
        self,
        frames_group: str,
        flags_group: str,
        index: int,
        records: dict[str, np.ndarray],
        frames: list[RawFrame],
        extra: dict[str, np.ndarray],
    ) -> None:
        """Write slot ``index``'s frames (``frames_group``) and records, then set its complete flag.

        ``flags_group`` holds the slot's ``complete`` flag, its ``frame_count`` and the ``extra``
        records. A complete slot is first marked incomplete (flushed), so that a reader never
        trusts a slot being rewritten; the flag is written and flushed last: the commit marker.
        """
        f = self._f
        complete = f[f"{flags_group}/complete"]
        if complete[index]:
            complete[index] = 0
            self._flush(complete)
        raw = f[f"{frames_group}/raw"]
        for k, frame in enumerate(frames):
            raw[index, k] = frame.mosaic
        for k in range(len(frames), raw.shape[1]):  # frames of an earlier take
            if raw.id.get_chunk_info_by_coord((index, k, 0, 0)).size:
                raw[index, k] = 0
        written = [raw]
        for name in FRAME_RECORDS:
            written.append(f[f"{frames_group}/{name}"])
            written[-1][index] = records[name]
        for name, value in {**extra, "frame_count": np.int16(len(frames))}.items():
            written.append(f[f"{flags_group}/{name}"])
            written[-1][index] = value
        self._flush(*written)
        complete[index] = 1  # the commit marker, written and flushed last
        self._flush(complete)

    # --- calibration frames ----------------------------------------------------------------
    def write_calibration(self, role: str, when: str, frames: list[RawFrame]) -> None:
        """Write one calibration set (``docs/run-file.md``), then mark it complete.

        Crash-safe like a position: the set is committed by its ``complete`` flag, so a reader
        sees it whole or not at all. A set already complete is replaced.

        Parameters
        ----------
        role : str
            ``ambient`` (the light off, the room lit) or ``dark`` (the light off, the room dark,
            or the shortest exposure where the room cannot be darkened).
        when : str
            ``before`` the first position or ``after`` the last.
        frames : list of RawFrame
            1 to 16 frames of ``frame_shape``, of one CFA pattern.

        Raises
        ------
        RunFileError
            An unknown role or time, a file of format version 1, bad frames (naming the set,
            the frame and the field), or the write failed.
        """
        with self._mutex:
            self._check_open()
            slot = self._calibration_slot(role, when)
            where = f"{self.path}: calibration {role} {when}"
            records = self._frame_records(where, frames, int(self._f["calibration/raw"].shape[1]))
            patterns = sorted({frame.cfa_pattern for frame in frames})
            if len(patterns) > 1:
                raise RunFileError(f"{where}: the frames mix CFA patterns ({', '.join(patterns)})")
            with self._writing(f"calibration {role} {when}"):
                self._commit("calibration", "calibration", slot, records, frames, {})
                self._keep_camera_colour(frames)

    def _keep_camera_colour(self, frames: list[RawFrame]) -> None:
        """Fill ``/header/camera_colour_json`` from the first frame whose raw file carried colour
        matrices (``frame.extra["colour"]``), once: a run's camera is one camera. A file without
        the dataset (written by an older version, resumed) or a frame without matrices is left as
        it is; a description that is not one, or too long for the dataset, is not kept."""
        if self.header.camera_colour or CAMERA_COLOUR not in self._f:
            return
        for frame in frames:
            extra = getattr(frame, "extra", None)
            description = extra.get("colour") if isinstance(extra, dict) else None
            if not description:
                continue
            try:
                colour = checked_camera_colour(description, "frame colour")
            except CameraColourError as exc:
                log.warning("%s: the camera's colour matrices are not kept: %s", self.path, exc)
                return
            text = json.dumps(colour, allow_nan=False).encode("utf-8")
            if len(text) > CAMERA_COLOUR_BYTES:
                log.warning("%s: the camera's colour matrices are not kept: %d bytes of JSON", self.path, len(text))
                return
            self._f[CAMERA_COLOUR][()] = np.bytes_(text)
            self._flush(self._f[CAMERA_COLOUR])
            self.header.camera_colour = colour
            return

    def calibration_complete(self, role: str, when: str) -> bool:
        """Whether the calibration set ``(role, when)`` is complete (False in a version-1 file)."""
        with self._mutex:
            self._check_open()
            if "calibration" not in self._f:
                calibration_slot(role, when)  # an unknown role or time is still an error
                return False
            return bool(self._f["calibration/complete"][self._calibration_slot(role, when)] == 1)

    def _calibration_slot(self, role: str, when: str) -> int:
        try:
            slot = calibration_slot(role, when)
        except RunFileError as exc:
            raise RunFileError(f"{self.path}: {exc}") from None
        if "calibration" not in self._f:
            raise RunFileError(f"{self.path}: a run file of format version 1 has no room for calibration frames")
        return slot

    @contextlib.contextmanager
    def _writing(self, what: str) -> Iterator[None]:
        """Around every write: a failed one raises :class:`RunFileWriteError` and drops what
        HDF5 holds unwritten (:func:`~drivers.contracts.runfile.disk.drop_unwritten`); the
        writer refuses every write and read after it (what it would read is no longer the
        file), and :meth:`close` still works."""
        try:
            yield
        except (OSError, RuntimeError) as exc:
            self._failed = write_error(self.path, what, exc)
            drop_unwritten(self._f)
            raise self._failed from None

    @property
    def failed(self) -> RunFileWriteError | None:
        """The write that failed, after which this writer writes nothing more (None if none)."""
        return self._failed

    def _flush(self, *datasets: h5py.Dataset) -> None:
        for dset in datasets:
            dset.flush()
        self._f.flush()
        if self._sync_fd is not None:  # on the disk, not only in the page cache
            os.fsync(self._sync_fd)

    def set_status(self, state: str, message: str = "") -> None:
        """Record the run's state and a message (flushed at once).

        Parameters
        ----------
        state : str
            One of ``created, running, paused, complete, aborted, failed, interrupted``.
        message : str
            The last error or a note; cut to 1024 bytes of UTF-8.
        """
        if state not in STATES:
            raise RunFileError(f"{self.path}: unknown status {state!r} (one of {', '.join(STATES)})")
        with self._mutex:
            self._check_open()
            with self._writing("the run's status"):
                self._f["status/state"][()] = np.bytes_(state.encode("ascii"))
                self._f["status/message"][()] = np.bytes_(encode_message(message))
                self._flush(self._f["status/state"], self._f["status/message"])

    # --- closing -------------------------------------------------------------------------
    def close(self) -> None:
        """Close the file and release the writer's lock (idempotent).

        Raises
        ------
        RunFileWriteError
            The last data could not be written (the file is closed all the same).
        """
        with self._mutex:
            if self._f is None:
                return
            try:
                if self._failed is None:  # what is still unwritten, dropped if the storage refuses it
                    with self._writing("closing the run file"):
                        self._f.flush()
            finally:
                self._close_file()

    def _close_file(self) -> None:
        if self._f is not None:
            try:
                self._f.close()
            finally:
                self._f = None
                if self._sync_fd is not None:
                    os.close(self._sync_fd)
                    self._sync_fd = None
                self._lock.release()

    @property
    def closed(self) -> bool:
        return self._f is None

    def _check_open(self) -> None:
        if self._f is None:
            raise RunFileError(f"{self.path}: the run file writer is closed")
        if self._failed is not None:
            raise RunFileWriteError(f"{self.path}: the writer stopped after a failed write: {self._failed}")

    def __enter__(self) -> RunFileWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
