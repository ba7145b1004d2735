"""A run's header in the file: validated and encoded as JSON for a new run, read back (and
checked against the layout) from an existing one, once per file and process."""

from __future__ import annotations

import copy
import functools
import json
import os
from dataclasses import replace
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from drivers.contracts.camera_colour import CameraColourError, checked_camera_colour
from drivers.contracts.rig import Rig, rig_from_dict
from drivers.contracts.runfile.layout import (
    CALIBRATION_DATASETS,
    CALIBRATION_SETS,
    CAMERA_COLOUR,
    DATASETS,
    FRAME_RECORDS,
    RunFileError,
    RunHeader,
    as_text,
    check_format,
    h5_cause,
    is_whole,
)
from drivers.pose import Pose


@functools.lru_cache(maxsize=16)
def _rig_from_json(rig_json: str, source: str) -> Rig:
    """The rig a run file's header describes, validated once per process and text: every
    position task opens the run anew, and the rig's physical checks are about half the cost
    of an open. Rig models are frozen, so the one object can be shared."""
    return rig_from_dict(json.loads(rig_json), source=source)


#: Headers already checked, by the file's identity and state: every position task of a
#: processing opens the run file again, and checking its layout and rebuilding the header costs
#: some 30 HDF5 lookups each time. A file that changes (one being written, one replaced) is
#: checked again: its modification time, size or inode differ.
_HEADERS: dict[tuple[str, int, int, int, int], RunHeader] = {}
_HEADERS_KEPT = 8


def read_header_once(f: h5py.File, path: Path) -> RunHeader:
    """:func:`read_header`, or the header this process already read from the file unchanged.

    Parameters
    ----------
    f : h5py.File
        The run file, open.
    path : Path
        Its path (with its modification time, size and inode, the key of the cache).

    Returns
    -------
    RunHeader
        A header whose lists and dicts are this caller's own; the rig is shared.
    """
    try:
        st = os.stat(path)
        key = (str(path.resolve()), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
    except OSError:
        return read_header(f, path)
    header = _HEADERS.get(key)
    if header is None:
        header = read_header(f, path)
        if len(_HEADERS) >= _HEADERS_KEPT:
            _HEADERS.pop(next(iter(_HEADERS)))
        _HEADERS[key] = header
    # Each RunFile its own containers (the rig is shared, as _rig_from_json shares it).
    return replace(
        header,
        tool_poses=list(header.tool_poses),
        light_poses=list(header.light_poses),
        bracket=copy.deepcopy(header.bracket),
        metadata=copy.deepcopy(header.metadata),
        devices=copy.deepcopy(header.devices),
        references=copy.deepcopy(header.references),
        calibration=copy.deepcopy(header.calibration),
        camera_colour=copy.deepcopy(header.camera_colour),
    )


def read_header(f: h5py.File, path: str | os.PathLike[str]) -> RunHeader:
    """Check the layout and rebuild the :class:`RunHeader`.

    Parameters
    ----------
    f : h5py.File
        The run file, open.
    path : str or Path
        Its path, for the messages.

    Raises
    ------
    RunFileError
        Not a run file, a newer format, or a layout or header that is broken.
    """
    version = check_format(f, path)
    for name, ndim in (DATASETS | CALIBRATION_DATASETS if version >= 2 else DATASETS).items():
        try:
            dset = f[name]
        except (KeyError, OSError, RuntimeError):
            raise RunFileError(f"{path}: corrupt run file: /{name} is missing or unreadable") from None
        if not isinstance(dset, h5py.Dataset) or (ndim is not None and dset.ndim != ndim):
            raise RunFileError(f"{path}: corrupt run file: /{name} has the wrong shape")
    try:
        rig_json = as_text(f["header/rig_json"][()])
        run_json = as_text(f["header/run_json"][()])
        commanded = f["schedule/commanded_pose"][()]
        light = f["schedule/light_pose"][()]
        raw_shape = f["frames/raw"].shape
    except (OSError, RuntimeError) as exc:
        raise RunFileError(f"{path}: corrupt run file: {h5_cause(exc)}") from None
    n, max_exposures, height, width = raw_shape
    if commanded.shape != (n, 6) or light.shape != (n, 6):
        raise RunFileError(f"{path}: corrupt run file: the schedule does not match /frames/raw")
    for name in ("positions/measured_pose", "positions/times", "positions/frame_count", "positions/complete"):
        if f[name].shape[0] != n:
            raise RunFileError(f"{path}: corrupt run file: /{name} does not match the schedule")
    for name in FRAME_RECORDS:
        if f[f"frames/{name}"].shape[:2] != (n, max_exposures):
            raise RunFileError(f"{path}: corrupt run file: /frames/{name} does not match /frames/raw")
    if version >= 2:
        _check_calibration_layout(f, path, (int(height), int(width)))
    try:
        run = json.loads(run_json)
        rig_data = json.loads(rig_json)
    except json.JSONDecodeError as exc:
        raise RunFileError(f"{path}: corrupt run file: header is not valid JSON ({exc})") from None
    if not isinstance(run, dict) or not isinstance(rig_data, dict):
        raise RunFileError(f"{path}: corrupt run file: header is not a JSON object")
    try:
        rig = _rig_from_json(rig_json, f"{path}: /header/rig_json")
    except ValueError as exc:
        raise RunFileError(str(exc)) from None
    return RunHeader(
        run_id=str(run.get("run_id", "")),
        rig=rig,
        tool_poses=_poses_from(commanded),
        light_poses=_poses_from(light),
        max_exposures=int(max_exposures),
        frame_shape=(int(height), int(width)),
        bracket=run.get("bracket", {}),
        metadata=run.get("metadata", {}),
        devices=run.get("devices", {}),
        software_version=str(run.get("software_version", "")),
        created_utc=str(run.get("created_utc", "")),
        preset=str(run.get("preset", "")),
        references=run.get("references", {}) if isinstance(run.get("references", {}), dict) else {},
        calibration=run.get("calibration", {}) if isinstance(run.get("calibration", {}), dict) else {},
        camera_colour=read_camera_colour(f, path),
    )


def read_camera_colour(f: h5py.File, path: str | os.PathLike[str]) -> dict[str, Any]:
    """The camera's colour matrices the file holds (``/header/camera_colour_json``), checked;
    empty for a file without them.

    Raises
    ------
    RunFileError
        The dataset holds something that is not a colour description.
    """
    if CAMERA_COLOUR not in f:
        return {}
    try:
        text = as_text(f[CAMERA_COLOUR][()])
    except (OSError, RuntimeError) as exc:
        raise RunFileError(f"{path}: corrupt run file: {h5_cause(exc)}") from None
    if not text:
        return {}
    try:
        return checked_camera_colour(json.loads(text), f"{path}: /{CAMERA_COLOUR}")
    except json.JSONDecodeError as exc:
        raise RunFileError(f"{path}: corrupt run file: /{CAMERA_COLOUR} is not valid JSON ({exc})") from None
    except CameraColourError as exc:
        raise RunFileError(str(exc)) from None


def _check_calibration_layout(f: h5py.File, path: str | os.PathLike[str], frame_shape: tuple[int, int]) -> None:
    """Raise a :class:`RunFileError` unless ``/calibration`` has a slot per calibration set, each
    of frames the size of the positions' frames."""
    try:
        raw_shape = f["calibration/raw"].shape
        roles = [as_text(v) for v in f["calibration/role"][()]]
        whens = [as_text(v) for v in f["calibration/when"][()]]
    except (OSError, RuntimeError) as exc:
        raise RunFileError(f"{path}: corrupt run file: {h5_cause(exc)}") from None
    m, max_frames = raw_shape[0], raw_shape[1]
    if tuple(raw_shape[2:]) != frame_shape or max_frames < 1:
        raise RunFileError(f"{path}: corrupt run file: /calibration/raw does not match /frames/raw")
    if list(zip(roles, whens, strict=False)) != list(CALIBRATION_SETS) or len(roles) != m or len(whens) != m:
        raise RunFileError(f"{path}: corrupt run file: /calibration/role and /calibration/when are not the sets")
    for name in ("calibration/frame_count", "calibration/complete"):
        if f[name].shape[0] != m:
            raise RunFileError(f"{path}: corrupt run file: /{name} does not match /calibration/raw")
    for name in FRAME_RECORDS:
        if f[f"calibration/{name}"].shape[:2] != (m, max_frames):
            raise RunFileError(f"{path}: corrupt run file: /calibration/{name} does not match /calibration/raw")


def encode_header(path: str | os.PathLike[str], header: RunHeader) -> tuple[str, str]:
    """Validate a new run's header and encode it as the file stores it.

    Parameters
    ----------
    path : str or Path
        The run file to be created, for the messages.
    header : RunHeader
        The new run's header.

    Returns
    -------
    tuple of str
        The rig's JSON and the run's JSON (``/header/rig_json``, ``/header/run_json``).

    Raises
    ------
    RunFileError
        The first problem found in the header.
    """
    problems = []
    if not isinstance(header.rig, Rig):
        problems.append("rig: not a Rig")
    n = len(header.tool_poses)
    if n < 1:
        problems.append("tool_poses: the run has no positions")
    if len(header.light_poses) != n:
        problems.append(f"light_poses: {len(header.light_poses)} poses for {n} tool poses")
    if not all(isinstance(p, Pose) for p in list(header.tool_poses) + list(header.light_poses)):
        problems.append("tool_poses/light_poses: every entry must be a Pose")
    if not is_whole(header.max_exposures) or not 1 <= header.max_exposures <= np.iinfo(np.int16).max:
        problems.append(f"max_exposures: must be a whole number from 1 to 32767 (got {header.max_exposures!r})")
    shape = tuple(header.frame_shape) if isinstance(header.frame_shape, (tuple, list)) else ()
    if len(shape) != 2 or not all(is_whole(v) and v > 0 for v in shape):
        problems.append(f"frame_shape: must be (height, width) in pixels (got {header.frame_shape!r})")
    if not isinstance(header.bracket, dict) or header.bracket.get("mode") not in ("fixed", "auto"):
        problems.append("bracket: must be a dict with mode 'fixed' or 'auto'")
    for name in ("metadata", "devices", "references", "calibration"):
        if not isinstance(getattr(header, name), dict):
            problems.append(f"{name}: must be a dict")
    if not header.run_id:
        problems.append("run_id: empty")
    if problems:
        raise RunFileError(f"{path}: cannot create the run: {problems[0]}")
    run = {
        "run_id": str(header.run_id),
        "preset": str(header.preset),
        "bracket": header.bracket,
        "metadata": header.metadata,
        "devices": header.devices,
        "software_version": str(header.software_version),
        "created_utc": str(header.created_utc),
        "references": header.references,
        "calibration": header.calibration,
    }
    try:
        run_json = json.dumps(run, ensure_ascii=False, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise RunFileError(f"{path}: cannot create the run: header is not plain JSON data ({exc})") from None
    rig_json = json.dumps(header.rig.model_dump(mode="json"), ensure_ascii=False)
    return rig_json, run_json


def _poses_from(array: np.ndarray) -> list[Pose]:
    return [Pose(*(float(v) for v in row)) for row in array]
