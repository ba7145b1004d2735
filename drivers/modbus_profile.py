"""Register-map profiles of Modbus arms and stages, loaded from TOML.

A profile says where a controller keeps its targets, read-backs, command, status bits,
alarm code and watchdog, how positions are scaled to integer counts and in which order
the two words of an int32 travel. The driver (:mod:`drivers.modbus_arm`) and the
simulator both read it, so a profile documents the device once (see
``drivers/profiles/sim_stage.toml`` for a commented example).

An impossible profile is refused with a one-line :class:`ProfileError` that names the
file and the field.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, field_validator, model_validator

from drivers.config_files import ConfigModel, load_model, validate_model
from drivers.pose import AXES

SIM_STAGE_PROFILE = Path(__file__).resolve().parent / "profiles" / "sim_stage.toml"

INT32_MIN = -(2**31)
INT32_MAX = 2**31 - 1

_LINEAR_AXES = ("x", "y", "z")

Address = Annotated[int, Field(ge=0, le=65535)]
Bit = Annotated[int, Field(ge=0, le=15)]
Code = Annotated[int, Field(ge=0, le=65535)]


class ProfileError(ValueError):
    """An impossible or unreadable profile (one line: file, field, cause)."""


class DeviceSection(ConfigModel):
    """Identity of the device on the bus."""

    name: str = Field(min_length=1)
    unit_id: int = Field(ge=1, le=247)
    word_order: Literal["big", "little"] = "big"


class AxisSection(ConfigModel):
    """Registers and scaling of one axis.

    Attributes
    ----------
    target : int
        Holding register of the int32 target (this one and the next).
    actual : int
        Input register of the int32 read-back position (this one and the next).
    unit : {"m", "deg"}
        Unit on the wire; the host side is always metres or radians.
    counts_per_unit : float
        Integer counts per unit: 1e6 per metre is micrometres.
    """

    target: Annotated[int, Field(ge=0, le=65534)]
    actual: Annotated[int, Field(ge=0, le=65534)]
    unit: Literal["m", "deg"]
    counts_per_unit: float = Field(gt=0, allow_inf_nan=False)

    def to_counts(self, value: float) -> int:
        """Counts for ``value`` in metres or radians.

        Raises
        ------
        ValueError
            If the value is not finite or does not fit in an int32.
        """
        wire = math.degrees(value) if self.unit == "deg" else value
        if not math.isfinite(wire):
            raise ValueError(f"{value!r} is not a finite number")
        counts = round(wire * self.counts_per_unit)
        if not INT32_MIN <= counts <= INT32_MAX:
            raise ValueError(f"{wire:g} {self.unit} does not fit in a signed 32-bit register")
        return counts

    def from_counts(self, counts: int) -> float:
        """Metres or radians for a count read from the device."""
        wire = counts / self.counts_per_unit
        return math.radians(wire) if self.unit == "deg" else wire


class CommandSection(ConfigModel):
    """The command register and the code of each command."""

    address: Address
    move: Code
    stop: Code
    home: Code
    reset_alarm: Code

    @model_validator(mode="after")
    def _codes_distinct(self) -> CommandSection:
        codes = {"move": self.move, "stop": self.stop, "home": self.home, "reset_alarm": self.reset_alarm}
        seen: dict[int, str] = {}
        for name, code in codes.items():
            if code in seen:
                raise ValueError(f"command.{name}: code {code} is also command.{seen[code]}")
            seen[code] = name
        return self


class StatusSection(ConfigModel):
    """The status input register and the bit number of each flag."""

    address: Address
    moving: Bit
    in_position: Bit
    alarm: Bit
    homed: Bit
    servo_on: Bit

    @model_validator(mode="after")
    def _bits_distinct(self) -> StatusSection:
        seen: dict[int, str] = {}
        for name in ("moving", "in_position", "alarm", "homed", "servo_on"):
            bit = getattr(self, name)
            if bit in seen:
                raise ValueError(f"status.{name}: bit {bit} is also status.{seen[bit]}")
            seen[bit] = name
        return self


class AlarmSection(ConfigModel):
    """The alarm-code input register and what the codes mean."""

    address: Address
    text: dict[int, str] = Field(default_factory=dict)

    @field_validator("text", mode="before")
    @classmethod
    def _parse_codes(cls, table: object) -> object:
        # TOML keys are strings; accept "0x0410" as well as "1040".
        if not isinstance(table, dict):
            return table
        parsed: dict[int, object] = {}
        for key, text in table.items():
            try:
                code = key if isinstance(key, int) else int(str(key), 0)
            except ValueError:
                raise ValueError(f"alarm.text.{key}: not an integer alarm code") from None
            if not 0 < code <= 0xFFFF:
                raise ValueError(f"alarm.text.{key}: alarm codes are 1..0xffff")
            # Error messages are one line, and the text goes into them.
            parsed[code] = " ".join(text.split()) if isinstance(text, str) else text
        return parsed


class WatchdogSection(ConfigModel):
    """The communication-watchdog register and the timeout the driver arms."""

    address: Address
    timeout_ms: int = Field(ge=1, le=65535)


class SimulationSection(ConfigModel):
    """Holding registers only the simulator understands (fault injection)."""

    inject_alarm_on_move: Annotated[int, Field(ge=0, le=65534)]
    inject_alarm_now: Address
    stop_answering_ms: Address


class ModbusProfile(ConfigModel):
    """A controller's register map (see ``drivers/profiles/sim_stage.toml``)."""

    device: DeviceSection
    axes: dict[str, AxisSection]
    command: CommandSection
    status: StatusSection
    alarm: AlarmSection
    watchdog: WatchdogSection | None = None
    simulation: SimulationSection | None = None

    @field_validator("axes", mode="before")
    @classmethod
    def _known_axes(cls, axes: object) -> object:
        # Before the axes' own fields, so a misspelt axis is named as such.
        if isinstance(axes, dict):
            for name in axes:
                if name not in AXES:
                    raise ValueError(f"axes.{name}: unknown axis (expected {', '.join(AXES)})")
        return axes

    @field_validator("axes")
    @classmethod
    def _six_axes(cls, axes: dict[str, AxisSection]) -> dict[str, AxisSection]:
        for name in AXES:
            if name not in axes:
                raise ValueError(f"axes.{name}: missing")
            expected = "m" if name in _LINEAR_AXES else "deg"
            if axes[name].unit != expected:
                raise ValueError(f"axes.{name}.unit: must be {expected!r} for this axis")
        return {name: axes[name] for name in AXES}

    @model_validator(mode="after")
    def _registers_do_not_overlap(self) -> ModbusProfile:
        holding: list[tuple[str, int, int]] = [
            (f"axes.{name}.target", axis.target, 2) for name, axis in self.axes.items()
        ]
        holding.append(("command.address", self.command.address, 1))
        if self.watchdog is not None:
            holding.append(("watchdog.address", self.watchdog.address, 1))
        if self.simulation is not None:
            sim = self.simulation
            holding += [
                ("simulation.inject_alarm_on_move", sim.inject_alarm_on_move, 2),
                ("simulation.inject_alarm_now", sim.inject_alarm_now, 1),
                ("simulation.stop_answering_ms", sim.stop_answering_ms, 1),
            ]
        inputs: list[tuple[str, int, int]] = [
            (f"axes.{name}.actual", axis.actual, 2) for name, axis in self.axes.items()
        ]
        inputs += [("status.address", self.status.address, 1), ("alarm.address", self.alarm.address, 1)]
        for table in (holding, inputs):
            owner: dict[int, str] = {}
            for field_name, start, count in table:
                for address in range(start, start + count):
                    if address in owner:
                        raise ValueError(f"{field_name}: register {address} is also used by {owner[address]}")
                    owner[address] = field_name
        return self

    # -- helpers shared by the driver and the simulator -----------------------------------
    def alarm_text(self, code: int) -> str:
        """What alarm ``code`` means according to the profile ("" for no alarm)."""
        if code == 0:
            return ""
        return self.alarm.text.get(code, "not in the profile's alarm table")


def profile_from_dict(data: dict, source: str = "<profile>") -> ModbusProfile:
    """Validate a profile given as a dictionary (the parsed TOML)."""
    return validate_model(ModbusProfile, data, source, ProfileError)


def load_profile(path: str | Path = SIM_STAGE_PROFILE) -> ModbusProfile:
    """Load and validate a profile TOML file.

    Raises
    ------
    ProfileError
        One line naming the file and the field, if the file is missing, is not TOML or
        describes an impossible register map.
    """
    return load_model(path, ModbusProfile, "profile file", ProfileError)


__all__ = [
    "SIM_STAGE_PROFILE",
    "AxisSection",
    "ModbusProfile",
    "ProfileError",
    "load_profile",
    "profile_from_dict",
]
