"""What the technician does at the rig outside a run: a test shot, a jog of the arm, homing.

Each holds the devices through :meth:`acquisition.daemon.engine.RunEngine.manual`: refused (409)
while a run is active, and a run is refused while it lasts. A jog is checked against the rig's
``[arm.soft_limits]`` before anything is sent (:class:`MoveRefusedError`, 422). A test shot's
frames go to the preview only: nothing is written to a run or the catalog.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace

from acquisition.daemon.engine import RunEngine
from acquisition.daemon.preview import saturated_mask
from drivers.arm import SoftLimits
from drivers.camera import RawFrame
from drivers.pose import Pose

log = logging.getLogger("mirrorgonio.manual")

#: The unit of a jog's step on each axis, and its factor to the arm's (metres, radians).
JOG_UNITS = {
    "x": ("mm", 1e-3),
    "y": ("mm", 1e-3),
    "z": ("mm", 1e-3),
    "rx": ("deg", math.pi / 180),
    "ry": ("deg", math.pi / 180),
    "rz": ("deg", math.pi / 180),
}


class MoveRefusedError(ValueError):
    """A move that would leave the arm's soft limits (nothing was sent to the arm)."""


def pose_record(pose: Pose) -> dict[str, float]:
    """A pose as the API gives it: x, y, z in metres, rx, ry, rz in degrees."""
    return {
        "x": pose.x,
        "y": pose.y,
        "z": pose.z,
        "rx": math.degrees(pose.rx),
        "ry": math.degrees(pose.ry),
        "rz": math.degrees(pose.rz),
    }


def shot_record(frame: RawFrame) -> dict:
    """One test-shot frame's exposure, peak and saturation."""
    saturated = saturated_mask(frame)
    peak = float(frame.mosaic.max()) - float(frame.black_level.max())
    return {
        "exposure_s": float(frame.exposure_s),
        "peak_dn": round(max(peak, 0.0), 1),
        "saturated_pixels": int(saturated.sum()),
        "saturated_share": float(saturated.mean()),
    }


def within_a_turn(pose: Pose, limits: SoftLimits) -> Pose:
    """``pose`` with each angle outside its soft limits taken a turn the other way where that
    is inside them: rx 180° + 10° is rx -170° within ±180°, and a read-back of rx 180.001° (the
    encoder's noise at the limit) is rx -179.999°."""
    for axis in ("rx", "ry", "rz"):
        low, high = limits.ranges.get(axis, (-math.inf, math.inf))
        value = getattr(pose, axis)
        if not low <= value <= high:
            for turned in (value - 2 * math.pi, value + 2 * math.pi):
                if low <= turned <= high:
                    pose = replace(pose, **{axis: turned})
                    break
    return pose


def take_test_shot(engine: RunEngine, exposures_s: list[float]) -> list[dict]:
    """Take one bracket at the arm's current pose; each frame is shown in the preview in turn
    (the last stays). Returns each frame's :func:`shot_record`."""
    taken = []
    with engine.manual(f"a test shot of {len(exposures_s)} frames"):
        for exposure in exposures_s:
            frame = engine.devices.camera.capture(exposure)
            engine.show_frame(None, frame)
            taken.append(shot_record(frame))
            engine.discard_raw(frame)
    log.info(
        "test shot: %s",
        ", ".join(f"{f['exposure_s']:g} s peak {f['peak_dn']:g} DN, {f['saturated_pixels']} saturated" for f in taken),
    )
    return taken


def jog(engine: RunEngine, axis: str, step: float) -> tuple[Pose, str]:
    """Move the arm by ``step`` (millimetres, or degrees for a rotation) along ``axis`` of its
    tool pose, from where it reads back now.

    Raises
    ------
    MoveRefusedError
        The target is outside the rig's soft limits (one line; nothing sent).
    RunConflictError
        A run is active, or another test shot, jog or homing is under way.
    """
    unit, factor = JOG_UNITS[axis]
    what = f"jog {axis} {step:+g} {unit}"
    with engine.manual(what):
        arm = engine.devices.arm
        start = arm.position()
        limits = engine.rig.soft_limits()
        target = within_a_turn(replace(start, **{axis: getattr(start, axis) + step * factor}), limits)
        problem = limits.violation(target)
        if problem is not None:
            raise MoveRefusedError(f"{what}: {problem} (the rig's arm.soft_limits)")
        reached = arm.move_to(target, timeout=engine.settings.arm.move_timeout_s)
    log.info("%s: at %s", what, _describe(reached))
    return reached, what


def home(engine: RunEngine) -> tuple[Pose, str]:
    """Run the arm controller's homing; returns where it reads back then."""
    with engine.manual("homing the arm"):
        reached = engine.devices.arm.home(timeout=max(120.0, engine.settings.arm.move_timeout_s))
    log.info("homed: at %s", _describe(reached))
    return reached, "homed"


def _describe(pose: Pose) -> str:
    p = pose_record(pose)

    def two(value: float) -> str:
        return f"{round(value, 2) + 0.0:.2f}"  # + 0.0: no "-0.00"

    mm = " ".join(f"{axis} {two(1e3 * p[axis])}" for axis in ("x", "y", "z"))
    deg = " ".join(f"{axis} {two(p[axis])}" for axis in ("rx", "ry", "rz"))
    return f"{mm} mm, {deg} deg"
