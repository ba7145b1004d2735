"""The run file on the disk: syncing a file and its directory, a file's SHA-256, and the
writes the storage refuses (a full disk, a read-only file system, an I/O error)."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import re
import tempfile
from collections.abc import Iterator
from pathlib import Path

import h5py

from drivers.contracts.runfile.layout import RunFileWriteError, h5_cause

#: The errors of a write that the storage refused (not the program's fault), as a person says them.
STORAGE_ERRNOS: dict[int, str] = {
    errno.ENOSPC: "no space left on device",
    errno.EDQUOT: "disk quota exceeded",
    errno.EFBIG: "file too large",
    errno.EROFS: "read-only file system",
    errno.EIO: "I/O error",
}
#: Those that more free space cures (the others need the storage mended).
NO_SPACE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG})
_ERRNO_IN_TEXT = re.compile(r"(?:errno = |\[Errno )(\d+)")


def storage_errno(exc: BaseException) -> int | None:
    """The :data:`STORAGE_ERRNOS` code behind ``exc``, or None when it is another failure.

    HDF5's errors carry the code only in their text (``errno = 28, error message = 'No space
    left on device'``), and errors re-raised with a one-line message (``[Errno 30] ...`` or the
    system's own words) likewise; an :class:`OSError` carries it as ``errno``.
    """
    code = getattr(exc, "errno", None)
    if isinstance(code, int) and code in STORAGE_ERRNOS:
        return code
    text = str(exc)
    for match in _ERRNO_IN_TEXT.finditer(text):
        if int(match.group(1)) in STORAGE_ERRNOS:
            return int(match.group(1))
    lowered = text.lower()
    for code in STORAGE_ERRNOS:
        if os.strerror(code).lower() in lowered:
            return code
    return None


def write_error(path: Path, what: str, exc: BaseException) -> RunFileWriteError:
    """The one-line error of a failed write of ``what`` (``position 12``) to ``path``: the
    storage's words when it refused (``no space left on device writing PATH (position 12)``),
    HDF5's cause otherwise."""
    code = storage_errno(exc)
    if code is not None:
        return RunFileWriteError(f"{STORAGE_ERRNOS[code]} writing {path} ({what})", code)
    return RunFileWriteError(f"{path}: {what}: write failed: {h5_cause(exc)}")


def drop_unwritten(f: h5py.File) -> None:
    """Point an open HDF5 file's descriptor at an anonymous memory file, so that what HDF5
    still holds unwritten goes nowhere and the file can be closed.

    HDF5 keeps data it failed to write (a full disk, a read-only file system, an I/O error) in
    its caches and tries again at every flush and at close; an object it then cannot close
    stays open with the file, and flushing that file again crashes the process (measured:
    a segmentation fault in ``H5Fflush`` once the disk had room again). Dropping the unwritten
    data leaves the file on the disk as it was: what was flushed before stays readable.
    """
    fd = f.id.get_vfd_handle()
    if hasattr(os, "memfd_create"):
        sink = os.memfd_create("mirrorgonio-unwritten")
    else:  # pragma: no cover - not Linux
        sink = os.dup(tempfile.TemporaryFile().fileno())
    try:
        os.dup2(sink, fd)
    finally:
        os.close(sink)


@contextlib.contextmanager
def fresh_file(path: Path) -> Iterator[h5py.File]:
    """A new HDF5 file at ``path`` (latest format), flushed and closed when the block ends;
    if the block or the flush fails, its unwritten data is dropped (:func:`drop_unwritten`)
    before the close, so that a full disk leaves no half-closed file behind in HDF5."""
    f = h5py.File(path, "w", libver="latest")
    try:
        yield f
        f.flush()
    except BaseException:
        drop_unwritten(f)
        raise
    finally:
        f.close()


#: The HDF5 signature, and the superblock's file consistency flags "open for write" (bit 0)
#: and "open for SWMR write" (bit 2), in the superblock versions 2 and 3 a run file has.
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_OPEN_FOR_WRITE_FLAGS = 0b101


def marked_open_for_write(path: str | os.PathLike[str]) -> bool:
    """Whether the file at ``path`` is marked open for writing in its superblock: its writer
    did not close it (killed, or stopped by a failed write), so reopening it to write salvages
    it into a fresh copy (which needs room for the copy). False for a missing or other file."""
    try:
        with open(path, "rb") as f:
            head = f.read(12)
    except OSError:
        return False
    return len(head) == 12 and head[:8] == _HDF5_SIGNATURE and head[8] >= 2 and bool(head[11] & _OPEN_FOR_WRITE_FLAGS)


def file_sha256(path: str | os.PathLike[str], chunk_bytes: int = 1 << 20) -> str:
    """Hex SHA-256 of a file's bytes (the identity of a referenced file)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk_bytes):
            digest.update(block)
    return digest.hexdigest()


def fsync_path(path: Path) -> None:
    """Wait until the file at ``path`` is on the disk, not only in the page cache."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_dir(path: Path) -> None:
    """Put the directory holding ``path`` on the disk (a rename into it then survives a crash)."""
    with contextlib.suppress(OSError):  # not every file system lets a directory be synced
        fsync_path(path.parent if str(path.parent) else Path("."))
