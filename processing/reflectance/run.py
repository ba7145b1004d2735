"""An object run to its albedo: the mesh, the light model, the HDR results, the estimate, the files."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from drivers.config_files import MAX_BINARY_BYTES, check_input_file
from drivers.contracts.rig import Light, Rig
from drivers.contracts.runfile import CorruptFrame, RunFile, RunFileError, file_sha256
from drivers.pose import Pose
from processing.hdr.mosaic import superpixels
from processing.light_run.checksums import skipped_line, sound_positions
from processing.light_run.errors import ProcessingError
from processing.light_run.output_guard import check_paths, output_path, written_for
from processing.light_run.outputs import skipped_record
from processing.light_run.run import process_run
from processing.lightmodel import LightModel, LightModelError
from processing.options import ProcessingOptions
from processing.radiometry import gain_mismatch, radiometric_gain
from processing.reflectance.camera import superpixel_any
from processing.reflectance.codes import ReflectanceError, ReflectanceSettings
from processing.reflectance.estimate import ReflectanceResult, estimate_reflectance
from processing.reflectance.materials import estimate_materials, relighting_images
from processing.reflectance.outputs import PlacedLight, outputs_in, write_outputs
from processing.results import Results, ResultsError, results_path_for, run_name
from processing.steps import Step
from processing.trace import RigGeometry, light_pose_at_position

log = logging.getLogger("mirrorgonio.processing")

#: ``progress(stage, done, total)``, stage ``"hdr"``, ``"rays"`` or ``"lights"``.
Progress = Callable[[str, int, int], None]


def load_mesh(path: str | os.PathLike[str], units_m: float = 1.0, pose: Pose | None = None) -> trimesh.Trimesh:
    """Read a PLY, OBJ or STL mesh with trimesh and place it in the rig frame.

    ``x_rig = R·(units_m·v) + t`` for the pose's rotation ``R`` and position ``t``
    (``[object]`` of the rig, ``docs/rig.md``).

    Raises
    ------
    ReflectanceError
        One line naming the file: missing, unreadable, or without faces.
    """

    path = Path(path)
    check_input_file(path, "mesh file", ReflectanceError, limit=MAX_BINARY_BYTES)  # no FIFO, device, directory
    try:
        mesh = trimesh.load(str(path), force="mesh")
    except Exception as exc:  # noqa: BLE001 - trimesh's loaders raise anything
        raise ReflectanceError(
            f"{path}: cannot read the mesh ({type(exc).__name__}: {' '.join(str(exc).split())})"
        ) from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ReflectanceError(f"{path}: cannot read the mesh (no triangles in it)")
    mesh = mesh.copy()
    if units_m != 1.0:
        mesh.apply_scale(float(units_m))
    if pose is not None:
        mesh.apply_transform(pose.matrix())
    return mesh


def find_light_model(light: str | os.PathLike[str]) -> Path:
    """The ``.light.json`` a ``--light`` argument means.

    ``light`` may be the light-model file itself, the light run's results folder (holding
    one ``*.light.json``), its ``RUN.results.h5`` or its run file ``RUN.h5`` (the model is
    ``RUN.light.json`` beside it).
    """
    path = Path(light)
    if path.is_dir():
        found = sorted(path.glob("*.light.json"))
        if len(found) == 1:
            return found[0]
        if not found:
            raise ReflectanceError(f"{path}: no *.light.json light model in this folder (process the light run first)")
        raise ReflectanceError(
            f"{path}: {len(found)} light models in this folder ({', '.join(p.name for p in found)}): give the file"
        )
    if path.name.endswith(".json"):
        if not path.is_file():
            raise ReflectanceError(f"{path}: light model not found")
        return path
    if path.suffix == ".h5":
        stem = path.name[: -len(".results.h5")] if path.name.endswith(".results.h5") else path.stem
        candidate = path.with_name(f"{stem}.light.json")
        if candidate.is_file():
            return candidate
        raise ReflectanceError(
            f"{path}: no light model {candidate.name} beside it (process the light run with the sources step)"
        )
    raise ReflectanceError(f"{path}: not a light model, a results folder or a results file")


def _light_section(rig_like: Rig | dict[str, Any] | None) -> dict[str, Any] | None:
    """The ``[light]`` of a rig (a Rig or its dict) as comparable numbers, or None."""

    if rig_like is None:
        return None
    section = rig_like.get("light", {}) if isinstance(rig_like, dict) else rig_like.light
    try:
        light = section if isinstance(section, Light) else Light.model_validate(section)
    except ValueError:
        return None
    return {
        "light_to_tool.position_m": tuple(light.light_to_tool.position_m),
        "light_to_tool.rotation_deg": tuple(light.light_to_tool.rotation_deg),
        "housing_radius_m": light.housing_radius_m,
        "housing_depth_m": light.housing_depth_m,
    }


def _light_run_rig(light_model: LightModel) -> Rig | dict[str, Any] | None:
    """The light run's rig: ``provenance["rig"]`` when it is the rig itself, else the rig
    stored in the run file the provenance names (None when neither is at hand)."""
    for key in ("rig_description", "rig"):
        rig = light_model.provenance.get(key)
        if isinstance(rig, dict):
            return rig
    run_file = light_model.provenance.get("run_file")
    if run_file and Path(run_file).is_file():
        try:
            with RunFile.open(run_file) as run:
                return run.header.rig
        except RunFileError:
            return None
    return None


def check_light_frame(
    light_model: LightModel, light_path: str | os.PathLike[str], rig: Rig, run_path: str | os.PathLike[str]
) -> str | None:
    """Refuse a light model measured on a rig whose ``[light]`` differs from the object run's.

    The light frame is the arm's tool frame composed with ``light_to_tool``; a model made
    with another mounting (or another housing) does not describe this run's light.

    Returns
    -------
    str or None
        A warning when the light run's rig is not known (the check could not be made).
    """
    theirs = _light_run_rig(light_model)
    if theirs is None:
        return (
            f"{light_path}: the light model does not record its rig's [light] section and its run file is not at "
            "hand: the light frame could not be checked"
        )
    a, b = _light_section(theirs), _light_section(rig)
    if a is None or b is None:
        return f"{light_path}: the light run's [light] section is unreadable: the light frame could not be checked"
    differs = [k for k in a if not np.allclose(np.atleast_1d(a[k]), np.atleast_1d(b[k]), rtol=0.0, atol=1e-9)]
    if differs:
        name_a = theirs.get("name", "?") if isinstance(theirs, dict) else theirs.name
        key = differs[0]
        raise ReflectanceError(
            f"{light_path}: light results from a different rig: the light run's rig {name_a!r} has [light] "
            f"{key} = {list(np.atleast_1d(a[key]))}, the object run {run_path}'s rig {rig.name!r} has "
            f"{list(np.atleast_1d(b[key]))}: the light frame would not be the same"
        )
    return None


def _results_for(run_path: Path, run_id: str, out: Path, progress: Progress | None, checks: _Checks) -> Path:
    """The run's HDR results: beside the run, in ``out`` (either written for this run), or made
    now (in ``out``, positions with a corrupt frame skipped as ``checks`` say)."""

    for folder in (run_path.parent, out):
        candidate = results_path_for(run_path, folder)
        if candidate.is_file() and written_for(candidate) == run_id:
            return candidate
    log.info("%s: no HDR results yet: merging the brackets into %s", run_path, out)
    try:
        report = process_run(
            run_path,
            out,
            ProcessingOptions(steps=(Step.HDR,), ignore_corrupt=checks.ignore_corrupt, overwrite=checks.overwrite),
            progress=(lambda d, t: progress("hdr", d, t)) if progress else None,
        )
    except ProcessingError as exc:
        raise ReflectanceError(str(exc)) from None
    return report.results_file


@dataclass(frozen=True)
class _Checks:
    """What the reflectance is told to skip and to replace: positions with a corrupt frame
    (``--ignore-corrupt``), outputs of another run or of unknown origin (``--overwrite``)."""

    ignore_corrupt: bool = False
    overwrite: bool = False


def _check_outputs(run_path: Path, run_id: str, out: Path, checks: _Checks) -> None:
    """No other run's reflectance, nor its HDR results, in ``out``: refused before any work
    unless ``--overwrite`` (:func:`processing.light_run.output_guard.check_paths`)."""
    paths = [*outputs_in(out), output_path(run_path, out, ".results.h5"), output_path(run_path, out, ".hdr")]
    try:
        check_paths(paths, run_path, run_id, checks.overwrite)
    except ProcessingError as exc:
        raise ReflectanceError(str(exc)) from None


def _sound(run: RunFile, run_path: Path, checks: _Checks) -> tuple[np.ndarray, list[CorruptFrame]]:
    """Every frame the reflectance may read (the complete positions', the ambient calibration
    sets' the merge takes) read through its checksum before any work: the positions to use and
    the frames skipped (``--ignore-corrupt``; without it a corrupt frame is one line)."""
    try:
        positions = run.completed_positions()
        ambient = [pair for pair in run.calibration_sets() if pair[0] == "ambient"]
        return sound_positions(run, run_path, positions, ambient, checks.ignore_corrupt)
    except RunFileError as exc:
        raise ReflectanceError(str(exc)) from None
    except ProcessingError as exc:
        raise ReflectanceError(str(exc)) from None


def reflectance_from_run(
    object_run: str | os.PathLike[str],
    light: str | os.PathLike[str] | None = None,
    mesh: str | os.PathLike[str] | None = None,
    out_dir: str | os.PathLike[str] | None = None,
    *,
    progress: Progress | None = None,
    settings: ReflectanceSettings | None = None,
    texture_size: int = 1024,
    bins: int = 24,
    ignore_corrupt: bool = False,
    overwrite: bool = False,
) -> ReflectanceResult:
    """Estimate an object's albedo from its run file and write every output.

    Parameters
    ----------
    object_run : path-like
        The object run (``object-arc`` on a rig with ``[object]``).
    light : path-like, optional
        The light model: a ``.light.json``, or the light run's results folder or file
        (:func:`find_light_model`). Default: the model the run recorded
        (``references.light_model``).
    mesh : path-like, optional
        The object's mesh (default: the rig's ``[object].mesh``). Its ``units_m`` and
        ``pose`` come from the rig's ``[object]`` (metres and the rig frame without one).
    out_dir : path-like, optional
        Folder for the outputs (default ``RUN.reflectance`` beside the run). The run's
        HDR results are looked for beside the run and here, and made here when missing.
    progress : callable, optional
        ``progress(stage, done, total)``, stage ``"hdr"``, ``"rays"`` or ``"lights"``.
    settings : ReflectanceSettings, optional
    texture_size, bins : int
        UV texture size (texels) and the number of height bins of the profiles.
    ignore_corrupt : bool
        Leave out the light positions with a frame that fails its checksum (said in the
        warnings and the summary's ``skipped_corrupt``); without it such a frame is a one-line
        error before any work.
    overwrite : bool
        Write over outputs in ``out_dir`` that another run's reflectance wrote, or whose run
        is unknown; without it they are a one-line error before any work.

    Raises
    ------
    ReflectanceError
        One line: an unreadable run, mesh or light model, an object run without
        ``[object]`` and no mesh, light results from a different rig, a frame that fails its
        checksum, outputs of another run in ``out_dir``, a mesh out of the camera's view, no
        valid point.
    """

    run_path = Path(object_run)
    out = Path(out_dir) if out_dir is not None else run_path.with_name(f"{run_name(run_path)}.reflectance")
    warnings: list[str] = []
    clock = {"start": time.perf_counter()}
    inputs = _gathered(run_path, light, mesh, out, progress, warnings, _Checks(ignore_corrupt, overwrite))
    clock["inputs"] = time.perf_counter()  # the run read, its HDR merged (or found), the light model
    rig, measured, obj = inputs.rig, inputs.measured, inputs.rig.object
    for text in warnings:
        log.warning("%s", text)
    result = estimate_reflectance(
        np.stack(measured.rates),
        np.stack(measured.saturated),
        rig.camera,
        inputs.mesh,
        measured.poses,
        inputs.light_model,
        object_pose=inputs.object_pose,
        up=obj.up if obj is not None else (0.0, 1.0, 0.0),
        housing=(rig.light.housing_radius_m, rig.light.housing_depth_m),
        settings=settings,
        mesh_name=str(inputs.mesh_path),
        progress=progress,
    )
    clock["albedo"] = time.perf_counter()  # rays, samples, shadows, the albedo under three models
    result.warnings[:0] = warnings
    if inputs.skipped:  # logged by the checksum pass itself
        result.warnings.append(f"{run_path}: {skipped_line(inputs.skipped)}")
    result.metadata = {
        "object_run": str(run_path),
        "run_id": inputs.run_id,
        "rig": rig.name,
        "results_file": str(inputs.results_file),
        "positions": [int(i) for i in measured.positions],
        **_light_and_mesh(inputs.light_path, inputs.light_model, inputs.mesh_path),
        "camera_sensitivity_e_per_s": rig.camera.sensitivity_e_per_s,
        "gain_e_per_dn": measured.gain,
        "gain_source": "rig",
        **({"skipped_corrupt": skipped_record(inputs.skipped)} if inputs.skipped else {}),
    }
    relit = _whole_reflectance(result, inputs, run_path)
    clock["brdf"] = time.perf_counter()  # the BRDF per point under three models, the relighting
    mesh_own_frame = load_mesh(inputs.mesh_path, obj.units_m if obj is not None else 1.0)
    write_outputs(
        result,
        out,
        texture_size=texture_size,
        bins=bins,
        metadata=result.metadata,
        mesh_object_frame=mesh_own_frame,
        relit=relit,
        placed_light=PlacedLight.from_run(inputs.light_model, measured.poses, measured.positions, inputs.object_pose)
        if result.materials is not None
        else None,
    )
    clock["outputs"] = time.perf_counter()  # maps, EXR, PNG, glTF, HDF5, report
    steps = list(clock)
    result.metadata["times_s"] = {
        step: round(clock[step] - clock[before], 2) for before, step in zip(steps, steps[1:], strict=False)
    }
    return result


def _whole_reflectance(result: ReflectanceResult, inputs: _ObjectInputs, run_path: Path) -> dict[str, np.ndarray]:
    """The BRDF per point into ``result.materials`` (or why not, in its metadata), and the
    relighting images of the measured light model for the report."""
    settings = result.settings
    rotation, translation = inputs.rig.camera.pose.extrinsics()
    camera_centre = -np.asarray(rotation).T @ np.asarray(translation, float)
    result.materials = estimate_materials(result, camera_centre, hold_out=settings.hold_out, max_basis=settings.basis)
    if result.materials is None:  # an albedo-only schedule (object-arc): said in the summary, not a warning
        result.metadata["brdf_skipped"] = (
            f"{len(result.lights)} light positions: too few to fit a specular lobe per point "
            "(the object-dome schedule samples the highlights)"
        )
        log.info("%s: %s", run_path, result.metadata["brdf_skipped"])
        return {}
    if "measured" not in result.materials.fits:
        return {}
    return relighting_images(result, "measured", inputs.light_model, inputs.mesh, camera_centre)


@dataclass
class _ObjectInputs:
    """What the estimate takes from an object run: its rig and id, the mesh in the rig frame
    (with its file and the object's pose), the light model (with its file), the HDR results
    file, the measured rates and the frames skipped as corrupt."""

    rig: Rig
    run_id: str
    mesh_path: Path
    object_pose: Pose | None
    mesh: trimesh.Trimesh
    light_path: Path
    light_model: LightModel
    results_file: Path
    measured: _MeasuredRates
    skipped: list[CorruptFrame]


def _gathered(
    run_path: Path,
    light: str | os.PathLike[str] | None,
    mesh: str | os.PathLike[str] | None,
    out: Path,
    progress: Progress | None,
    warnings: list[str],
    checks: _Checks,
) -> _ObjectInputs:
    """Everything the estimate needs from the object run, its mesh, its light model and its
    HDR results (merged now where missing), with what is worth a warning added to ``warnings``.
    The outputs in ``out`` and the run's frames are checked before any of it is written."""
    try:
        run = RunFile.open(run_path)
    except RunFileError as exc:
        raise ReflectanceError(str(exc)) from None
    with run:
        rig, references, run_id = run.header.rig, run.header.references or {}, run.header.run_id
        _check_outputs(run_path, run_id, out, checks)
        mesh_path, object_pose, mesh_rig = _object_mesh(run_path, rig, references, mesh, warnings)
        light_path, light_model = _light_model(run_path, rig, references, light, warnings)
        sound, skipped = _sound(run, run_path, checks)
        out.mkdir(parents=True, exist_ok=True)
        results_file = _results_for(run_path, run_id, out, progress, checks)
        measured = _measured_rates(run, run_path, results_file, sound, warnings)
        return _ObjectInputs(
            rig, run_id, mesh_path, object_pose, mesh_rig, light_path, light_model, results_file, measured, skipped
        )


def _light_and_mesh(light_path: Path, light_model: LightModel, mesh_path: Path) -> dict[str, Any]:
    """What the reflectance was measured with, for its summary."""
    return {
        "light_model": str(light_path),
        "light_run_id": light_model.provenance.get("run_id", ""),
        "light_units": light_model.units,
        "mesh": str(mesh_path),
    }


def _object_mesh(
    run_path: Path, rig: Rig, references: dict[str, Any], mesh: str | os.PathLike[str] | None, warnings: list[str]
) -> tuple[Path, Pose | None, trimesh.Trimesh]:
    """(mesh file, object pose, the mesh in the rig frame): the one given, or the rig's ``[object]``."""
    obj = rig.object
    if mesh is None:
        if obj is None:
            raise ReflectanceError(
                f"{run_path}: the run's rig {rig.name!r} has no [object] and no mesh was given (--mesh)"
            )
        mesh_path = obj.mesh_path()
    else:
        mesh_path = Path(mesh)
    object_pose = obj.pose.to_pose() if obj is not None else None
    mesh_rig = load_mesh(mesh_path, obj.units_m if obj is not None else 1.0, object_pose)
    recorded = references.get("object_mesh") or {}
    if recorded.get("sha256") and recorded["sha256"] != file_sha256(mesh_path):
        warnings.append(f"{mesh_path}: not the mesh the run recorded ({recorded.get('path')}): its contents differ")
    return mesh_path, object_pose, mesh_rig


def _light_model(
    run_path: Path, rig: Rig, references: dict[str, Any], light: str | os.PathLike[str] | None, warnings: list[str]
) -> tuple[Path, LightModel]:
    """The light model given, or the one the run recorded, checked against the run's light frame."""
    recorded = references.get("light_model") or {}
    if light is None:
        if not recorded.get("path"):
            raise ReflectanceError(f"{run_path}: the run records no light model: give one with --light")
        light_path = find_light_model(recorded["path"])
    else:
        light_path = find_light_model(light)
        if recorded.get("sha256") and recorded["sha256"] != file_sha256(light_path):
            warnings.append(f"{light_path}: not the light model the run recorded ({recorded.get('path')})")
    try:
        light_model = LightModel.load(light_path)
    except LightModelError as exc:
        raise ReflectanceError(str(exc)) from None
    note = check_light_frame(light_model, light_path, rig, run_path)
    if note:
        warnings.append(note)
    return light_path, light_model


@dataclass
class _MeasuredRates:
    """An object run's merged positions as the estimate takes them: superpixel rates in e⁻/s,
    the superpixels saturated everywhere, and the light's pose at each."""

    positions: np.ndarray
    rates: list[np.ndarray]
    saturated: list[np.ndarray]
    poses: list[Pose]
    gain: float


def _measured_rates(
    run: RunFile, run_path: Path, results_file: Path, sound: np.ndarray, warnings: list[str]
) -> _MeasuredRates:
    """The merged positions with frames (of ``sound``: none with a corrupt frame), converted
    with the rig's calibrated gain, as the light step converts them: k (e⁻/s per unit radiance)
    is calibrated with it; the HDR's own estimate only weights the merge (a gain far from the
    rig's is said)."""
    geometry = RigGeometry.from_rig(run.header.rig)
    try:
        with Results.open(results_file) as results:
            merged = np.flatnonzero(results.hdr_done & run.complete)
            positions = merged[np.isin(merged, sound)]
            if positions.size < 2:
                raise ReflectanceError(
                    f"{run_path}: {positions.size} position(s) with frames and an HDR result: "
                    "the albedo needs at least 2 light positions"
                )
            gain = radiometric_gain(run)
            mismatch = gain_mismatch(results.noise, gain)
            measured = _MeasuredRates(positions, [], [], [], gain)
            for index in map(int, positions):
                mosaic = results.radiance(index).astype(np.float64) * gain  # DN/s -> e-/s
                measured.rates.append(superpixels(mosaic, results.cfa_pattern))
                measured.saturated.append(superpixel_any(results.saturated(index)))
                measured.poses.append(light_pose_at_position(run, geometry, index))
    except ResultsError as exc:
        raise ReflectanceError(str(exc)) from None
    if mismatch is not None and mismatch[0] >= logging.WARNING:
        warnings.append(f"{results_file}: {mismatch[1]}")
    elif mismatch is not None:
        log.info("%s: %s", results_file, mismatch[1])
    return measured
