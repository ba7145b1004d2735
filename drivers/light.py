"""The light switch interface: the measured light on or off, the room's lights on or off.

A run's calibration frames (``docs/run-file.md``) are taken with the measured light off:
*ambient* frames with the room lit, *dark* frames with the room dark; the sweep with the light
on and the room dark. A :class:`LightSwitch` sets one of these :class:`Lighting` states.

Some switches work by themselves (a relay, the simulated world); others need a person: they
give an :meth:`~LightSwitch.instruction` for the operator, and the acquisition pauses the run
until the operator says it is done. A rig without any switch takes no calibration frames
(:attr:`LightSwitch.takes_calibration` False).
"""

from __future__ import annotations

import abc
from dataclasses import dataclass


@dataclass(frozen=True)
class Lighting:
    """The state of the rig's lights.

    Attributes
    ----------
    light_on : bool
        The measured light shines.
    room_lit : bool
        The room's lights are on (the ball then reflects the room).
    """

    light_on: bool
    room_lit: bool

    def describe(self) -> str:
        """The state in words: ``"the light off, the room lit"``."""
        light = "on" if self.light_on else "off"
        room = "lit" if self.room_lit else "dark"
        return f"the light {light}, the room {room}"


#: The sweep: the measured light on, the room dark.
SWEEP = Lighting(light_on=True, room_lit=False)
#: Ambient calibration frames: the light off, the room lit.
AMBIENT = Lighting(light_on=False, room_lit=True)
#: Dark calibration frames: the light off, the room dark.
DARK = Lighting(light_on=False, room_lit=False)


class LightSwitch(abc.ABC):
    """Anything that can put the rig's lights in a :class:`Lighting` state.

    Attributes
    ----------
    state : Lighting or None
        The state the switch last set, None while it is not known (a manual switch before
        the operator was first asked).
    takes_calibration : bool
        False for a rig without a switch: its runs take no calibration frames.
    """

    name: str = "light switch"
    takes_calibration: bool = True

    def __init__(self) -> None:
        self.state: Lighting | None = None

    @property
    def identity(self) -> str:
        return self.name

    def instruction(self, lighting: Lighting) -> str | None:
        """What the operator must do before :meth:`set` can report ``lighting``; None when the
        switch does it alone."""
        return None

    @abc.abstractmethod
    def set(self, lighting: Lighting) -> None:
        """Put the lights in ``lighting`` (for a manual switch: record that the operator did)."""


class ManualLightSwitch(LightSwitch):
    """A person switches the lights: each change is an instruction, confirmed by resuming the run."""

    name = "manual (the operator switches the lights)"

    def instruction(self, lighting: Lighting) -> str | None:
        light = "on" if lighting.light_on else "off"
        room = "on" if lighting.room_lit else "off"
        return f"turn the light {light} and the room lights {room}, then resume"

    def set(self, lighting: Lighting) -> None:
        self.state = lighting


class NoLightSwitch(LightSwitch):
    """No way to switch the light: runs take no calibration frames."""

    name = "none"
    takes_calibration = False

    def set(self, lighting: Lighting) -> None:
        """Nothing to do: the lights stay as they are."""
