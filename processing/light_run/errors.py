"""The light run's one-line error, and the run file opened with it."""

from __future__ import annotations

import logging
import os

from drivers.contracts.runfile import RunFile, RunFileError

log = logging.getLogger("mirrorgonio.processing")


class ProcessingError(ValueError):
    """A run that cannot be processed (one line naming the file and the cause)."""


def open_run(path: str | os.PathLike[str]) -> RunFile:
    try:
        return RunFile.open(path)
    except RunFileError as exc:
        raise ProcessingError(str(exc)) from None
