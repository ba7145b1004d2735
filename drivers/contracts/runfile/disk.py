"""The run file on the disk: syncing a file and its directory, and a file's SHA-256."""

from __future__ import annotations

import contextlib
import hashlib
import os
from pathlib import Path


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
