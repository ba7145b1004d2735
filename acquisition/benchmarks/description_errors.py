"""The errors of a rig description that ``bench tolerance`` tries: their names and what they change.

An error is named PART±SIZE (``pinhole+10%``, ``ball-x-20um``, ``light-z+0.5mm``): one number
of the description (:data:`ERROR_PARTS`) scaled or shifted. This module reads the names and
makes the error in a description; it imports nothing heavy, since the command line's help
lists the parts and the default errors.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass

#: The numbers of the description an error can touch, by name: (the rig field, the component
#: of a 3-vector or None, whether a relative error in % makes sense for it).
ERROR_PARTS: dict[str, tuple[str, int | None, bool]] = {
    "pinhole": ("camera.pinhole_diameter_m", None, True),
    "sensor-distance": ("camera.sensor_distance_m", None, True),
    "ball-x": ("ball.centre_m", 0, False),
    "ball-y": ("ball.centre_m", 1, False),
    "ball-z": ("ball.centre_m", 2, False),
    "ball-radius": ("ball.radius_m", None, True),
    "light-x": ("light.light_to_tool.position_m", 0, False),
    "light-y": ("light.light_to_tool.position_m", 1, False),
    "light-z": ("light.light_to_tool.position_m", 2, False),
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
_ERROR_SYNTAX = re.compile(r"(?P<part>[a-z-]+?)(?P<sign>[+-])(?P<size>\d+(?:\.\d+)?)(?P<unit>%|mm|um|µm)")
_METRES = {"mm": 1e-3, "um": 1e-6, "µm": 1e-6}


@dataclass(frozen=True)
class WrongNumber:
    """One number of the rig description made wrong: ``field`` scaled by ``amount`` (``how`` is
    "scale") or ``amount`` added to it (a 3-vector for a vector field), in metres."""

    name: str
    field: str
    how: str
    amount: float | tuple[float, float, float]

    @property
    def what(self) -> str:
        """The change in words: the field, and × or + the amount."""
        return f"{self.field} {'×' if self.how == 'scale' else '+'} {self.amount}"


def parse_error(name: str) -> WrongNumber:
    """The error a name such as ``pinhole+10%``, ``ball-x-20um`` or ``light-z+0.5mm`` stands for:
    PART±SIZE with PART one of :data:`ERROR_PARTS` and SIZE in % (of the pinhole, the sensor
    distance, the ball's radius) or in mm or µm.

    Raises
    ------
    ValueError
        One line naming the error and what an error looks like.
    """
    syntax = (
        f"PART±SIZE, PART one of {', '.join(ERROR_PARTS)}, SIZE in mm or um (or % of pinhole, "
        f"sensor-distance, ball-radius), e.g. pinhole+10%, ball-x-20um"
    )
    match = _ERROR_SYNTAX.fullmatch(name.strip())
    if match is None or match["part"] not in ERROR_PARTS:
        raise ValueError(f"--errors: {name!r} is not an error of the rig description: {syntax}")
    field, component, relative = ERROR_PARTS[match["part"]]
    size = float(match["size"]) * (-1.0 if match["sign"] == "-" else 1.0)
    if match["unit"] == "%":
        if not relative:
            raise ValueError(f"--errors: {name!r}: {match['part']} is a position: give its error in mm or um, not %")
        if size <= -100.0:
            raise ValueError(f"--errors: {name!r}: a length cannot shrink by 100 % or more")
        return WrongNumber(name, field, "scale", round(1.0 + size / 100.0, 12))
    metres = round(size * _METRES[match["unit"]], 15)
    if component is None:
        return WrongNumber(name, field, "add", metres)
    vector = [0.0, 0.0, 0.0]
    vector[component] = metres
    return WrongNumber(name, field, "add", (vector[0], vector[1], vector[2]))


def described_wrong(rig: dict, error: str) -> dict:
    """``rig`` (the run file's JSON description) with the error named ``error`` made in it
    (:func:`parse_error`)."""
    wrong = parse_error(error)
    out = json.loads(json.dumps(rig))
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
