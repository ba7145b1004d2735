"""The writer's lock: one process at a time writes a run file."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
from pathlib import Path

from drivers.contracts.runfile.layout import RunFileError


class WriterLock:
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
        """Remove the lock file and drop the lock (idempotent)."""
        if self._fd is None:
            return
        with contextlib.suppress(OSError):
            os.unlink(self.path)
        os.close(self._fd)
        self._fd = None
