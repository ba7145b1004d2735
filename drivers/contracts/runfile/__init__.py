"""The run file: one HDF5 file per run, written position by position, safe to kill.

This package is the only place that knows the layout (see ``docs/run-file.md``). The
acquisition writes with :class:`RunFileWriter`; the processing and anyone else read with
:class:`RunFile`. Its modules, in the order of the data:

* :mod:`~drivers.contracts.runfile.layout`: the format, the records (:class:`RunHeader`,
  :class:`PositionTimes`, :class:`CalibrationFrames`) and the empty layout of a new file;
* :mod:`~drivers.contracts.runfile.header`: the header encoded for a new file, read back
  and checked from an existing one;
* :mod:`~drivers.contracts.runfile.writer`: :class:`RunFileWriter`, with its lock
  (:mod:`~drivers.contracts.runfile.lock`) and the salvage of a killed run
  (:mod:`~drivers.contracts.runfile.salvage`);
* :mod:`~drivers.contracts.runfile.reader`: :class:`RunFile`, whose frames are read through
  their checksums (:mod:`~drivers.contracts.runfile.check`: a frame that fails its checksum is
  a :class:`FrameCorruptError`);
* :mod:`~drivers.contracts.runfile.disk`: syncing files to the disk, a file's SHA-256, the
  writes the storage refuses.

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
  everything else of the position; a reader trusts only positions whose flag is 1; a
  calibration set (:meth:`RunFileWriter.write_calibration`) likewise by its
  ``/calibration/complete`` flag;
* readers always open with ``swmr=True``, which works on a file whose writer was killed
  (a normal open refuses it: HDF5 marks it "already open for write");
* :meth:`RunFileWriter.reopen` of a killed run copies its complete positions and calibration
  sets, frames as their compressed chunks, into a fresh file that replaces the old one
  (salvage).

A lock file ``PATH.lock`` (``flock``, released by the kernel when the writer dies) keeps
a second writer off a run that is still being written; it is removed on a clean close.

Write failures
--------------
A write the storage refuses (a full disk, a read-only file system, an I/O error) raises
:class:`RunFileWriteError`, one line such as ``no space left on device writing
/data/runs/X.h5 (position 12)``. The writer then drops what HDF5 holds unwritten and
refuses to write again; the file on the disk keeps every position committed before, and
is salvaged like a killed run's when the run resumes (which needs room for the copy).
"""

from drivers.contracts.runfile.check import CorruptFrame, FrameCorruptError
from drivers.contracts.runfile.disk import (
    NO_SPACE_ERRNOS,
    STORAGE_ERRNOS,
    file_sha256,
    marked_open_for_write,
    storage_errno,
)
from drivers.contracts.runfile.layout import (
    CALIBRATION_MAX_FRAMES,
    CALIBRATION_ROLES,
    CALIBRATION_SETS,
    CALIBRATION_WHENS,
    MESSAGE_BYTES,
    RUN_FILE_FORMAT,
    RUN_FILE_VERSION,
    STATE_BYTES,
    STATES,
    CalibrationFrames,
    PositionTimes,
    RunFileError,
    RunFileWriteError,
    RunHeader,
)
from drivers.contracts.runfile.reader import RunFile
from drivers.contracts.runfile.writer import RunFileWriter

__all__ = [
    "CALIBRATION_MAX_FRAMES",
    "CALIBRATION_ROLES",
    "CALIBRATION_SETS",
    "CALIBRATION_WHENS",
    "MESSAGE_BYTES",
    "NO_SPACE_ERRNOS",
    "RUN_FILE_FORMAT",
    "RUN_FILE_VERSION",
    "STATES",
    "STATE_BYTES",
    "STORAGE_ERRNOS",
    "CalibrationFrames",
    "CorruptFrame",
    "FrameCorruptError",
    "PositionTimes",
    "RunFile",
    "RunFileError",
    "RunFileWriteError",
    "RunFileWriter",
    "RunHeader",
    "file_sha256",
    "marked_open_for_write",
    "storage_errno",
]
