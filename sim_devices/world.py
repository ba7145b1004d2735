"""The simulated world shared by the simulated arm and camera.

The camera learns where the light is from here: the arm's tool pose composed with the
light-to-tool transform, never from the acquisition code's schedule. Where the tool
pose comes from depends on where the arm is:

- the simulated stage in the same process: its true pose (:class:`SimulatedStage.true_pose`);
- any other arm (the simulated stage in another process or container, reached over
  Modbus TCP, or a real arm): the pose its controller reads back through the driver, so
  the simulated camera photographs the light where the arm actually is
  (:meth:`SimWorld.following`).
"""

from __future__ import annotations

from collections.abc import Callable

from drivers.pose import Pose


class SimWorld:
    """Where the light is, right now.

    Parameters
    ----------
    tool_pose : callable
        Returns the pose of the arm's tool (normally ``SimulatedStage.true_pose``).
    light_to_tool : Pose
        The light's frame expressed in the tool's frame (fixed by the light's mount).
    arm_base : Pose, optional
        The arm's base frame in the rig frame, where the tool poses are (the rig frame if None).
    hold_within_m, hold_within_rad : float
        A read-back pose jitters from one reading to the next (encoder noise) while the
        tool stands still. A reading within these of the pose returned last is taken as
        the same pose, so the camera renders a standing light once, not once per frame.
        Zero (the default, for a true pose) returns every reading as it is.
    """

    def __init__(
        self,
        tool_pose: Callable[[], Pose],
        light_to_tool: Pose | None = None,
        *,
        arm_base: Pose | None = None,
        hold_within_m: float = 0.0,
        hold_within_rad: float = 0.0,
    ):
        self._tool_pose = tool_pose
        self.light_to_tool = light_to_tool or Pose(0.0, 0.0, 0.0)
        self.arm_base = arm_base
        self.hold_within_m = hold_within_m
        self.hold_within_rad = hold_within_rad
        self._held: Pose | None = None

    @classmethod
    def following(
        cls,
        read_tool_pose: Callable[[], Pose],
        light_to_tool: Pose | None = None,
        *,
        arm_base: Pose | None = None,
        hold_within_m: float = 50e-6,
        hold_within_rad: float = 2e-4,
    ) -> SimWorld:
        """A world whose light follows an arm known only through its read-back pose.

        ``read_tool_pose`` is normally the arm driver's ``position`` (``Arm.position``):
        each capture asks the controller where the tool is. The default hold (50 um,
        0.2 mrad) is well above the read-back noise of the simulated stage (5 um,
        0.01 mrad) and of a lab arm's encoders, and far below the spacing of any schedule.
        """
        hold = {"hold_within_m": hold_within_m, "hold_within_rad": hold_within_rad}
        return cls(read_tool_pose, light_to_tool, arm_base=arm_base, **hold)

    def tool_pose(self) -> Pose:
        pose = self._tool_pose()
        if not (self.hold_within_m > 0.0 or self.hold_within_rad > 0.0):
            return pose
        held = self._held
        if held is not None:
            distance, angle = pose.distance_to(held)
            if distance <= self.hold_within_m and angle <= self.hold_within_rad:
                return held
        self._held = pose
        return pose

    def light_pose(self) -> Pose:
        """The light's pose in the rig frame: ``arm_base ∘ tool ∘ light_to_tool``."""
        light = self.tool_pose().compose(self.light_to_tool)
        return light if self.arm_base is None else self.arm_base.compose(light)
