"""The rig's geometry and template builder, made once per process for a run's rig."""

from __future__ import annotations

import functools
import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from drivers.contracts.rig import Rig
from drivers.contracts.runfile import RunFile
from processing.rig_fit import RigCorrection
from processing.trace import RigGeometry
from processing.unmixing.fresnel import FresnelPupil
from processing.unmixing.kernels import PointSpreadCorrection
from processing.unmixing.measured import MeasuredKernels, load_measured_point_spread
from processing.unmixing.templates import TemplateBuilder

log = logging.getLogger("mirrorgonio.processing")


_GEOMETRIES: dict[tuple[int, tuple[float, ...] | None, CameraFit], tuple[Rig, RigGeometry, TemplateBuilder]] = {}


def geometry_and_builder(
    run: RunFile, ball_centre: Sequence[float] | np.ndarray | None, camera: CameraFit | None = None
) -> tuple[RigGeometry, TemplateBuilder]:
    """The rig's geometry and template builder (ball at ``ball_centre``, or where the rig says;
    the camera's aperture and sensor distance as ``camera`` has them, or as the rig says; the
    rig corrected as ``camera.rig`` says; the point spread the rig's camera names, or the one
    it measured).

    Kept per process for the rig object the run file's header shares (``drivers.contracts.runfile``
    validates a rig once per text): every position task of a run asks for the same one, and
    making them cost 1 ms a task. The rig itself is held with them, so its ``id`` stays its own.
    """

    rig = run.header.rig
    camera = camera or CameraFit()
    key = (id(rig), None if ball_centre is None else tuple(float(x) for x in ball_centre), camera)
    held = _GEOMETRIES.get(key)
    if held is None or held[0] is not rig:
        geometry = RigGeometry.from_rig(rig, ball_centre=ball_centre)
        if camera.aperture_m is not None:
            geometry = replace(geometry, aperture_radius=0.5 * float(camera.aperture_m))
        if camera.sensor_distance_m is not None:
            geometry = geometry.with_sensor_distance(float(camera.sensor_distance_m))
        if camera.rig is not None:
            geometry = camera.rig.apply(geometry)
        if len(_GEOMETRIES) >= 8:
            _GEOMETRIES.pop(next(iter(_GEOMETRIES)))
        pupil = FresnelPupil.from_camera(rig.camera) if rig.camera.point_spread == "fresnel" else None
        builder = TemplateBuilder(
            geometry,
            rig.camera.sensitivity_e_per_s,
            pupil=pupil,
            measured=measured_point_spread(rig),
            correction=camera.point_spread,
        )
        held = _GEOMETRIES[key] = (rig, geometry, builder)
    return held[1], held[2]


def measured_point_spread(rig: Rig) -> MeasuredKernels | None:
    """The point spread the rig's camera measured (``[camera.measured_point_spread]``), or None.

    Raises
    ------
    PointSpreadError
        The file cannot be read or used (one line naming it).
    """
    measured = rig.camera.measured_point_spread
    if measured is None:
        return None
    path = Path(measured.file)
    try:
        stat = path.stat()
    except OSError:
        stat = None
    version = (stat.st_mtime_ns, stat.st_size) if stat is not None else None
    return _measured(str(path), version, float(rig.camera.pixel_pitch_m))


@functools.lru_cache(maxsize=4)
def _measured(path: str, version: tuple[int, int] | None, pitch: float) -> MeasuredKernels:
    return load_measured_point_spread(path, pitch)


@dataclass(frozen=True)
class CameraFit:
    """The rig's numbers fitted to the data: the camera's aperture and sensor distance
    (``--fit-aperture``, ``--fit-sensor-distance``), then the self-calibration's correction of
    the rig (``--calibrate-rig``), and the point spread refined from the sweep
    (``--refine-point-spread``); each None where the rig's description stands."""

    aperture_m: float | None = None
    sensor_distance_m: float | None = None
    rig: RigCorrection | None = None
    point_spread: PointSpreadCorrection | None = None
