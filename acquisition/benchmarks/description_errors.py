"""The errors of a rig description that ``bench tolerance`` tries: their names and what they change.

An error is named PART±SIZE (``pinhole+10%``, ``ball-x-20um``, ``camera-yaw+0.05deg``,
``principal-x+3px``, ``arm-yaw+0.2deg``): one number of the description (:data:`ERROR_PARTS`)
scaled, shifted or turned. This module reads the names and makes the error in a description.

The camera's and the arm's errors are those a lab makes: the camera turned about its own
axes (yaw about its image's vertical, pitch about its horizontal, roll about its optical axis)
or moved along its axis or across it; the principal point off the sensor's centre; the arm's
base frame turned about the rig's axes through the rig's origin (yaw about the vertical +y,
pitch about +x, roll about +z) or moved; the light tilted on its mount (about the light
frame's x axis, ``light-tilt``, or its y axis, ``light-tilt-y``) or moved on it.

A *preset* is many errors at once, as a lab makes them (:data:`PRESETS`): each part at its
size, in a direction drawn from a seed (:func:`preset_errors`).
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass

import numpy as np

from drivers.contracts.rig import PoseSpec, rig_from_dict
from drivers.pose import Pose, rotation_from_angles

#: The numbers an error can touch, by name: (what it changes, which axis or component, the units it
#: takes). What it changes: a rig field (``scale`` by %, or ``add`` a length), or one of the
#: camera's, the arm's or the light's poses (``camera-turn``, ``camera-move``, ``principal``,
#: ``arm-turn``, ``arm-move``, ``light-turn``).
ERROR_PARTS: dict[str, tuple[str, int | None, tuple[str, ...]]] = {
    "pinhole": ("camera.pinhole_diameter_m", None, ("%", "mm", "um")),
    "sensor-distance": ("camera.sensor_distance_m", None, ("%", "mm", "um")),
    "ball-x": ("ball.centre_m", 0, ("mm", "um")),
    "ball-y": ("ball.centre_m", 1, ("mm", "um")),
    "ball-z": ("ball.centre_m", 2, ("mm", "um")),
    "ball-radius": ("ball.radius_m", None, ("%", "mm", "um")),
    "light-x": ("light.light_to_tool.position_m", 0, ("mm", "um")),
    "light-y": ("light.light_to_tool.position_m", 1, ("mm", "um")),
    "light-z": ("light.light_to_tool.position_m", 2, ("mm", "um")),
    "light-tilt": ("light-turn", 0, ("deg",)),
    "light-tilt-y": ("light-turn", 1, ("deg",)),
    "camera-pitch": ("camera-turn", 0, ("deg",)),
    "camera-yaw": ("camera-turn", 1, ("deg",)),
    "camera-roll": ("camera-turn", 2, ("deg",)),
    "camera-across": ("camera-move", 0, ("mm", "um")),
    "camera-across-y": ("camera-move", 1, ("mm", "um")),
    "camera-along": ("camera-move", 2, ("mm", "um")),
    "principal-x": ("principal", 0, ("px",)),
    "principal-y": ("principal", 1, ("px",)),
    "arm-pitch": ("arm-turn", 0, ("deg",)),
    "arm-yaw": ("arm-turn", 1, ("deg",)),
    "arm-roll": ("arm-turn", 2, ("deg",)),
    "arm-x": ("arm-move", 0, ("mm", "um")),
    "arm-y": ("arm-move", 1, ("mm", "um")),
    "arm-z": ("arm-move", 2, ("mm", "um")),
}
#: The errors tried by default. Sizes a lab can plausibly get wrong: a 0.2 mm pinhole drilled or
#: measured 10 % off, the sensor distance of a camera without a datasheet, the ball placed by eye,
#: the light's mount measured with a rule.
DEFAULT_ERRORS = (
    "pinhole+10%",
    "pinhole-10%",
    "sensor-distance+1%",
    "ball-x+0.2mm",
    "ball-z+0.2mm",
    "ball-radius+0.1mm",
    "light-x+0.2mm",
    "light-z+0.5mm",
)
_ERROR_SYNTAX = re.compile(r"(?P<part>[a-z-]+?)(?P<sign>[+-])(?P<size>\d+(?:\.\d+)?)(?P<unit>%|mm|um|µm|deg|px)")
_IN_SI = {"mm": 1e-3, "um": 1e-6, "µm": 1e-6, "deg": math.pi / 180.0, "px": 1.0}


@dataclass(frozen=True)
class WrongNumber:
    """One number of the rig description made wrong: ``field`` scaled by ``amount`` (``how`` is
    "scale"), ``amount`` added to it (a 3-vector for a vector field; metres), or one of the
    poses turned or moved (``how`` one of the pose kinds of :data:`ERROR_PARTS`; ``amount`` in
    radians, metres or pixels about or along ``axis``)."""

    name: str
    field: str
    how: str
    amount: float | tuple[float, float, float]
    axis: int | None = None

    @property
    def what(self) -> str:
        """The change in words: the field, and × or + the amount."""
        if self.how == "scale":
            return f"{self.field} × {self.amount}"
        if self.how == "add":
            return f"{self.field} + {self.amount}"
        unit = {"principal": "px", "camera-move": "m", "arm-move": "m"}.get(self.how, "rad")
        return f"{self.how} {'xyz'[self.axis or 0]} {self.amount:+.6g} {unit}"


def parse_error(name: str) -> WrongNumber:
    """The error a name such as ``pinhole+10%``, ``ball-x-20um``, ``camera-yaw+0.05deg`` or
    ``principal-x+3px`` stands for: PART±SIZE with PART one of :data:`ERROR_PARTS` and SIZE in
    the units the part takes.

    Raises
    ------
    ValueError
        One line naming the error and what an error looks like.

    Examples
    --------
    >>> parse_error("pinhole+10%").amount
    1.1
    >>> parse_error("arm-yaw-0.5deg").what
    'arm-turn y -0.00872665 rad'
    """
    syntax = (
        f"PART±SIZE, PART one of {', '.join(ERROR_PARTS)}, SIZE in mm or um (lengths), deg (turns), px (the "
        "principal point) or % (of the pinhole, the sensor distance, the ball's radius), e.g. pinhole+10%, "
        "ball-x-20um, camera-yaw+0.05deg"
    )
    match = _ERROR_SYNTAX.fullmatch(name.strip())
    if match is None or match["part"] not in ERROR_PARTS:
        raise ValueError(f"--errors: {name!r} is not an error of the rig description: {syntax}")
    what, axis, units = ERROR_PARTS[match["part"]]
    unit = "um" if match["unit"] == "µm" else match["unit"]
    if unit not in units:
        kind = "a position: give its error" if units == ("mm", "um") else "given"
        raise ValueError(f"--errors: {name!r}: {match['part']} is {kind} in {' or '.join(units)}, not {unit}")
    size = float(match["size"]) * (-1.0 if match["sign"] == "-" else 1.0)
    if unit == "%":
        if size <= -100.0:
            raise ValueError(f"--errors: {name!r}: a length cannot shrink by 100 % or more")
        return WrongNumber(name, what, "scale", round(1.0 + size / 100.0, 12))
    amount = round(size * _IN_SI[unit], 15)
    if "." in what:
        if axis is None:
            return WrongNumber(name, what, "add", amount)
        vector = [0.0, 0.0, 0.0]
        vector[axis] = amount
        return WrongNumber(name, what, "add", (vector[0], vector[1], vector[2]))
    return WrongNumber(name, what, what, amount, axis)


def described_wrong(rig: dict, error: str) -> dict:
    """``rig`` (the run file's JSON description) with the error named ``error`` made in it
    (:func:`parse_error`)."""
    wrong = parse_error(error)
    out = json.loads(json.dumps(rig))
    if wrong.how in ("scale", "add"):
        *parents, key = wrong.field.split(".")
        holder = out
        for name in parents:
            holder = holder[name]
        value = holder[key]
        if wrong.how == "scale":
            holder[key] = value * wrong.amount
        elif isinstance(wrong.amount, tuple):
            holder[key] = [v + a for v, a in zip(value, wrong.amount, strict=True)]
        else:
            holder[key] = value + wrong.amount
        return out
    assert isinstance(wrong.amount, float) and wrong.axis is not None
    _POSE_ERRORS[wrong.how](out, wrong.axis, wrong.amount)
    return out


def _turn(axis: int, angle: float) -> np.ndarray:
    angles = [0.0, 0.0, 0.0]
    angles[axis] = angle
    return rotation_from_angles(*angles)


def _camera(out: dict) -> tuple[np.ndarray, np.ndarray]:
    """The described camera's OpenCV extrinsics (R, t)."""
    return rig_from_dict(out).camera.pose.extrinsics()


def _set_camera(out: dict, rotation: np.ndarray, translation: np.ndarray) -> None:
    """The camera's pose as OpenCV's ``rvec``/``tvec_m`` (Rodrigues' vector of the rotation)."""
    from scipy.spatial.transform import Rotation  # noqa: PLC0415 - heavy; the command line's help reads this module

    rvec = Rotation.from_matrix(rotation).as_rotvec()
    out["camera"]["pose"] = {"rvec": rvec.tolist(), "tvec_m": np.asarray(translation, float).tolist()}


def _camera_turn(out: dict, axis: int, angle: float) -> None:
    """The camera turned about its own ``axis`` (its pinhole held): ``x_cam' = Rδ x_cam``."""
    rotation, translation = _camera(out)
    turn = _turn(axis, angle)
    _set_camera(out, turn @ rotation, turn @ translation)


def _camera_move(out: dict, axis: int, distance: float) -> None:
    """The camera moved along its own ``axis`` (its orientation held)."""
    rotation, translation = _camera(out)
    centre = -rotation.T @ translation + distance * rotation[axis]
    _set_camera(out, rotation, -rotation @ centre)


def _principal(out: dict, axis: int, pixels: float) -> None:
    point = list(rig_from_dict(out).camera.principal_point)
    point[axis] += pixels
    out["camera"]["principal_point_px"] = point


def _arm_turn(out: dict, axis: int, angle: float) -> None:
    """The arm's base frame turned about the rig's ``axis`` through the rig's origin."""
    base = rig_from_dict(out).arm.base.to_pose()
    turned = Pose.from_rotation(np.zeros(3), _turn(axis, angle)).compose(base)
    out.setdefault("arm", {})["base"] = _pose_spec(turned)


def _arm_move(out: dict, axis: int, distance: float) -> None:
    base = rig_from_dict(out).arm.base.to_pose()
    position = base.position.copy()
    position[axis] += distance
    out.setdefault("arm", {})["base"] = _pose_spec(Pose.from_rotation(position, base.rotation))


def _light_turn(out: dict, axis: int, angle: float) -> None:
    """The light turned on its mount about the light frame's own ``axis``."""
    mount = rig_from_dict(out).light.light_to_tool.to_pose()
    out["light"]["light_to_tool"] = _pose_spec(mount.compose(Pose.from_rotation(np.zeros(3), _turn(axis, angle))))


def _pose_spec(pose: Pose) -> dict:
    return PoseSpec.of(pose).model_dump()


_POSE_ERRORS = {
    "camera-turn": _camera_turn,
    "camera-move": _camera_move,
    "principal": _principal,
    "arm-turn": _arm_turn,
    "arm-move": _arm_move,
    "light-turn": _light_turn,
}


#: Many errors at once, by name: each part with its size, in a direction a seed draws
#: (:func:`preset_errors`). ``typical-lab``: what a careful lab measures its rig to (the camera's
#: axis 0.3° and its roll 0.3°, the principal point 10 px, the camera 2 mm along its axis and
#: 1 mm across, the ball's radius 10 µm, the arm's base 0.5° and 1 mm, the light's tilt 1° and
#: its mount 0.5 mm, the pinhole 10 %, the sensor distance 1 %).
PRESETS: dict[str, tuple[tuple[tuple[str, ...], float, str], ...]] = {
    "typical-lab": (
        (("camera-yaw", "camera-pitch"), 0.3, "deg"),
        (("camera-roll",), 0.3, "deg"),
        (("principal-x", "principal-y"), 10.0, "px"),
        (("camera-along",), 2.0, "mm"),
        (("camera-across", "camera-across-y"), 1.0, "mm"),
        (("ball-radius",), 10.0, "um"),
        (("arm-pitch", "arm-yaw", "arm-roll"), 0.5, "deg"),
        (("arm-x", "arm-y", "arm-z"), 1.0, "mm"),
        (("light-tilt", "light-tilt-y"), 1.0, "deg"),
        (("light-x", "light-y"), 0.5, "mm"),
        (("pinhole",), 10.0, "%"),
        (("sensor-distance",), 1.0, "%"),
    ),
}


def preset_errors(preset: str, seed: int) -> list[str]:
    """The errors of ``preset`` (:data:`PRESETS`) for one ``seed``: each part's size along a
    direction drawn uniformly (a sign for one number, a unit vector for two or three), as names
    :func:`parse_error` reads.

    Examples
    --------
    >>> errors = preset_errors("typical-lab", 0)
    >>> len(errors), errors[-1]
    (21, 'sensor-distance-1%')
    >>> preset_errors("typical-lab", 0) == errors
    True
    """
    if preset not in PRESETS:
        raise ValueError(f"--preset: {preset!r} is not one of {', '.join(PRESETS)}")
    rng = np.random.default_rng(seed)
    names = []
    for parts, size, unit in PRESETS[preset]:
        direction = rng.standard_normal(len(parts)) if len(parts) > 1 else rng.choice([-1.0, 1.0], 1)
        direction /= np.linalg.norm(direction)
        for part, component in zip(parts, direction, strict=True):
            amount = round(size * float(component), 4)
            if amount != 0.0:
                names.append(f"{part}{'+' if amount > 0 else '-'}{abs(amount):g}{unit}")
    return names


def described_wrong_all(rig: dict, errors: list[str]) -> dict:
    """``rig`` with every error of ``errors`` made in it, in turn (:func:`described_wrong`)."""
    for error in errors:
        rig = described_wrong(rig, error)
    return rig
