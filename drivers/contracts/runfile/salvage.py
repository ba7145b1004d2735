"""Salvage: the complete positions of a run whose writer was killed, copied into a fresh file.

HDF5 leaves the file of a killed writer marked "open for write", and it cannot be opened for
writing again; its complete positions and complete calibration sets (frames copied as their
compressed chunks) go into a fresh file that replaces it. A set or position being written when
the writer died is left out, to be taken again, and so is one with a frame that fails its
checksum or cannot be read (a warning names it): every frame is read through its checksum
before its chunk is copied.
"""

from __future__ import annotations

import contextlib
import logging
import os
from pathlib import Path

import h5py
import numpy as np

from drivers.contracts.runfile.check import frame_fault, is_checksummed
from drivers.contracts.runfile.disk import fresh_file, fsync_dir, fsync_path, storage_errno, write_error
from drivers.contracts.runfile.header import read_header
from drivers.contracts.runfile.layout import (
    CALIBRATION_MAX_FRAMES,
    CALIBRATION_SETS,
    CAMERA_COLOUR,
    FRAME_RECORDS,
    RunFileError,
    as_text,
    build_layout,
    encode_message,
    h5_cause,
)

log = logging.getLogger("mirrorgonio.runfile")


def salvage_run(path: Path) -> None:
    """Copy the complete positions of a killed run into a fresh file replacing ``path``."""
    try:
        src = h5py.File(path, "r", swmr=True)
    except OSError as exc:
        raise RunFileError(f"{path}: cannot salvage the run file: {h5_cause(exc)}") from None
    tmp = Path(str(path) + ".salvage.tmp")
    try:
        header = read_header(src, path)
        n, max_exposures = header.n_positions, header.max_exposures
        try:
            complete = src["positions/complete"][()] == 1
            counts = src["positions/frame_count"][()].astype(np.int64)
            rows = {
                name: src[name][()] for name in ("positions/measured_pose", "positions/times", "positions/frame_count")
            }
            rows.update({f"frames/{name}": src[f"frames/{name}"][()] for name in FRAME_RECORDS})
        except (OSError, RuntimeError) as exc:
            raise RunFileError(f"{path}: cannot salvage the run file: {h5_cause(exc)}") from None
        complete &= (counts >= 1) & (counts <= max_exposures)
        calibration_frames = src["calibration/raw"].shape[1] if "calibration" in src else CALIBRATION_MAX_FRAMES
        with fresh_file(tmp) as dst:
            build_layout(
                dst,
                as_text(src["header/rig_json"][()]),
                as_text(src["header/run_json"][()]),
                src["schedule/commanded_pose"][()],
                src["schedule/light_pose"][()],
                max_exposures,
                header.frame_shape,
                calibration_frames,
            )
            sets_kept = _copy_calibration(src, dst) if "calibration" in src else []
            kept, lost = [], []
            for i in np.flatnonzero(complete):
                fault = copy_frames(src["frames/raw"], dst["frames/raw"], int(i), int(counts[i]))
                if fault is None:
                    kept.append(int(i))
                    continue
                lost.append(int(i))
                log.warning("%s: salvage: position %d frame %s: dropped, to be taken again", path, i, fault)
            for name, values in rows.items():
                fresh = dst[name][()]
                fresh[kept] = values[kept]
                dst[name][...] = fresh
            flags = np.zeros(n, np.uint8)
            flags[kept] = 1
            dst["positions/complete"][...] = flags  # after the data, as always
            message = f"salvaged after the writer stopped unexpectedly: {len(kept)} of {n} positions complete"
            if lost:
                message += (
                    f"; positions {', '.join(map(str, lost))} were unreadable or failed their checksums "
                    "and will be taken again"
                )
            if sets_kept:
                message += f"; calibration sets complete: {', '.join(sets_kept)}"
            if CAMERA_COLOUR in src:
                dst[CAMERA_COLOUR][()] = src[CAMERA_COLOUR][()]
            dst["status/state"][()] = np.bytes_(b"interrupted")
            dst["status/message"][()] = np.bytes_(encode_message(message))
    except (OSError, RuntimeError) as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if storage_errno(exc) is not None:
            raise write_error(path, "salvaging the run file", exc) from None
        raise RunFileError(f"{path}: cannot salvage the run file: {h5_cause(exc)}") from None
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    finally:
        src.close()
    fsync_path(tmp)
    os.replace(tmp, path)
    fsync_dir(path)


def _copy_calibration(src: h5py.File, dst: h5py.File) -> list[str]:
    """Copy the complete, readable calibration sets of ``src`` into ``dst`` (records, then the
    frames as their compressed chunks, then the complete flags); their names ("ambient before")."""
    try:
        complete = src["calibration/complete"][()] == 1
        counts = src["calibration/frame_count"][()].astype(np.int64)
        rows = {name: src[f"calibration/{name}"][()] for name in (*FRAME_RECORDS, "frame_count")}
    except (OSError, RuntimeError):
        return []
    max_frames = src["calibration/raw"].shape[1]
    complete &= (counts >= 1) & (counts <= max_frames)
    kept = []
    for slot in np.flatnonzero(complete):
        fault = copy_frames(src["calibration/raw"], dst["calibration/raw"], int(slot), int(counts[slot]))
        if fault is None:
            kept.append(int(slot))
        else:  # taken again
            name = " ".join(CALIBRATION_SETS[slot])
            log.warning("%s: salvage: calibration %s frame %s: dropped, to be taken again", src.filename, name, fault)
    for name, values in rows.items():
        fresh = dst[f"calibration/{name}"][()]
        fresh[kept] = values[kept]
        dst[f"calibration/{name}"][...] = fresh
    flags = np.zeros(len(CALIBRATION_SETS), np.uint8)
    flags[kept] = 1
    dst["calibration/complete"][...] = flags  # after the data, as always
    return [" ".join(CALIBRATION_SETS[slot]) for slot in kept]


def copy_frames(src_raw: h5py.Dataset, dst_raw: h5py.Dataset, slot: int, count: int) -> str | None:
    """Copy frames ``0 … count − 1`` of ``slot`` from ``src_raw`` to ``dst_raw``, each read through
    its checksum first: None when copied, else what is wrong with the first bad frame
    (``"1 fails its checksum …"``), and nothing is copied.

    Frames go as their compressed chunks (not recompressed) where both datasets store them alike;
    frames of a file without checksums are decoded and written again, with theirs.
    """
    buffer = np.empty(src_raw.shape[2:], dtype=src_raw.dtype)
    chunks = []
    for k in range(count):
        fault = frame_fault(src_raw, slot, k, buffer)
        if fault is None:
            try:
                chunks.append(src_raw.id.read_direct_chunk((slot, k, 0, 0)))
            except (OSError, RuntimeError, ValueError) as exc:
                fault = f"cannot be read ({h5_cause(exc)})"
        if fault is not None:
            return f"{k} {fault}"
    if is_checksummed(src_raw) == is_checksummed(dst_raw):
        for k, (mask, data) in enumerate(chunks):
            dst_raw.id.write_direct_chunk((slot, k, 0, 0), data, filter_mask=mask)
    else:
        for k in range(count):
            dst_raw[slot, k] = src_raw[slot, k]
    return None
