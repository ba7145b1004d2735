"""The rig's numbers the data can correct, and a correction of them applied to the rig's geometry.

A lab's rig description is never exact. What the sweep's images measure, and what they cannot
tell apart, follows from the geometry: the ball is a sphere, so

- turning the camera about the line from it to the ball, or moving it around the ball, is
  turning the rest of the rig about the ball's centre: the arm's base frame turned
  (``arm_yaw``, ``arm_pitch``, ``arm_roll``) stands for the camera's roll and its place across
  the line of sight;
- shifting the principal point shifts the image as turning the camera does (by ``f·δ``, to a
  per cent across the ball's image): the camera's yaw and pitch stand for both;
- moving the arm's base frame within the light's plane moves every source alike, which the
  sources' places on the plane take up; only the move along the light's axis (``arm_along``)
  is the rig's;
- the light turned on its mount turns the frame the light model is made in, not the light the
  rig sees (the model is right in the frame described, and the light files say which frame).

So the fitted numbers are the camera's yaw and pitch, its distance from the ball, the sensor
distance, the pinhole's diameter, and the arm's base frame turned about the ball's centre and
moved along the light's axis; the others are held, each with its reason (:data:`HELD`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from drivers.contracts.rig import PoseSpec, Rig, Tolerances
from drivers.pose import Pose, rotation_from_angles
from processing.trace import RigGeometry
from processing.unmixing.fresnel import FresnelPupil


@dataclass(frozen=True)
class RigNumber:
    """One of the rig's numbers the processing fits: its name, its unit in the fit and on paper,
    and how far the description may be off (from the rig's ``[tolerances]``)."""

    name: str
    unit: str
    what: str


#: The numbers fitted, in the order of a correction's vector, with the unit the fit works in.
FITTED: tuple[RigNumber, ...] = (
    RigNumber("camera_yaw", "deg", "the camera turned about its image's vertical (and the principal point across)"),
    RigNumber("camera_pitch", "deg", "the camera turned about its image's horizontal (and the principal point up)"),
    RigNumber("camera_distance", "mm", "the camera moved away from the ball along the line between them"),
    RigNumber("sensor_distance", "%", "the pinhole-to-sensor distance"),
    RigNumber("pinhole", "%", "the pinhole's diameter"),
    RigNumber("arm_yaw", "deg", "the arm's base frame turned about the rig's vertical through the ball"),
    RigNumber("arm_pitch", "deg", "the arm's base frame turned about the rig's x axis through the ball"),
    RigNumber("arm_roll", "deg", "the arm's base frame turned about the rig's z axis through the ball"),
    RigNumber("arm_along", "mm", "the arm's base frame moved along the light's axis"),
    RigNumber("pinhole_shape_plus", "%", "the pinhole's ellipticity along the camera's x and y (Fresnel templates)"),
    RigNumber("pinhole_shape_cross", "%", "the pinhole's ellipticity along the diagonals (Fresnel templates)"),
)

#: The numbers only the Fresnel templates see (the geometric-Airy ones draw a round aperture):
#: held elsewhere.
APERTURE_SHAPE = ("pinhole_shape_plus", "pinhole_shape_cross")

#: The numbers held as described, and why: the data cannot tell them from fitted ones.
HELD: dict[str, str] = {
    "camera_roll": "a turn about the line of sight to the ball turns the rest of the rig about the ball: arm_yaw, "
    "arm_pitch and arm_roll take it up",
    "camera_across": "the camera moved around the ball turns the rest of the rig about the ball: the arm's turns "
    "take it up",
    "principal_point": "a shift of the principal point shifts the image as the camera's yaw and pitch do (1 px is "
    "1/f rad): they take it up",
    "arm_across": "the arm's base frame moved within the light's plane moves every source alike: the sources' places "
    "take it up",
    "light_mount": "the light turned or moved on its mount changes the frame the light model is made in, not the light "
    "the rig sees: the model is made in the frame described",
    "ball_radius": "the ball's radius sets the rig's scale with the camera's and the light's distances; it is measured "
    "to micrometres",
}


def bounds(tolerances: Tolerances, camera: RigGeometry, shape: bool = False) -> np.ndarray:
    """How far each fitted number may move (in its fit unit), from the rig's tolerances: the
    camera's yaw and pitch take the principal point's tolerance too; the aperture's shape only
    with ``shape`` (Fresnel templates), else 0 (held)."""
    f_px = camera.K[0, 0]
    turn = tolerances.camera_rotation_deg + math.degrees(tolerances.principal_point_px / f_px)
    return np.array(
        [
            turn,
            turn,
            1e3 * tolerances.camera_position_m,
            100.0 * tolerances.sensor_distance_fraction,
            100.0 * tolerances.pinhole_fraction,
            tolerances.arm_base_rotation_deg,
            tolerances.arm_base_rotation_deg,
            tolerances.arm_base_rotation_deg,
            1e3 * (tolerances.arm_base_position_m + tolerances.light_position_m),
            100.0 * tolerances.pinhole_ellipticity if shape else 0.0,
            100.0 * tolerances.pinhole_ellipticity if shape else 0.0,
        ]
    )


@dataclass(frozen=True)
class RigCorrection:
    """Changes to the described rig, in the fit's units (:data:`FITTED`), all zero: as described.

    A correction is hashable (the per-process geometry cache keys on it) and applies to a
    :class:`~processing.trace.RigGeometry` (:meth:`apply`): the camera turned and moved, the
    sensor distance and the pinhole scaled, the arm's base frame turned about the ball's centre
    and moved along ``light_axis`` (the light's axis at the sweep's middle, rig frame).
    """

    values: tuple[float, ...] = (0.0,) * len(FITTED)
    light_axis: tuple[float, float, float] = (0.0, 0.0, 1.0)

    @classmethod
    def of(cls, vector: np.ndarray, light_axis: np.ndarray) -> RigCorrection:
        x, y, z = (float(a) for a in light_axis)
        return cls(tuple(float(v) for v in vector), (x, y, z))

    def value(self, name: str) -> float:
        return self.values[[n.name for n in FITTED].index(name)]

    @property
    def vector(self) -> np.ndarray:
        return np.array(self.values)

    def is_null(self) -> bool:
        return not any(self.values)

    def apply(self, geometry: RigGeometry) -> RigGeometry:
        """``geometry`` corrected: the camera, the sensor, the pinhole and the arm's base frame."""
        if self.is_null():
            return geometry
        yaw, pitch, distance, sensor, pinhole, arm_yaw, arm_pitch, arm_roll, along, plus, cross = self.values
        g = geometry.with_sensor_distance(geometry.sensor_distance * (1.0 + sensor / 100.0))
        turn = rotation_from_angles(math.radians(pitch), math.radians(yaw), 0.0)  # about the camera's own axes
        away = g.camera_centre - g.ball_centre
        centre = g.camera_centre + 1e-3 * distance * away / np.linalg.norm(away)
        rotation = turn @ g.R
        g = replace(
            g,
            R=rotation,
            t=-rotation @ centre,
            camera_centre=centre,
            aperture_radius=geometry.aperture_radius * (1.0 + pinhole / 100.0),
            aperture_shape=_reshaped(geometry.aperture_shape, plus, cross),
        )
        arm = _about(
            g.ball_centre,
            rotation_from_angles(math.radians(arm_pitch), math.radians(arm_yaw), math.radians(arm_roll)),
            1e-3 * along * np.asarray(self.light_axis),
        )
        base = arm if g.arm_base is None else arm.compose(g.arm_base)
        return replace(g, arm_base=base)


def _reshaped(shape: tuple[float, float, float], plus: float, cross: float) -> tuple[float, float, float]:
    """The aperture's shape matrix with an ellipticity of ``plus`` % along x and y and ``cross`` %
    along the diagonals added (axes 1 ± e/2 for an ellipticity e)."""
    xx, xy, yy = shape
    return (xx + plus / 200.0, xy + cross / 200.0, yy - plus / 200.0)


def _about(centre: np.ndarray, rotation: np.ndarray, shift: np.ndarray) -> Pose:
    """The rigid motion that turns by ``rotation`` about ``centre``, then moves by ``shift``."""
    return Pose.from_rotation(centre + shift - rotation @ centre, rotation)


def fitted_rig(rig: Rig, correction: RigCorrection, ball_centre: np.ndarray | None = None) -> Rig:
    """``rig``'s description with ``correction`` made in it: the camera's pose (as OpenCV's
    ``rvec``/``tvec_m``), its sensor distance and aperture, and the arm's base frame; the ball at
    ``ball_centre`` where given. A rig file written from it describes the rig as fitted."""
    geometry = RigGeometry.from_rig(rig, ball_centre=ball_centre)
    fitted = correction.apply(geometry)
    camera = rig.camera.model_dump()
    camera["pose"] = {
        "position_m": None,
        "rvec": Rotation.from_matrix(fitted.R).as_rotvec().tolist(),
        "tvec_m": fitted.t.tolist(),
    }
    camera["sensor_distance_m"] = fitted.sensor_distance
    diameter = 2.0 * fitted.aperture_radius
    if rig.camera.thin_lens is None:
        camera["pinhole_diameter_m"] = diameter
        if fitted.aperture_shape != geometry.aperture_shape and rig.camera.aperture.shape != "mask":
            camera["aperture"] = _ellipse(fitted.aperture_shape, diameter)
    else:  # the lens's aperture is its focal length over its f-number
        camera["thin_lens"]["f_number"] = 1.0 / (fitted.inverse_focal * diameter)
    arm = rig.arm.model_dump()
    arm["base"] = PoseSpec().model_dump() if fitted.arm_base is None else PoseSpec.of(fitted.arm_base).model_dump()
    ball = rig.ball.model_dump()
    ball["centre_m"] = fitted.ball_centre.tolist()
    return Rig.model_validate({**rig.model_dump(), "camera": camera, "arm": arm, "ball": ball})


def _ellipse(shape: tuple[float, float, float], diameter: float) -> dict:
    """``[camera.aperture]`` for the shape matrix ``shape`` over a circle of ``diameter``."""
    ellipse = FresnelPupil.shape(diameter / 2.0, shape)
    return {"shape": "ellipse", "axes_m": list(ellipse.axes_m), "angle_deg": math.degrees(ellipse.angle_rad) % 180.0}
