"""The arm interface: what the acquisition needs of anything that moves the light.

Concrete arms (:mod:`drivers.modbus_arm`, :mod:`drivers.serial_arm`) differ only in how
they talk to the controller; checking soft limits before anything is sent and waiting
for "in position" are shared here.
"""

from __future__ import annotations

import abc
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from drivers.errors import AlarmError, DeviceTimeoutError, LimitsError, MoveInterruptedError
from drivers.pose import AXES, Pose

_ANGULAR = {"rx", "ry", "rz"}


@dataclass(frozen=True)
class SoftLimits:
    """Allowed range per axis: metres for x, y, z, radians for rx, ry, rz.

    An axis that is absent is not limited.
    """

    ranges: dict[str, tuple[float, float]] = field(default_factory=dict)

    def violation(self, pose: Pose) -> str | None:
        """The first axis outside its range, described in one line, or None."""
        for axis in AXES:
            if axis not in self.ranges:
                continue
            low, high = self.ranges[axis]
            value = getattr(pose, axis)
            if not low <= value <= high:
                if axis in _ANGULAR:
                    return (
                        f"{axis}={math.degrees(value):.3f} deg outside the soft limits "
                        f"[{math.degrees(low):.3f}, {math.degrees(high):.3f}] deg"
                    )
                return f"{axis}={value:.6f} m outside the soft limits [{low:.6f}, {high:.6f}] m"
        return None

    def check(self, pose: Pose, device: str, command: str = "move_to") -> None:
        """Raise :class:`LimitsError` if ``pose`` is outside the limits."""
        problem = self.violation(pose)
        if problem is not None:
            raise LimitsError(device, command, problem)


@dataclass(frozen=True)
class ArmStatus:
    """What the controller says about itself."""

    moving: bool
    in_position: bool
    alarm_code: int = 0
    alarm_text: str = ""
    homed: bool = True
    servo_on: bool = True

    @property
    def alarm(self) -> bool:
        return self.alarm_code != 0


class Arm(abc.ABC):
    """An arm or stage that holds the light.

    Use as a context manager: ``with ModbusArm(...) as arm: arm.move_to(pose)``.

    ``start_grace_s`` is how long a move may show neither motion nor "in position"
    before it counts as stopped short.

    Parameters
    ----------
    name : str
        Device name used in every error message.
    limits : SoftLimits
        Checked before any byte of a move is sent.
    poll_interval_s : float
        How often :meth:`move_to` reads the status while waiting.
    sleep : callable
        Injected so that tests and simulations can run on their own clock.
    clock : callable
        Monotonic clock in seconds, injected for the same reason.
    """

    start_grace_s = 1.0

    def __init__(
        self,
        name: str,
        limits: SoftLimits | None = None,
        poll_interval_s: float = 0.01,
        sleep: Callable[[float], None] = time.sleep,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.name = name
        self.limits = limits or SoftLimits()
        self.poll_interval_s = poll_interval_s
        self._sleep = sleep
        self._clock = clock

    # -- life cycle -------------------------------------------------------------------
    @abc.abstractmethod
    def connect(self) -> None: ...

    @abc.abstractmethod
    def close(self) -> None: ...

    def __enter__(self) -> Arm:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- backend-specific primitives ---------------------------------------------------
    @abc.abstractmethod
    def _start_move(self, pose: Pose) -> None:
        """Send the target and the move command; return without waiting."""

    @abc.abstractmethod
    def _start_home(self) -> None:
        """Send the homing command; return without waiting."""

    @abc.abstractmethod
    def position(self) -> Pose:
        """The position the controller reads back (not the commanded one)."""

    @abc.abstractmethod
    def status(self) -> ArmStatus: ...

    @abc.abstractmethod
    def stop(self) -> None:
        """Stop at once, also in the middle of a move."""

    @abc.abstractmethod
    def reset_alarm(self) -> None:
        """Clear a latched alarm once its cause is fixed."""

    @property
    def identity(self) -> str:
        """A description of the device for the run file."""
        return self.name

    # -- shared motion logic -----------------------------------------------------------
    def move_to(self, pose: Pose, timeout: float = 60.0) -> Pose:
        """Move to ``pose`` and return the read-back position once in position.

        Raises
        ------
        LimitsError
            Before anything is sent, if ``pose`` is outside the soft limits.
        AlarmError
            If the controller raises an alarm during the move.
        DeviceTimeoutError
            If the arm is not in position after ``timeout`` seconds (it is then stopped).
        """
        self.limits.check(pose, self.name, "move_to")
        self._start_move(pose)
        self._wait_in_position("move_to", timeout)
        return self.position()

    def home(self, timeout: float = 120.0) -> Pose:
        """Run the controller's homing and return the read-back position."""
        self._start_home()
        self._wait_in_position("home", timeout)
        return self.position()

    def _wait_in_position(self, command: str, timeout: float) -> None:
        start = self._clock()
        deadline = start + timeout
        seen_moving = False
        while True:
            status = self.status()
            if status.alarm:
                raise AlarmError(self.name, command, status.alarm_code, status.alarm_text)
            if status.in_position and not status.moving:
                return
            seen_moving |= status.moving
            # Neither moving nor in position: stopped short (a stop command, an operator's
            # emergency stop). A controller may take a moment to start, hence the grace.
            if not status.moving and (seen_moving or self._clock() - start > self.start_grace_s):
                raise MoveInterruptedError(self.name, command, "stopped before reaching the target")
            if self._clock() > deadline:
                try:
                    self.stop()
                finally:
                    raise DeviceTimeoutError(self.name, command, f"not in position after {timeout:g} s")
            self._sleep(self.poll_interval_s)
