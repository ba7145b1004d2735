"""The run file: one HDF5 file per run, written position by position, safe to kill.

This module is the only place that knows the layout (see ``docs/run-file.md``). The
acquisition writes with :class:`RunFileWriter`; the processing and anyone else read with
:class:`RunFile`.

Crash safety
------------
The writer may be killed at any moment (SIGKILL, a crash of the daemon) and every
position that was complete before the kill stays readable, bit-exact:

* the file is built in ``PATH.tmp`` with every small dataset already holding its initial
  values (so its storage is allocated), then atomically renamed onto ``PATH``; a kill
  during creation leaves no file, or a whole one;
* the writer then works in HDF5's single-writer/multiple-reader (SWMR) mode, and never
  creates a dataset, group or attribute afterwards;
* a position is committed by its ``/positions/complete`` flag, written and flushed after
  everything else of the position; a reader trusts only positions whose flag is 1;
* readers always open with ``swmr=True``, which works on a file whose writer was killed
  (a normal open refuses it: HDF5 marks it "already open for write");
* :meth:`RunFileWriter.reopen` of a killed run copies its complete positions, frames as
  their compressed chunks, into a fresh file that replaces the old one (salvage).

A lock file ``PATH.lock`` (``flock``, released by the kernel when the writer dies) keeps
a second writer off a run that is still being written; it is removed on a clean close.
"""

from __future__ import annotations

import contextlib
import copy
import errno
import fcntl
import functools
import hashlib
import json
import math
import os
import re
import threading
from dataclasses import dataclass, field, replace
from pathlib import Path

import h5py
import hdf5plugin
import numpy as np

from drivers.camera import RawFrame
from drivers.contracts.rig import Rig, rig_from_dict
from drivers.pose import Pose

RUN_FILE_FORMAT = "mirrorgonio-run"
RUN_FILE_VERSION = 1

#: The states a run file's ``/status/state`` may hold.
STATES = ("created", "running", "paused", "complete", "aborted", "failed", "interrupted")
STATE_BYTES = 16
MESSAGE_BYTES = 1024

_FRAME_RECORDS = ("exposure_s", "black_level", "white_level", "timestamp", "cfa_pattern")
_CFA_SITES = 4


class RunFileError(ValueError):
    """A run file that cannot be written or read (one line: the file and the cause)."""


@dataclass
class PositionTimes:
    """When a position was taken, unix seconds.

    Attributes
    ----------
    move_started : float
        The arm was commanded to the position.
    in_position : float
        The arm reported it had arrived.
    frames_done : float
        The last frame of the position was captured.
    """

    move_started: float
    in_position: float
    frames_done: float


@dataclass
class RunHeader:
    """Everything fixed when a run starts.

    Attributes
    ----------
    run_id : str
        The run's identifier (also the file's name, by convention).
    rig : Rig
        The rig description the run was planned with.
    tool_poses : list of Pose
        The commanded tool pose at each position; their number is the run's length.
    light_poses : list of Pose
        The light's pose at each position (from the rig).
    max_exposures : int
        The most frames one position may hold.
    frame_shape : tuple of int
        ``(height, width)`` of every raw mosaic.
    bracket : dict
        The exposure bracket: ``{"mode": "fixed", ...exposures}`` or
        ``{"mode": "auto", ...rule parameters}``.
    metadata : dict
        The operator's notes: ``operator``, ``light_source``, ``notes``.
    devices : dict
        Identities of the devices used, e.g. ``{"arm": ..., "camera": ...}``.
    software_version : str
        mirrorgonio's version.
    created_utc : str
        ISO 8601 time of creation (UTC).
    preset : str
        Name of the preset or schedule the run was started from.
    references : dict
        Files the run belongs with, each ``{"path", "sha256", ...}``: ``light_model`` (the
        processed light run whose model lit an object run) and ``object_mesh`` (the object's
        geometry, with its ``units_m`` and ``pose``). Empty for a light run.
    """

    run_id: str
    rig: Rig
    tool_poses: list[Pose]
    light_poses: list[Pose]
    max_exposures: int
    frame_shape: tuple[int, int]
    bracket: dict
    metadata: dict
    devices: dict
    software_version: str
    created_utc: str
    preset: str = ""
    references: dict = field(default_factory=dict)

    @property
    def n_positions(self) -> int:
        return len(self.tool_poses)


# --- helpers -----------------------------------------------------------------------------
def _h5_cause(exc: BaseException) -> str:
    """The useful part of an h5py error: ``Unable to ... (cause)`` gives ``cause``."""
    text = str(exc)
    match = re.search(r"\((.*)\)\s*$", text)
    cause = match.group(1) if match else text
    return " ".join(cause.split())


def file_sha256(path, chunk_bytes: int = 1 << 20) -> str:
    """Hex SHA-256 of a file's bytes (the identity of a referenced file)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk_bytes):
            digest.update(block)
    return digest.hexdigest()


def _fsync_path(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(path: Path) -> None:
    with contextlib.suppress(OSError):  # not every file system lets a directory be synced
        _fsync_path(path.parent if str(path.parent) else Path("."))


def _poses_array(poses: list[Pose]) -> np.ndarray:
    return np.array([p.as_tuple() for p in poses], dtype=np.float64).reshape(len(poses), 6)


def _poses_from(array: np.ndarray) -> list[Pose]:
    return [Pose(*(float(v) for v in row)) for row in array]


def _encode_message(message: str) -> bytes:
    data = str(message).replace("\x00", " ").encode("utf-8")
    if len(data) > MESSAGE_BYTES:
        data = data[:MESSAGE_BYTES].decode("utf-8", errors="ignore").encode("utf-8")
    return data


def _text(value) -> str:
    if isinstance(value, bytes):
        return value.decode("utf-8", errors="replace")
    if isinstance(value, np.ndarray):
        return _text(value[()])
    return str(value)


class _WriterLock:
    """An exclusive ``flock`` on ``PATH.lock``; the kernel drops it if the holder dies."""

    def __init__(self, path: Path):
        self.path = Path(str(path) + ".lock")
        self._fd: int | None = None
        while True:
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError as exc:
                raise RunFileError(f"{path}: cannot create {self.path.name}: {exc.strerror}") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                holder = os.pread(fd, 32, 0).decode(errors="replace").strip()
                os.close(fd)
                if exc.errno in (errno.EWOULDBLOCK, errno.EACCES):
                    who = f" (pid {holder})" if holder.isdigit() else ""
                    raise RunFileError(f"{path}: another process{who} is writing this run") from None
                raise RunFileError(f"{path}: cannot lock {self.path.name}: {exc.strerror}") from None
            try:  # the previous holder may have removed the file between open and flock
                same = os.stat(self.path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:
                os.ftruncate(fd, 0)
                os.pwrite(fd, str(os.getpid()).encode(), 0)
                self._fd = fd
                return
            os.close(fd)

    def release(self) -> None:
        if self._fd is None:
            return
        with contextlib.suppress(OSError):
            os.unlink(self.path)
        os.close(self._fd)
        self._fd = None


# --- the layout --------------------------------------------------------------------------
def _build_layout(
    f: h5py.File,
    rig_json: str,
    run_json: str,
    commanded: np.ndarray,
    light: np.ndarray,
    max_exposures: int,
    frame_shape: tuple[int, int],
) -> None:
    """Create every group, attribute and dataset, small ones with their initial values.

    Writing the initial values allocates the storage of the contiguous datasets now,
    before SWMR mode: a contiguous dataset first written in SWMR mode is unreadable after
    a crash.
    """
    n = commanded.shape[0]
    height, width = frame_shape
    f.attrs["format"] = RUN_FILE_FORMAT
    f.attrs["format_version"] = np.int64(RUN_FILE_VERSION)
    text = h5py.string_dtype("utf-8")
    header = f.create_group("header")
    header.create_dataset("rig_json", data=rig_json, dtype=text)
    header.create_dataset("run_json", data=run_json, dtype=text)
    schedule = f.create_group("schedule")
    schedule.create_dataset("commanded_pose", data=commanded.astype(np.float64))
    schedule.create_dataset("light_pose", data=light.astype(np.float64))
    positions = f.create_group("positions")
    positions.create_dataset("measured_pose", data=np.full((n, 6), np.nan))
    positions.create_dataset("times", data=np.full((n, 3), np.nan))
    positions.create_dataset("frame_count", data=np.zeros(n, np.int16))
    positions.create_dataset("complete", data=np.zeros(n, np.uint8))
    frames = f.create_group("frames")
    frames.create_dataset(
        "raw",
        shape=(n, max_exposures, height, width),
        dtype=np.uint16,
        chunks=(1, 1, height, width),
        fillvalue=0,
        **hdf5plugin.LZ4(),
    )
    for name, value in _empty_frame_records(n, max_exposures).items():
        frames.create_dataset(name, data=value)
    status = f.create_group("status")
    status.create_dataset("state", data=np.bytes_(b"created"), dtype=f"S{STATE_BYTES}")
    status.create_dataset("message", data=np.bytes_(b""), dtype=f"S{MESSAGE_BYTES}")


def _empty_frame_records(n: int, max_exposures: int) -> dict[str, np.ndarray]:
    return {
        "exposure_s": np.full((n, max_exposures), np.nan),
        "black_level": np.full((n, max_exposures, 2, 2), np.nan, dtype=np.float32),
        "white_level": np.zeros((n, max_exposures), np.int32),
        "timestamp": np.full((n, max_exposures), np.nan),
        "cfa_pattern": np.zeros((n, max_exposures), dtype="S4"),
    }


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


def _check_format(f: h5py.File, path) -> None:
    fmt = f.attrs.get("format")
    if fmt is None:
        raise RunFileError(f"{path}: not a mirrorgonio run file (no 'format' attribute)")
    if _text(fmt) != RUN_FILE_FORMAT:
        raise RunFileError(f"{path}: not a mirrorgonio run file (format is {_text(fmt)!r})")
    version = f.attrs.get("format_version")
    try:
        version = int(version)
    except (TypeError, ValueError):
        raise RunFileError(f"{path}: run file has no valid format_version ({version!r})") from None
    if version > RUN_FILE_VERSION:
        raise RunFileError(
            f"{path}: run file format version {version} is newer than this software reads "
            f"(up to {RUN_FILE_VERSION}); update mirrorgonio"
        )
    if version < 1:
        raise RunFileError(f"{path}: run file has an invalid format_version {version}")


_DATASETS = {
    "header/rig_json": None,
    "header/run_json": None,
    "schedule/commanded_pose": 2,
    "schedule/light_pose": 2,
    "positions/measured_pose": 2,
    "positions/times": 2,
    "positions/frame_count": 1,
    "positions/complete": 1,
    "frames/raw": 4,
    "frames/exposure_s": 2,
    "frames/black_level": 4,
    "frames/white_level": 2,
    "frames/timestamp": 2,
    "frames/cfa_pattern": 2,
    "status/state": 0,
    "status/message": 0,
}


@functools.lru_cache(maxsize=16)
def _rig_from_json(rig_json: str, source: str) -> Rig:
    """The rig a run file's header describes, validated once per process and text: every
    position task opens the run anew, and the physical checks took half of an open (6 ms).
    Rig models are frozen, so the one object can be shared."""
    return rig_from_dict(json.loads(rig_json), source=source)


#: Headers already checked, by the file's identity and state: every position task of a
#: processing opens the run file again, and checking its layout and rebuilding the header took
#: 3 ms of each (some 30 HDF5 lookups). A file that changes (one being written, one replaced)
#: is checked again: its modification time, size or inode differ.
_HEADERS: dict[tuple, RunHeader] = {}
_HEADERS_KEPT = 8


def _read_header_once(f: h5py.File, path: Path) -> RunHeader:
    """:func:`_read_header`, or the header this process already read from the file unchanged."""
    try:
        st = os.stat(path)
        key = (str(path.resolve()), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
    except OSError:
        return _read_header(f, path)
    header = _HEADERS.get(key)
    if header is None:
        header = _read_header(f, path)
        if len(_HEADERS) >= _HEADERS_KEPT:
            _HEADERS.pop(next(iter(_HEADERS)))
        _HEADERS[key] = header
    # Each RunFile its own containers (the rig is shared, as _rig_from_json shares it).
    return replace(
        header,
        tool_poses=list(header.tool_poses),
        light_poses=list(header.light_poses),
        bracket=copy.deepcopy(header.bracket),
        metadata=copy.deepcopy(header.metadata),
        devices=copy.deepcopy(header.devices),
        references=copy.deepcopy(header.references),
    )


def _read_header(f: h5py.File, path) -> RunHeader:
    """Check the layout and rebuild the :class:`RunHeader`; RunFileError if broken."""
    _check_format(f, path)
    for name, ndim in _DATASETS.items():
        try:
            dset = f[name]
        except (KeyError, OSError, RuntimeError):
            raise RunFileError(f"{path}: corrupt run file: /{name} is missing or unreadable") from None
        if not isinstance(dset, h5py.Dataset) or (ndim is not None and dset.ndim != ndim):
            raise RunFileError(f"{path}: corrupt run file: /{name} has the wrong shape")
    try:
        rig_json = _text(f["header/rig_json"][()])
        run_json = _text(f["header/run_json"][()])
        commanded = f["schedule/commanded_pose"][()]
        light = f["schedule/light_pose"][()]
        raw_shape = f["frames/raw"].shape
    except (OSError, RuntimeError) as exc:
        raise RunFileError(f"{path}: corrupt run file: {_h5_cause(exc)}") from None
    n, max_exposures, height, width = raw_shape
    if commanded.shape != (n, 6) or light.shape != (n, 6):
        raise RunFileError(f"{path}: corrupt run file: the schedule does not match /frames/raw")
    for name in ("positions/measured_pose", "positions/times", "positions/frame_count", "positions/complete"):
        if f[name].shape[0] != n:
            raise RunFileError(f"{path}: corrupt run file: /{name} does not match the schedule")
    for name in _FRAME_RECORDS:
        if f[f"frames/{name}"].shape[:2] != (n, max_exposures):
            raise RunFileError(f"{path}: corrupt run file: /frames/{name} does not match /frames/raw")
    try:
        run = json.loads(run_json)
        rig_data = json.loads(rig_json)
    except json.JSONDecodeError as exc:
        raise RunFileError(f"{path}: corrupt run file: header is not valid JSON ({exc})") from None
    if not isinstance(run, dict) or not isinstance(rig_data, dict):
        raise RunFileError(f"{path}: corrupt run file: header is not a JSON object")
    try:
        rig = _rig_from_json(rig_json, f"{path}: /header/rig_json")
    except ValueError as exc:
        raise RunFileError(str(exc)) from None
    return RunHeader(
        run_id=str(run.get("run_id", "")),
        rig=rig,
        tool_poses=_poses_from(commanded),
        light_poses=_poses_from(light),
        max_exposures=int(max_exposures),
        frame_shape=(int(height), int(width)),
        bracket=run.get("bracket", {}),
        metadata=run.get("metadata", {}),
        devices=run.get("devices", {}),
        software_version=str(run.get("software_version", "")),
        created_utc=str(run.get("created_utc", "")),
        preset=str(run.get("preset", "")),
        references=run.get("references", {}) if isinstance(run.get("references", {}), dict) else {},
    )


def _header_strings(path, header: RunHeader) -> tuple[str, str]:
    """Validate a new run's header; its rig and run JSON."""
    problems = []
    if not isinstance(header.rig, Rig):
        problems.append("rig: not a Rig")
    n = len(header.tool_poses)
    if n < 1:
        problems.append("tool_poses: the run has no positions")
    if len(header.light_poses) != n:
        problems.append(f"light_poses: {len(header.light_poses)} poses for {n} tool poses")
    if not all(isinstance(p, Pose) for p in list(header.tool_poses) + list(header.light_poses)):
        problems.append("tool_poses/light_poses: every entry must be a Pose")
    if not _whole(header.max_exposures) or not 1 <= header.max_exposures <= np.iinfo(np.int16).max:
        problems.append(f"max_exposures: must be a whole number from 1 to 32767 (got {header.max_exposures!r})")
    shape = tuple(header.frame_shape) if isinstance(header.frame_shape, (tuple, list)) else ()
    if len(shape) != 2 or not all(_whole(v) and v > 0 for v in shape):
        problems.append(f"frame_shape: must be (height, width) in pixels (got {header.frame_shape!r})")
    if not isinstance(header.bracket, dict) or header.bracket.get("mode") not in ("fixed", "auto"):
        problems.append("bracket: must be a dict with mode 'fixed' or 'auto'")
    for name in ("metadata", "devices", "references"):
        if not isinstance(getattr(header, name), dict):
            problems.append(f"{name}: must be a dict")
    if not header.run_id:
        problems.append("run_id: empty")
    if problems:
        raise RunFileError(f"{path}: cannot create the run: {problems[0]}")
    run = {
        "run_id": str(header.run_id),
        "preset": str(header.preset),
        "bracket": header.bracket,
        "metadata": header.metadata,
        "devices": header.devices,
        "software_version": str(header.software_version),
        "created_utc": str(header.created_utc),
        "references": header.references,
    }
    try:
        run_json = json.dumps(run, ensure_ascii=False, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise RunFileError(f"{path}: cannot create the run: header is not plain JSON data ({exc})") from None
    rig_json = json.dumps(header.rig.model_dump(mode="json"), ensure_ascii=False)
    return rig_json, run_json


# --- writing -----------------------------------------------------------------------------
class RunFileWriter:
    """Writes one run file, position by position (see the module's crash-safety notes).

    Open it with :meth:`create` or :meth:`reopen`, never directly. Methods may be called
    from more than one thread (each call holds an internal lock).

    Attributes
    ----------
    path : Path
        The run file.
    header : RunHeader
        The run's header, as stored in the file.
    """

    def __init__(self, path: Path, f: h5py.File, header: RunHeader, lock: _WriterLock):
        self.path = path
        self.header = header
        self._f = f
        self._lock = lock
        self._mutex = threading.RLock()
        self._sync_fd: int | None = os.open(path, os.O_RDONLY)
        self._n = header.n_positions

    # --- opening -------------------------------------------------------------------------
    @classmethod
    def create(cls, path, header: RunHeader) -> RunFileWriter:
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
        rig_json, run_json = _header_strings(path, header)
        commanded = _poses_array(header.tool_poses)
        light = _poses_array(header.light_poses)
        lock = _WriterLock(path)
        try:
            if path.exists():
                raise RunFileError(f"{path}: run file already exists")
            tmp = Path(str(path) + ".tmp")
            try:
                with h5py.File(tmp, "w", libver="latest") as f:
                    _build_layout(
                        f,
                        rig_json,
                        run_json,
                        commanded,
                        light,
                        int(header.max_exposures),
                        (int(header.frame_shape[0]), int(header.frame_shape[1])),
                    )
                _fsync_path(tmp)
                os.replace(tmp, path)
            except OSError as exc:
                with contextlib.suppress(OSError):
                    tmp.unlink()
                raise RunFileError(f"{path}: cannot create the run file: {_h5_cause(exc)}") from None
            _fsync_dir(path)
            return cls._open_for_writing(path, lock)
        except BaseException:
            lock.release()
            raise

    @classmethod
    def reopen(cls, path) -> RunFileWriter:
        """Open an existing run file to go on writing (resume).

        A file whose writer was killed cannot be opened for writing again (HDF5 leaves
        it marked "open for write"); it is salvaged: its header, schedule and complete
        positions (frames copied as their compressed chunks) go into a fresh file that
        replaces it, status ``interrupted``. Incomplete positions are left empty, to be
        taken again.

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
        lock = _WriterLock(path)
        try:
            RunFile.open(path).close()  # the reader's checks, before touching the file
            return cls._open_for_writing(path, lock, salvage=True)
        except BaseException:
            lock.release()
            raise

    @classmethod
    def _open_for_writing(cls, path: Path, lock: _WriterLock, salvage: bool = False) -> RunFileWriter:
        try:
            f = _open_swmr_write(path)
        except OSError as exc:
            cause = _h5_cause(exc)
            if salvage and "already open for write" in cause:
                _salvage(path)
                return cls._open_for_writing(path, lock, salvage=False)
            if "unable to lock file" in cause:
                raise RunFileError(f"{path}: the run file is open in another process (close it there first)") from None
            if not h5py.is_hdf5(path):
                raise RunFileError(f"{path}: not an HDF5 file") from None
            raise RunFileError(f"{path}: cannot open the run file for writing: {cause}") from None
        try:
            header = _read_header(f, path)
        except BaseException:
            f.close()
            raise
        for suffix in (".tmp", ".salvage.tmp"):  # left by a creation or salvage that was killed
            with contextlib.suppress(OSError):
                Path(str(path) + suffix).unlink()
        return cls(path, f, header, lock)

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
            try:
                self._write(index, records, frames)
            except OSError as exc:
                raise RunFileError(f"{self.path}: position {index}: write failed: {_h5_cause(exc)}") from None

    def _validate(self, index, measured, times, frames) -> dict[str, np.ndarray]:
        where = f"{self.path}: position {index}"
        if not _whole(index) or not 0 <= index < self._n:
            raise RunFileError(f"{self.path}: position {index!r} out of range (0 to {self._n - 1})")
        if not isinstance(measured, Pose) or not all(math.isfinite(v) for v in measured.as_tuple()):
            raise RunFileError(f"{where}: measured pose must be a Pose of finite numbers (got {measured!r})")
        try:
            time_row = np.array([times.move_started, times.in_position, times.frames_done], dtype=np.float64)
        except (AttributeError, TypeError, ValueError):
            raise RunFileError(f"{where}: times must be a PositionTimes (got {times!r})") from None
        if not np.all(np.isfinite(time_row)):
            raise RunFileError(f"{where}: times must be finite (got {times!r})")
        maximum = self.header.max_exposures
        if not isinstance(frames, (list, tuple)):
            raise RunFileError(f"{where}: frames must be a list of RawFrame (got {type(frames).__name__})")
        if not 1 <= len(frames) <= maximum:
            raise RunFileError(f"{where}: {len(frames)} frames, expected 1 to {maximum}")
        height, width = self.header.frame_shape
        records = _empty_frame_records(1, maximum)
        records = {name: value[0] for name, value in records.items()}
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
            if not _whole(white) or not 0 < white < 2**31:
                raise RunFileError(f"{at}: white_level must be a positive whole number (got {white!r})")
            cfa = frame.cfa_pattern
            if not isinstance(cfa, str) or len(cfa) != _CFA_SITES or not cfa.isascii() or not cfa.isalpha():
                raise RunFileError(f"{at}: cfa_pattern must be 4 letters such as 'RGGB' (got {cfa!r})")
            records["exposure_s"][k] = exposure
            records["timestamp"][k] = timestamp
            records["black_level"][k] = black
            records["white_level"][k] = int(white)
            records["cfa_pattern"][k] = cfa.encode("ascii")
        records["measured_pose"] = np.array(measured.as_tuple(), dtype=np.float64)
        records["times"] = time_row
        return records

    def _write(self, index: int, records: dict[str, np.ndarray], frames: list[RawFrame]) -> None:
        f = self._f
        complete = f["positions/complete"]
        if complete[index]:
            complete[index] = 0
            self._flush(complete)
        raw = f["frames/raw"]
        for k, frame in enumerate(frames):
            raw[index, k] = frame.mosaic
        for k in range(len(frames), self.header.max_exposures):  # frames of an earlier take
            if raw.id.get_chunk_info_by_coord((index, k, 0, 0)).size:
                raw[index, k] = 0
        for name in _FRAME_RECORDS:
            f[f"frames/{name}"][index] = records[name]
        f["positions/measured_pose"][index] = records["measured_pose"]
        f["positions/times"][index] = records["times"]
        f["positions/frame_count"][index] = len(frames)
        self._flush(
            raw,
            *(f[f"frames/{name}"] for name in _FRAME_RECORDS),
            f["positions/measured_pose"],
            f["positions/times"],
            f["positions/frame_count"],
        )
        complete[index] = 1  # the commit marker, written and flushed last
        self._flush(complete)

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
            try:
                self._f["status/state"][()] = np.bytes_(state.encode("ascii"))
                self._f["status/message"][()] = np.bytes_(_encode_message(message))
                self._flush(self._f["status/state"], self._f["status/message"])
            except OSError as exc:
                raise RunFileError(f"{self.path}: cannot write the status: {_h5_cause(exc)}") from None

    # --- closing -------------------------------------------------------------------------
    def close(self) -> None:
        """Close the file and release the writer's lock (idempotent)."""
        with self._mutex:
            if self._f is None:
                return
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

    def __enter__(self) -> RunFileWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _whole(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _float(value) -> float | None:
    if isinstance(value, bool):
        return None
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


def _salvage(path: Path) -> None:
    """Copy the complete positions of a killed run into a fresh file replacing ``path``."""
    try:
        src = h5py.File(path, "r", swmr=True)
    except OSError as exc:
        raise RunFileError(f"{path}: cannot salvage the run file: {_h5_cause(exc)}") from None
    tmp = Path(str(path) + ".salvage.tmp")
    try:
        header = _read_header(src, path)
        n, max_exposures = header.n_positions, header.max_exposures
        try:
            complete = src["positions/complete"][()] == 1
            counts = src["positions/frame_count"][()].astype(np.int64)
            rows = {
                name: src[name][()] for name in ("positions/measured_pose", "positions/times", "positions/frame_count")
            }
            rows.update({f"frames/{name}": src[f"frames/{name}"][()] for name in _FRAME_RECORDS})
        except (OSError, RuntimeError) as exc:
            raise RunFileError(f"{path}: cannot salvage the run file: {_h5_cause(exc)}") from None
        complete &= (counts >= 1) & (counts <= max_exposures)
        with h5py.File(tmp, "w", libver="latest") as dst:
            _build_layout(
                dst,
                _text(src["header/rig_json"][()]),
                _text(src["header/run_json"][()]),
                src["schedule/commanded_pose"][()],
                src["schedule/light_pose"][()],
                max_exposures,
                header.frame_shape,
            )
            src_raw, dst_raw = src["frames/raw"], dst["frames/raw"]
            kept, lost = [], []
            for i in np.flatnonzero(complete):
                try:
                    chunks = [src_raw.id.read_direct_chunk((i, k, 0, 0)) for k in range(counts[i])]
                except (OSError, RuntimeError, ValueError):
                    lost.append(int(i))
                    continue
                for k, (mask, data) in enumerate(chunks):
                    dst_raw.id.write_direct_chunk((i, k, 0, 0), data, filter_mask=mask)
                kept.append(int(i))
            for name, values in rows.items():
                fresh = dst[name][()]
                fresh[kept] = values[kept]
                dst[name][...] = fresh
            flags = np.zeros(n, np.uint8)
            flags[kept] = 1
            dst["positions/complete"][...] = flags  # after the data, as always
            message = f"salvaged after the writer stopped unexpectedly: {len(kept)} of {n} positions complete"
            if lost:
                message += f"; positions {', '.join(map(str, lost))} were unreadable and will be taken again"
            dst["status/state"][()] = np.bytes_(b"interrupted")
            dst["status/message"][()] = np.bytes_(_encode_message(message))
    except OSError as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise RunFileError(f"{path}: cannot salvage the run file: {_h5_cause(exc)}") from None
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    finally:
        src.close()
    _fsync_path(tmp)
    os.replace(tmp, path)
    _fsync_dir(path)


# --- reading -----------------------------------------------------------------------------
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
    def open(cls, path) -> RunFile:
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
            raise RunFileError(f"{path}: cannot read the run file: {_h5_cause(exc)}") from None
        if not is_hdf5:
            raise RunFileError(f"{path}: not an HDF5 file")
        try:
            f = h5py.File(path, "r", swmr=True)
        except OSError as exc:
            cause = _h5_cause(exc)
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
            header = _read_header_once(f, path)
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

    def __exit__(self, *exc) -> None:
        self.close()

    def refresh(self) -> None:
        """See what a live writer has written since the file was opened."""
        for name, _ in _DATASETS.items():
            if name.startswith(("positions/", "frames/", "status/")):
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
        return _text(self._read("status/state", ())).strip()

    @property
    def status_message(self) -> str:
        """The last error or note the writer recorded."""
        return _text(self._read("status/message", ()))

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

    def exposures(self, i: int) -> np.ndarray:
        """Exposure times (s) of position ``i``'s frames, shape (k,)."""
        k = self._count(i)
        return self._read("frames/exposure_s", (i, slice(0, k)))

    def frames(self, i: int) -> np.ndarray:
        """Raw mosaics of position ``i``, uint16, shape (k, height, width)."""
        k = self._count(i)
        return self._read("frames/raw", (i, slice(0, k)), what=f"position {i} frames")

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
        return [_text(v) for v in self._read("frames/cfa_pattern", (i, slice(0, k)))]

    def timestamps(self, i: int) -> np.ndarray:
        """Capture times (unix s) of position ``i``'s frames, shape (k,)."""
        k = self._count(i)
        return self._read("frames/timestamp", (i, slice(0, k)))

    def frame(self, i: int, k: int) -> RawFrame:
        """Frame ``k`` of position ``i`` as a :class:`RawFrame`, with its metadata."""
        count = self._count(i)
        if not _whole(k) or not 0 <= k < count:
            raise RunFileError(f"{self.path}: position {i} has no frame {k!r} ({count} frames)")
        camera = self.header.devices.get("camera", "") if isinstance(self.header.devices, dict) else ""
        return RawFrame(
            mosaic=self._read("frames/raw", (i, k), what=f"position {i} frame {k}"),
            black_level=self._read("frames/black_level", (i, k)).astype(np.float64),
            white_level=int(self._read("frames/white_level", (i, k))),
            cfa_pattern=_text(self._read("frames/cfa_pattern", (i, k))),
            exposure_s=float(self._read("frames/exposure_s", (i, k))),
            timestamp=float(self._read("frames/timestamp", (i, k))),
            camera_id=str(camera),
            source=f"{self.path}:/frames/raw[{i},{k}]",
        )

    # --- internals -------------------------------------------------------------------------
    def _dset(self, name: str) -> h5py.Dataset:
        if self._f is None:
            raise RunFileError(f"{self.path}: the run file is closed")
        return self._f[name]

    def _read(self, name: str, selection, what: str | None = None):
        dset = self._dset(name)
        try:
            return dset[selection]
        except (OSError, RuntimeError) as exc:
            raise RunFileError(f"{self.path}: cannot read {what or '/' + name}: {_h5_cause(exc)}") from None

    def _check_index(self, i) -> None:
        if not _whole(i) or not 0 <= i < self.n_positions:
            raise RunFileError(f"{self.path}: position {i!r} out of range (0 to {self.n_positions - 1})")

    def _is_complete(self, i) -> bool:
        self._check_index(i)
        return bool(self._read("positions/complete", i) == 1)

    def _count(self, i) -> int:
        if not self._is_complete(i):
            raise RunFileError(f"{self.path}: position {i} is not complete")
        k = int(self._read("positions/frame_count", i))
        if not 1 <= k <= self.max_exposures:
            raise RunFileError(f"{self.path}: corrupt run file: position {i} has frame_count {k}")
        return k
