"""Motion model of the simulated stage: the physics behind both simulated protocols.

Moves take time (a trapezoidal velocity profile along a straight line in pose space),
the read-back position has small noise, travel limits and alarms latch as on a real
controller, a communication watchdog stops the stage when the host goes silent, and
faults can be injected. The Modbus server and the serial peer only translate their
protocol into calls on one :class:`SimulatedStage`.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

# Imported here, not at the first rotating move: importing it then, on the simulated Modbus
# server's event loop, can stall request handling past the watchdog on a busy machine.
from scipy.spatial.transform import Rotation, Slerp

from drivers.pose import AXES, Pose, rotation_from_angles

# Alarm codes of the simulated controller (documented in drivers/profiles/sim_stage.toml).
ALARM_TRAVEL = 0x0101
ALARM_NOT_HOMED = 0x0102
ALARM_COMM_TIMEOUT = 0x0301
ALARM_INJECTED = 0x0410

ALARM_TEXT = {
    ALARM_TRAVEL: "target outside the travel range",
    ALARM_NOT_HOMED: "move commanded before homing",
    ALARM_COMM_TIMEOUT: "communication watchdog expired, stage stopped",
    ALARM_INJECTED: "overload (injected fault)",
}


@dataclass
class StageConfig:
    """Mechanics of the simulated stage.

    ``travel`` holds the hard travel range per axis (metres, radians); a target outside
    it raises an alarm, as a real controller does, whatever the host's soft limits say.
    A speed of ``math.inf`` makes every move instantaneous (zero-latency benchmarks).
    """

    name: str = "mirrorgonio simulated stage"
    speed_m_s: float = 0.05
    accel_m_s2: float = 0.5
    angular_speed_rad_s: float = 1.0
    angular_accel_rad_s2: float = 5.0
    readback_noise_m: float = 5e-6
    readback_noise_rad: float = 1e-5
    in_position_tolerance_m: float = 20e-6
    travel: dict[str, tuple[float, float]] = field(
        default_factory=lambda: {
            "x": (-0.30, 0.30),
            "y": (-0.30, 0.30),
            "z": (-0.10, 0.50),
            "rx": (-math.pi, math.pi),
            "ry": (-math.pi, math.pi),
            "rz": (-math.pi, math.pi),
        }
    )
    home_pose: Pose = field(default_factory=lambda: Pose(0.0, 0.10, 0.20, math.pi, 0.0, 0.0))
    require_homing: bool = False
    seed: int = 0


def _profile_duration(distance: float, speed: float, accel: float) -> float:
    """Duration of a trapezoidal (or triangular) move over ``distance``."""
    if distance <= 0.0 or math.isinf(speed):
        return 0.0
    if math.isinf(accel):
        return distance / speed
    if distance < speed * speed / accel:  # never reaches full speed
        return 2.0 * math.sqrt(distance / accel)
    return distance / speed + speed / accel


def _profile_fraction(t: float, duration: float) -> float:
    """Fraction of the path covered at time ``t`` of a symmetric trapezoid-like profile."""
    if duration <= 0.0 or t >= duration:
        return 1.0
    if t <= 0.0:
        return 0.0
    # A smooth symmetric S-curve: the position error of this stand-in for the exact
    # trapezoid is irrelevant to the host, which only sees "moving" and the read-back.
    x = t / duration
    return x * x * (3.0 - 2.0 * x)


class SimulatedStage:
    """Thread-safe simulated stage; all timing comes from the injected ``clock``."""

    def __init__(self, config: StageConfig | None = None, clock: Callable[[], float] | None = None):
        self.config = config or StageConfig()
        self._clock = clock or time.monotonic
        self._lock = threading.RLock()
        now = self._clock()
        self._start = self.config.home_pose
        self._target = self.config.home_pose
        self._t0 = now
        self._duration = 0.0
        self._stopped_at: Pose | None = None
        self._alarm = 0
        self._homed = not self.config.require_homing
        self._servo_on = True
        self.watchdog_timeout_s = 0.0
        self._last_comm = now
        self.move_count = 0
        self._fail_on_move: dict[int, int] = {}

    # -- host commands -----------------------------------------------------------------
    def touch(self) -> None:
        """Any message from the host feeds the watchdog."""
        with self._lock:
            self._check_watchdog()
            self._last_comm = self._clock()

    def move(self, target: Pose) -> None:
        """Start a move; an alarm latches instead if the move is impossible."""
        with self._lock:
            self._update()
            if self._alarm:
                return  # a latched alarm blocks motion until reset
            self.move_count += 1
            if self.move_count in self._fail_on_move:
                self._raise_alarm(self._fail_on_move.pop(self.move_count))
                return
            if not self._homed:
                self._raise_alarm(ALARM_NOT_HOMED)
                return
            for axis in AXES:
                low, high = self.config.travel.get(axis, (-math.inf, math.inf))
                if not low <= getattr(target, axis) <= high:
                    self._raise_alarm(ALARM_TRAVEL)
                    return
            self._begin(target)

    def home(self) -> None:
        with self._lock:
            self._update()
            if self._alarm:
                return
            self._homed = True
            self._begin(self.config.home_pose)

    def stop(self) -> None:
        """Stop at once where the stage is now; the target stays unreached."""
        with self._lock:
            here = self._true_pose_locked()
            self._start = here
            self._duration = 0.0
            self._stopped_at = here

    def reset_alarm(self) -> None:
        with self._lock:
            self._alarm = 0

    def set_watchdog(self, timeout_s: float) -> None:
        """Arm (``> 0``) or disarm (``0``) the communication watchdog."""
        with self._lock:
            self.watchdog_timeout_s = max(0.0, float(timeout_s))
            self._last_comm = self._clock()

    # -- fault injection ---------------------------------------------------------------
    def inject_alarm_on_move(self, move_number: int, code: int = ALARM_INJECTED) -> None:
        """Raise alarm ``code`` when the ``move_number``-th move command (1-based) arrives."""
        with self._lock:
            self._fail_on_move[int(move_number)] = code

    def inject_alarm_now(self, code: int = ALARM_INJECTED) -> None:
        with self._lock:
            self._raise_alarm(code)

    # -- read-back ---------------------------------------------------------------------
    def true_pose(self) -> Pose:
        """Where the tool really is (the world's truth, no read-back noise)."""
        with self._lock:
            self._update()
            return self._true_pose_locked()

    def readback_pose(self) -> Pose:
        """What the encoders report: the true pose plus small noise.

        The noise is drawn once per move, from the stage's seed and the move's number, and
        held until the next: how often the host polls (which depends on how fast the
        machine is) does not change what a pose reads, so a seeded run records the same
        poses on any machine. It stands for the encoders' error at a standstill, which does
        not change from one reading to the next either.
        """
        with self._lock:
            self._update()
            p = self._true_pose_locked()
            noise = np.random.default_rng((self.config.seed, self.move_count))
            dn = noise.normal(0.0, self.config.readback_noise_m, 3)
            da = noise.normal(0.0, self.config.readback_noise_rad, 3)
            return Pose(p.x + dn[0], p.y + dn[1], p.z + dn[2], p.rx + da[0], p.ry + da[1], p.rz + da[2])

    @property
    def target(self) -> Pose:
        with self._lock:
            return self._target

    @property
    def moving(self) -> bool:
        with self._lock:
            self._update()
            return self._duration > 0.0 and self._clock() - self._t0 < self._duration

    @property
    def in_position(self) -> bool:
        with self._lock:
            if self.moving or self._alarm:
                return False
            here = self._true_pose_locked()
            dp, da = here.distance_to(self._target)
            return dp <= self.config.in_position_tolerance_m and da <= 1e-4

    @property
    def alarm_code(self) -> int:
        with self._lock:
            self._update()
            return self._alarm

    @property
    def alarm_text(self) -> str:
        code = self.alarm_code
        return ALARM_TEXT.get(code, f"alarm {code:#06x}") if code else ""

    @property
    def homed(self) -> bool:
        return self._homed

    @property
    def servo_on(self) -> bool:
        return self._servo_on

    def tick(self) -> None:
        """Advance the simulation; a server calls this periodically for the watchdog."""
        with self._lock:
            self._update()

    # -- internals ---------------------------------------------------------------------
    def _begin(self, target: Pose) -> None:
        here = self._true_pose_locked()
        distance, angle = here.distance_to(target)
        c = self.config
        self._duration = max(
            _profile_duration(distance, c.speed_m_s, c.accel_m_s2),
            _profile_duration(angle, c.angular_speed_rad_s, c.angular_accel_rad_s2),
        )
        self._start = here
        self._target = target
        self._t0 = self._clock()
        self._stopped_at = None

    def _raise_alarm(self, code: int) -> None:
        here = self._true_pose_locked()
        self._start = here
        self._duration = 0.0
        self._stopped_at = here
        self._alarm = code

    def _check_watchdog(self) -> None:
        if self.watchdog_timeout_s > 0.0 and not self._alarm:
            if self._clock() - self._last_comm > self.watchdog_timeout_s:
                self._raise_alarm(ALARM_COMM_TIMEOUT)

    def _update(self) -> None:
        self._check_watchdog()

    def _true_pose_locked(self) -> Pose:
        if self._stopped_at is not None:
            return self._stopped_at
        if self._duration <= 0.0:
            return self._target
        s = _profile_fraction(self._clock() - self._t0, self._duration)
        if s >= 1.0:
            return self._target
        a, b = self._start, self._target
        position = (1.0 - s) * a.position + s * b.position
        rotation = _slerp_rotation(a.rotation, b.rotation, s)
        return Pose.from_rotation(position, rotation)


def _slerp_rotation(r0: np.ndarray, r1: np.ndarray, s: float) -> np.ndarray:
    """Rotation a fraction ``s`` of the way from ``r0`` to ``r1`` (shortest arc)."""
    key = Rotation.from_matrix(np.stack([r0, r1]))
    return Slerp([0.0, 1.0], key)([s]).as_matrix()[0]


__all__ = [
    "ALARM_COMM_TIMEOUT",
    "ALARM_INJECTED",
    "ALARM_NOT_HOMED",
    "ALARM_TEXT",
    "ALARM_TRAVEL",
    "SimulatedStage",
    "StageConfig",
    "rotation_from_angles",
]
