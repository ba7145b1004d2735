"""No processing overwrites another run's outputs: the files a run's processing writes, and whose
run the ones already there belong to (the light run's here; the reflectance's in
:mod:`processing.reflectance.outputs`)."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import h5py

from processing.light_run.errors import ProcessingError
from processing.results import run_name

#: What a light run's processing writes into its output folder, after the run's name.
OUTPUT_SUFFIXES = (
    ".results.h5",
    ".hdr",
    ".light.json",
    ".ies",
    ".ldt",
    ".tm25ray",
    ".pbrt",
    ".report.html",
    ".rig-fitted.toml",
)


def output_path(run_path: str | Path, out: str | Path, suffix: str) -> Path:
    """The output ``suffix`` (one of :data:`OUTPUT_SUFFIXES`) of ``run_path`` in ``out``: named after
    the run's whole name (``yaw-0.05.h5`` gives ``yaw-0.05.ies``)."""
    if suffix not in OUTPUT_SUFFIXES:
        raise ValueError(f"{suffix!r} is not an output of a light run")
    return Path(out) / f"{run_name(run_path)}{suffix}"


def outputs_of(run_path: str | Path, out: str | Path) -> list[Path]:
    """The files (and the ``.hdr`` folder) a processing of ``run_path`` writes into ``out``."""
    return [output_path(run_path, out, suffix) for suffix in OUTPUT_SUFFIXES]


#: Outputs that say which run they were written for (:func:`written_for` reads them): a light
#: run's results file and light model, a reflectance's per-point file and summary.
OWNED_OUTPUTS = (".results.h5", ".light.json", "reflectance.h5", "reflectance.json")


def written_for(path: Path) -> str | None:
    """The run id an existing output says it was written for (the ``run_id`` attribute of a
    results file or ``reflectance.h5``, the light model's provenance, the reflectance summary's
    ``run_id``); None where the file does not say or cannot be read."""
    try:
        if path.name.endswith((".results.h5", "reflectance.h5")):
            with h5py.File(path, "r") as f:
                value = f.attrs.get("run_id")
            return value.decode() if isinstance(value, bytes) else None if value is None else str(value)
        if path.name.endswith(".json"):
            with path.open(encoding="utf-8") as stream:
                document = json.load(stream)
            if path.name.endswith(".light.json"):
                document = document.get("provenance", {})
            value = document.get("run_id")
            return None if value is None else str(value)
    except (OSError, ValueError, AttributeError):
        return None
    return None


def check_outputs(run_path: str | Path, run_id: str, out: str | Path, overwrite: bool = False) -> None:
    """Refuse to write over the outputs of another run: before any work.

    The results file and the light model say which run they were written for; where either is
    there, it must be ``run_id``'s. Where neither is, but other outputs of the same name are
    (a light file, the report, the ``.hdr`` folder), nothing says whose they are: refused too.

    Raises
    ------
    ProcessingError
        One line naming the file in the way and the run it belongs to, unless ``overwrite``.
    """
    check_paths(outputs_of(run_path, out), run_path, run_id, overwrite)


def check_paths(paths: Sequence[Path], run_path: str | Path, run_id: str, overwrite: bool = False) -> None:
    """Refuse to write ``paths`` (the outputs of one processing of ``run_path``) where those
    already there are another run's, or nothing says whose they are: before any work.

    Of the files in :data:`OWNED_OUTPUTS` that are there, each must say it was written for
    ``run_id``; where none of them is there but other paths are, those are refused too.

    Raises
    ------
    ProcessingError
        One line naming the file in the way and the run it belongs to, unless ``overwrite``.
    """
    if overwrite:
        return
    present = [path for path in paths if path.exists()]
    if not present:
        return
    advice = "pass --overwrite to replace it, or choose another --out"
    owned = [path for path in present if path.name.endswith(OWNED_OUTPUTS)]
    for path in owned:
        owner = written_for(path)
        if owner is None:
            raise ProcessingError(
                f"{path}: already there and not known to be written for run {run_id} ({run_path}): {advice}"
            )
        if owner != run_id:
            raise ProcessingError(
                f"{path}: holds the outputs of another run ({owner}), not of run {run_id} ({run_path}): {advice}"
            )
    if not owned:
        raise ProcessingError(
            f"{present[0]}: already there and not known to be written for run {run_id} ({run_path}): {advice}"
        )
