"""The data directory's storage: the errors of writes it refuses, its free space, and the
size a run will take (``docs/daemon.md``, "When the disk fills").

A write the storage refuses is :class:`InsufficientStorageError` when more free space cures
it (a full disk, a quota: HTTP 507) and :class:`StorageUnavailableError` otherwise (a
read-only file system, an I/O error, a busy catalog: HTTP 503), one line each.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

from drivers.contracts.runfile import STORAGE_ERRNOS, RunFileError, RunFileWriteError, storage_errno

MB = 1_000_000
#: What a run needs besides its frames: the run file's header, schedule and records, and the
#: catalog's rows (a run file of the default rig's 66 positions without frames is ~0.2 MB).
OVERHEAD_BYTES = 1 * MB
#: Bytes of one stored pixel (uint16).
PIXEL_BYTES = 2


class StorageError(Exception):
    """A write the data directory's storage refused, or would refuse (one line)."""


class InsufficientStorageError(StorageError):
    """Not enough free space (HTTP 507): freeing space cures it."""


class StorageUnavailableError(StorageError):
    """The storage cannot be written (HTTP 503): read-only, failing, or busy."""


def mb(n_bytes: float) -> str:
    """``n_bytes`` for a person: ``12.3 MB``."""
    return f"{n_bytes / MB:.1f} MB"


def free_bytes(path: str | os.PathLike[str]) -> int:
    """Bytes an unprivileged writer can still use on ``path``'s file system."""
    st = os.statvfs(path)
    return st.f_bavail * st.f_frsize


def frame_bytes(frame_shape: tuple[int, int]) -> int:
    """The bytes of one uncompressed frame of ``frame_shape`` (rows, columns)."""
    return int(frame_shape[0]) * int(frame_shape[1]) * PIXEL_BYTES


def run_bytes(frames: int, frame_shape: tuple[int, int], compression_ratio: float) -> int:
    """The estimated size of a run of ``frames`` frames of ``frame_shape``, each stored at
    ``compression_ratio`` of its raw size, with the run file's records and the catalog's rows."""
    return int(frames * frame_bytes(frame_shape) * compression_ratio) + OVERHEAD_BYTES


def min_free_bytes(min_free_mb: float | None, frame_shape: tuple[int, int], exposures: int) -> int:
    """The free space below which the daemon reports itself degraded: ``min_free_mb``, or one
    position of ``exposures`` uncompressed frames with the run file's and catalog's margin."""
    if min_free_mb is not None:
        return int(min_free_mb * MB)
    return exposures * frame_bytes(frame_shape) + OVERHEAD_BYTES


def failure_message(exc: BaseException, path: Path | None) -> str:
    """The one-line ``last_error`` of a run that failed with ``exc`` while writing ``path``: the
    message of a write error, the storage's words for another write it refused (``read-only
    file system writing PATH``), else the error's own message."""
    if isinstance(exc, RunFileWriteError | StorageError):
        return str(exc)
    code = storage_errno(exc)
    if code is not None and path is not None:
        return f"{STORAGE_ERRNOS[code]} writing {path}"
    if isinstance(exc, RunFileError):
        return str(exc)
    return f"{type(exc).__name__}: {exc}"


def directory_problems(directories: list[Path], min_free: int) -> list[str]:
    """Why the daemon cannot write its data now: a directory that cannot be read or written,
    on a read-only file system, or with less than ``min_free`` bytes free (one line each;
    each file system once). Empty when all is well.
    """
    problems, seen = [], set()
    for directory in directories:
        try:
            device = os.stat(directory).st_dev
            st = os.statvfs(directory)
        except OSError as exc:
            problems.append(f"data directory {directory}: {exc.strerror or exc}")
            continue
        if device in seen:
            continue
        seen.add(device)
        free = st.f_bavail * st.f_frsize
        if st.f_flag & os.ST_RDONLY:
            problems.append(f"data directory {directory}: {STORAGE_ERRNOS[errno.EROFS]}")
        elif not os.access(directory, os.W_OK):
            problems.append(f"data directory {directory}: not writable by the daemon")
        elif free < min_free:
            problems.append(
                f"data directory {directory}: {mb(free)} free, less than the {mb(min_free)} "
                "a position needs (storage.min_free_mb)"
            )
    return problems


def check_room(directory: Path, needed: int, what: str) -> None:
    """Refuse ``what`` (``the run``) unless ``directory`` can be written and has ``needed``
    bytes free.

    Raises
    ------
    StorageUnavailableError
        The directory's file system is read-only, or the directory cannot be written.
    InsufficientStorageError
        Less than ``needed`` bytes free; the message gives both, and how to start anyway.
    """
    problems = directory_problems([directory], 0)
    if problems:
        raise StorageUnavailableError(f"{what}: {problems[0]}")
    free = free_bytes(directory)
    if free < needed:
        raise InsufficientStorageError(
            f"{what} needs about {mb(needed)}, {mb(free)} free in {directory}: "
            'free some space, or send "force": true to start anyway'
        )


def storage_error(exc: OSError, path: Path) -> StorageError | OSError:
    """A write of ``path`` the storage refused as the one-line error the API maps to 507 (full)
    or 503 (read-only, an I/O error); ``exc`` itself for any other failure."""
    code = storage_errno(exc)
    if code is None:
        return exc
    kind = InsufficientStorageError if code == errno.ENOSPC else StorageUnavailableError
    return kind(f"{STORAGE_ERRNOS[code]} writing {path}")
