"""A stored frame read back through its checksum: what is wrong with a frame that does not.

Every frame is one HDF5 chunk, LZ4-compressed, then checksummed (Fletcher32, over the compressed
bytes). HDF5 checks the checksum whenever the chunk is read and refuses it on a mismatch, so a
frame read back is the frame written, or an error. These helpers turn that error into a
:class:`CorruptFrame` naming the position (or calibration set) and the frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from drivers.contracts.runfile.layout import RunFileError, h5_cause


@dataclass(frozen=True)
class CorruptFrame:
    """A stored frame that does not read back as it was written.

    Attributes
    ----------
    path : Path
        The run file.
    slot : str
        Where the frame is: ``"position 3"``, or ``"calibration ambient before"``.
    position : int or None
        The position; None for a calibration frame.
    frame : int
        The frame's index in its bracket (its exposure index).
    exposure_s : float
        Its exposure time as recorded (NaN when that record is unreadable too).
    cause : str
        What is wrong: the checksum fails, the data cannot be decoded, or no data is stored.
    """

    path: Path
    slot: str
    position: int | None
    frame: int
    exposure_s: float
    cause: str

    def describe(self) -> str:
        """``position 3 frame 1 (exposure index 1, 0.004 s) fails its checksum …``: one line."""
        exposure = f", {self.exposure_s:.6g} s" if math.isfinite(self.exposure_s) else ""
        return f"{self.slot} frame {self.frame} (exposure index {self.frame}{exposure}) {self.cause}"

    def record(self) -> dict[str, object]:
        """The frame as plain JSON values (for a light model's provenance)."""
        return {
            "where": self.slot,
            "position": self.position,
            "frame": self.frame,
            "exposure_s": self.exposure_s if math.isfinite(self.exposure_s) else None,
            "cause": self.cause,
        }


class FrameCorruptError(RunFileError):
    """A frame read from a run file fails its checksum or cannot be decoded (one line naming the
    file, the position or calibration set, and the frame).

    Attributes
    ----------
    corrupt : CorruptFrame
        The frame.
    """

    def __init__(self, corrupt: CorruptFrame) -> None:
        super().__init__(f"{corrupt.path}: {corrupt.describe()}")
        self.corrupt = corrupt


def is_checksummed(raw: h5py.Dataset) -> bool:
    """Whether the frames of ``raw`` carry a checksum (its filter pipeline has Fletcher32)."""
    return bool(raw.fletcher32)


def failure_cause(raw: h5py.Dataset, exc: BaseException) -> str:
    """Why a frame of ``raw`` did not read back, from HDF5's error."""
    if is_checksummed(raw):
        return "fails its checksum (corrupt data: the stored bytes differ from those written)"
    return f"cannot be decoded (corrupt data: {h5_cause(exc)}; the file carries no frame checksums)"


def frame_fault(raw: h5py.Dataset, slot: int, k: int, buffer: np.ndarray | None = None) -> str | None:
    """Why frame ``k`` of slot ``slot`` of ``raw`` does not read back; None when it does.

    The frame is read whole (decoded and its checksum checked by HDF5) into ``buffer`` (a
    ``(H, W)`` uint16 array, reused between calls), and dropped.
    """
    if not raw.id.get_chunk_info_by_coord((slot, k, 0, 0)).size:
        return "is missing (no data stored for it)"
    if buffer is None:
        buffer = np.empty(raw.shape[2:], dtype=raw.dtype)
    try:
        raw.read_direct(buffer, np.s_[slot, k])
    except (OSError, RuntimeError) as exc:
        return failure_cause(raw, exc)
    return None
