"""The up-front checksum pass: every frame a processing will read, read through its checksum
before any work (the light run's processing, the reflectance), and what ``--ignore-corrupt``
skipped, on one line."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from drivers.contracts.runfile import CorruptFrame, RunFile, RunFileError
from processing.light_run.errors import ProcessingError

log = logging.getLogger("mirrorgonio.processing")

#: How the command line names the choice to skip corrupt positions (a job names it ``ignore_corrupt``).
IGNORE_CORRUPT = "--ignore-corrupt"


class CorruptRunError(ProcessingError):
    """A frame that fails its checksum, the processing not told to skip it: one line naming the
    run, the position and the frame, and the choice that processes the rest.

    Attributes
    ----------
    run_path : Path
        The run file.
    corrupt : list of CorruptFrame
        Every corrupt frame found (the first is named).
    """

    def __init__(self, run_path: Path, corrupt: Sequence[CorruptFrame]) -> None:
        self.run_path, self.corrupt = run_path, list(corrupt)
        super().__init__(self.line())

    def line(self, option: str = IGNORE_CORRUPT) -> str:
        """The error on one line, ``option`` named as what processes the rest."""
        more = f", and {len(self.corrupt) - 1} more corrupt frames (`mirrorgonio verify` lists them)"
        return (
            f"{self.run_path}: {self.corrupt[0].describe()}{more if len(self.corrupt) > 1 else ''}; "
            f"{option} processes the rest"
        )


def sound_positions(
    run: RunFile,
    run_path: Path,
    positions: np.ndarray,
    sets: Sequence[tuple[str, str]],
    ignore_corrupt: bool,
) -> tuple[np.ndarray, list[CorruptFrame]]:
    """Every frame of ``positions`` and of the calibration ``sets`` read through its checksum,
    before any work: the positions to process and the frames skipped.

    A position with a corrupt frame is skipped whole (its bracket merged without one exposure
    would hold saturated or noisier pixels than its neighbours'); only with ``ignore_corrupt``:
    without it the first corrupt frame is a one-line :class:`CorruptRunError`.

    Raises
    ------
    ProcessingError
        A position or set that is not complete (:class:`CorruptRunError` for a corrupt frame);
        every position given has a corrupt frame.
    """
    try:
        corrupt = run.corrupt_frames(positions, sets)
    except RunFileError as exc:
        raise ProcessingError(str(exc)) from None
    if not corrupt:
        return positions, []
    if not ignore_corrupt:
        raise CorruptRunError(run_path, corrupt)
    bad = {frame.position for frame in corrupt if frame.position is not None}
    kept = np.array([i for i in positions if int(i) not in bad], dtype=positions.dtype)
    log.warning("%s: %s", run_path, skipped_line(corrupt))
    if kept.size == 0 and positions.size:
        raise ProcessingError(f"{run_path}: every complete position has a corrupt frame: nothing to process")
    return kept, corrupt


def skipped_line(corrupt: Sequence[CorruptFrame], option: str = IGNORE_CORRUPT) -> str:
    """What ``--ignore-corrupt`` (``option``) skipped, on one line."""
    positions = sorted({frame.position for frame in corrupt if frame.position is not None})
    sets = sorted({frame.slot for frame in corrupt if frame.position is None})
    parts = [f"positions {', '.join(map(str, positions))}"] if positions else []
    parts += [f"the {name} frames" for name in sets]
    frames = "; ".join(frame.describe() for frame in corrupt[:3]) + ("; …" if len(corrupt) > 3 else "")
    return f"skipped {' and '.join(parts)} ({option}): {len(corrupt)} corrupt frames: {frames}"
