"""Edits a program makes to a lab's own rig file: the rest of the file (its comments, its order)
kept as the lab wrote it (tomlkit), the result checked as a rig before it replaces the file."""

from __future__ import annotations

import os
from pathlib import Path

from drivers.contracts.photometric import PhotometricCalibration
from drivers.contracts.rig import RigError, load_rig


def store_photometric_calibration(path: str | Path, calibration: PhotometricCalibration) -> Path:
    """Write ``calibration`` into the rig file at ``path`` as its ``[camera.photometric]`` table,
    the rest of the file (its comments, its order) kept as it was; the file is replaced only
    once the result reads back as a valid rig (:class:`RigError` naming the file otherwise)."""
    import tomlkit  # noqa: PLC0415 - only the calibration command edits rig files

    path = Path(path)
    load_rig(path)  # a file that is not a rig is refused before it is touched
    document = tomlkit.parse(path.read_text(encoding="utf-8"))
    camera = document.get("camera")
    if camera is None:
        camera = tomlkit.table()
        document["camera"] = camera
    table = tomlkit.table()
    for key, value in calibration.model_dump(mode="json", exclude_none=True).items():
        table[key] = value
    camera["photometric"] = table
    staged = path.with_name(f".{path.name}.tmp")
    staged.write_text(tomlkit.dumps(document), encoding="utf-8")
    try:
        load_rig(staged)
    except RigError:
        staged.unlink(missing_ok=True)
        raise
    os.replace(staged, path)
    return path
