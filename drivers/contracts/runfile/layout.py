"""The run file's layout: its format name and version, the records a run holds (the header,
a position's times), building the empty layout of a new file and checking an opened one's format.

This is the one place that knows the HDF5 layout (see ``docs/run-file.md``); the reader and the
writer of :mod:`drivers.contracts.runfile` build on it.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from typing import Any

import h5py
import hdf5plugin
import numpy as np

from drivers.contracts.rig import Rig
from drivers.pose import Pose

RUN_FILE_FORMAT = "mirrorgonio-run"
#: 2: the ``/calibration`` group (frames taken with the light off, before and after the sweep).
RUN_FILE_VERSION = 2

#: The states a run file's ``/status/state`` may hold.
STATES = ("created", "running", "paused", "complete", "aborted", "failed", "interrupted")
STATE_BYTES = 16
MESSAGE_BYTES = 1024
#: ``/header/camera_colour_json``: the camera's colour matrices as JSON, filled from the first
#: frame that carries them (empty until then, and for a camera whose files carry none). Fixed
#: in size, as the status is, so that the writer fills it in SWMR mode; optional in a file
#: (files without it read as "no colour matrices").
CAMERA_COLOUR = "header/camera_colour_json"
CAMERA_COLOUR_BYTES = 2048

#: The per-frame records stored beside each raw mosaic, under ``/frames``.
FRAME_RECORDS = ("exposure_s", "black_level", "white_level", "timestamp", "cfa_pattern")


#: Every dataset of the layout and its number of dimensions (None: a scalar string).
DATASETS: dict[str, int | None] = {
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

#: What a calibration frame shows: ``ambient``, the light off and the room lit (the ball's
#: silhouette); ``dark``, the light off and the room dark (the black level and read noise).
CALIBRATION_ROLES = ("ambient", "dark")
#: When a calibration set is taken: before the first position or after the last one.
CALIBRATION_WHENS = ("before", "after")
#: The calibration sets a run file has room for, in the order of ``/calibration``'s first axis.
CALIBRATION_SETS = tuple((role, when) for role in CALIBRATION_ROLES for when in CALIBRATION_WHENS)
#: The most frames one calibration set may hold.
CALIBRATION_MAX_FRAMES = 16

#: The datasets of ``/calibration`` (format version 2) and their number of dimensions.
CALIBRATION_DATASETS: dict[str, int | None] = {
    "calibration/role": 1,
    "calibration/when": 1,
    "calibration/frame_count": 1,
    "calibration/complete": 1,
    "calibration/raw": 4,
    "calibration/exposure_s": 2,
    "calibration/black_level": 4,
    "calibration/white_level": 2,
    "calibration/timestamp": 2,
    "calibration/cfa_pattern": 2,
}


class RunFileError(ValueError):
    """A run file that cannot be written or read (one line: the file and the cause)."""


class RunFileWriteError(RunFileError):
    """A write to the run file that failed (one line: what was written, where, and why).

    Attributes
    ----------
    errno : int or None
        The storage's refusal (``errno.ENOSPC``, ``EROFS``, ``EIO``, ...:
        :data:`~drivers.contracts.runfile.disk.STORAGE_ERRNOS`), None for another failure.
    """

    def __init__(self, message: str, errno: int | None = None):
        super().__init__(message)
        self.errno = errno


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


@dataclass(frozen=True, eq=False)
class CalibrationFrames:
    """One calibration set: the frames of a role taken at one time (see ``docs/run-file.md``).

    Attributes
    ----------
    frames : ndarray of uint16, shape (k, H, W)
        The raw mosaics.
    exposures_s : ndarray of float64, shape (k,)
        Their exposure times, as the camera recorded them.
    black_level : ndarray of float64, shape (2, 2)
        Black level per CFA site, laid out like ``cfa_pattern``: the mean of the frames' own.
    white_level : int
        The saturation level: the lowest of the frames' own.
    cfa_pattern : str
        The 2x2 CFA tile, row-major, e.g. ``"RGGB"`` (one for the whole set).
    timestamps : ndarray of float64, shape (k,)
        Capture times, unix seconds.
    """

    frames: np.ndarray
    exposures_s: np.ndarray
    black_level: np.ndarray
    white_level: int
    cfa_pattern: str
    timestamps: np.ndarray


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
    calibration : dict
        The calibration sets the run planned and how (``docs/run-file.md``): ``sets`` (a list
        of ``[role, when]``), ``switch`` (the light switch), the ``ambient_exposures_s`` and the
        way dark frames are taken; ``sets`` empty, with a ``reason``, for a run that takes none.
        Empty for a file of format version 1.
    camera_colour : dict
        The camera's colour matrices as its raw files carry them
        (:mod:`drivers.contracts.camera_colour`), read from the run's first frame that has
        them; empty where none is known (a file written before the run file kept them, a
        camera whose files carry none): the run's colour is then camera RGB only.
    """

    run_id: str
    rig: Rig
    tool_poses: list[Pose]
    light_poses: list[Pose]
    max_exposures: int
    frame_shape: tuple[int, int]
    bracket: dict[str, Any]
    metadata: dict[str, Any]
    devices: dict[str, Any]
    software_version: str
    created_utc: str
    preset: str = ""
    references: dict[str, Any] = field(default_factory=dict)
    calibration: dict[str, Any] = field(default_factory=dict)
    camera_colour: dict[str, Any] = field(default_factory=dict)

    @property
    def n_positions(self) -> int:
        return len(self.tool_poses)


# --- the layout --------------------------------------------------------------------------
def build_layout(
    f: h5py.File,
    rig_json: str,
    run_json: str,
    commanded: np.ndarray,
    light: np.ndarray,
    max_exposures: int,
    frame_shape: tuple[int, int],
    calibration_frames: int = CALIBRATION_MAX_FRAMES,
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
    create_frame_stack(f.create_group("frames"), n, max_exposures, (height, width))
    build_calibration_layout(f, calibration_frames, frame_shape)
    status = f.create_group("status")
    status.create_dataset("state", data=np.bytes_(b"created"), dtype=f"S{STATE_BYTES}")
    status.create_dataset("message", data=np.bytes_(b""), dtype=f"S{MESSAGE_BYTES}")
    header.create_dataset("camera_colour_json", data=np.bytes_(b""), dtype=f"S{CAMERA_COLOUR_BYTES}")


def build_calibration_layout(f: h5py.File, max_frames: int, frame_shape: tuple[int, int]) -> None:
    """Create ``/calibration``: a slot per calibration set, each with room for ``max_frames``.

    The slots' ``role`` and ``when`` are written now; a slot is committed, like a position, by
    its ``complete`` flag.
    """
    m = len(CALIBRATION_SETS)
    height, width = frame_shape
    group = f.create_group("calibration")
    group.create_dataset("role", data=np.array([role for role, _ in CALIBRATION_SETS], dtype="S8"))
    group.create_dataset("when", data=np.array([when for _, when in CALIBRATION_SETS], dtype="S8"))
    group.create_dataset("frame_count", data=np.zeros(m, np.int16))
    group.create_dataset("complete", data=np.zeros(m, np.uint8))
    create_frame_stack(group, m, max_frames, (height, width))


def create_frame_stack(group: h5py.Group, slots: int, per_slot: int, frame_shape: tuple[int, int]) -> None:
    """``raw`` (slots × per_slot frames, one chunk a frame: LZ4, then a Fletcher32 checksum of the
    compressed bytes) and its per-frame records, in ``group``: the sweep's positions and the
    calibration sets share the layout.

    HDF5 checks the checksum on every read of a chunk and refuses a chunk that fails it, so a
    flipped bit is an error, never different pixels (LZ4 alone decodes many flips silently).
    """
    height, width = frame_shape
    group.create_dataset(
        "raw",
        shape=(slots, per_slot, height, width),
        dtype=np.uint16,
        chunks=(1, 1, height, width),
        fillvalue=0,
        fletcher32=True,
        **hdf5plugin.LZ4(),
    )
    for name, value in empty_frame_records(slots, per_slot).items():
        group.create_dataset(name, data=value)


def calibration_slot(role: str, when: str) -> int:
    """The index of the calibration set ``(role, when)`` in ``/calibration``.

    Raises
    ------
    RunFileError
        An unknown role or time.
    """
    if role not in CALIBRATION_ROLES:
        raise RunFileError(f"calibration role {role!r} is not one of {', '.join(CALIBRATION_ROLES)}")
    if when not in CALIBRATION_WHENS:
        raise RunFileError(f"calibration time {when!r} is not one of {', '.join(CALIBRATION_WHENS)}")
    return CALIBRATION_SETS.index((role, when))


def empty_frame_records(n: int, max_exposures: int) -> dict[str, np.ndarray]:
    """The per-frame records of ``n`` positions before any frame is written, by name."""
    return {
        "exposure_s": np.full((n, max_exposures), np.nan),
        "black_level": np.full((n, max_exposures, 2, 2), np.nan, dtype=np.float32),
        "white_level": np.zeros((n, max_exposures), np.int32),
        "timestamp": np.full((n, max_exposures), np.nan),
        "cfa_pattern": np.zeros((n, max_exposures), dtype="S4"),
    }


def check_format(f: h5py.File, path: str | os.PathLike[str]) -> int:
    """The format version of ``f``; a :class:`RunFileError` unless it is a mirrorgonio run file of
    a version this reads."""
    fmt = f.attrs.get("format")
    if fmt is None:
        raise RunFileError(f"{path}: not a mirrorgonio run file (no 'format' attribute)")
    if as_text(fmt) != RUN_FILE_FORMAT:
        raise RunFileError(f"{path}: not a mirrorgonio run file (format is {as_text(fmt)!r})")
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
    return version


# --- values shared by the reader and the writer -------------------------------------------
def h5_cause(exc: BaseException) -> str:
    """The useful part of an h5py error: ``Unable to ... (cause)`` gives ``cause``."""
    text = str(exc)
    match = re.search(r"\((.*)\)\s*$", text)
    cause = match.group(1) if match else text
    return " ".join(cause.split())


def encode_message(message: str) -> bytes:
    """``message`` as ``/status/message`` stores it: UTF-8, no NUL, cut to whole characters."""
    data = str(message).replace("\x00", " ").encode("utf-8")
    if len(data) > MESSAGE_BYTES:
        data = data[:MESSAGE_BYTES].decode("utf-8", errors="ignore").encode("utf-8")
    return data


def as_text(value: object) -> str:
    """A string read from the file (bytes, a scalar array or a str) as a str."""
    if isinstance(value, bytes):
        return value.decode("utf-8", errors="replace")
    if isinstance(value, np.ndarray):
        return as_text(value[()])
    return str(value)


def is_whole(value: object) -> bool:
    """Whether ``value`` is an integer (a bool is not)."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)
