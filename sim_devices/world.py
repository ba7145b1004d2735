"""The simulated world shared by the simulated arm, camera and light switch.

The camera learns where the light is from here: the arm's tool pose composed with the
light-to-tool transform, never from the acquisition code's schedule. Where the tool
pose comes from depends on where the arm is:

- the simulated stage in the same process: its true pose (:class:`SimulatedStage.true_pose`);
- any other arm (the simulated stage in another process or container, reached over
  Modbus TCP, or a real arm): the pose its controller reads back through the driver, so
  the simulated camera photographs the light where the arm actually is
  (:meth:`SimWorld.following`).

The world also holds the state of the lights: whether the measured light shines and whether
the room is lit. The camera renders the light's emitters only while it shines and the room
(its environment radiance) only while it is lit; :class:`SimulatedLightSwitch` is the
daemon's switch of them.
"""

from __future__ import annotations

from collections.abc import Callable

from drivers.light import Lighting, LightSwitch
from drivers.pose import Pose


class SimWorld:
    """Where the light is, right now, and whether it and the room are lit.

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
    light_on : bool
        The measured light shines (its emitters are rendered; its housing is always there).
    room_lit : bool
        The room is lit: the camera renders its environment radiance (a camera's default
        environment is dark anyway, so a world built without a room state changes nothing).
    """

    def __init__(
        self,
        tool_pose: Callable[[], Pose],
        light_to_tool: Pose | None = None,
        *,
        arm_base: Pose | None = None,
        hold_within_m: float = 0.0,
        hold_within_rad: float = 0.0,
        light_on: bool = True,
        room_lit: bool = True,
    ):
        self._tool_pose = tool_pose
        self.light_on = light_on
        self.room_lit = room_lit
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
        light_on: bool = True,
        room_lit: bool = True,
    ) -> SimWorld:
        """A world whose light follows an arm known only through its read-back pose.

        ``read_tool_pose`` is normally the arm driver's ``position`` (``Arm.position``):
        each capture asks the controller where the tool is. The default hold (50 um,
        0.2 mrad) is well above the read-back noise of the simulated stage (5 um,
        0.01 mrad) and of a lab arm's encoders, and far below the spacing of any schedule.
        """
        hold = {"hold_within_m": hold_within_m, "hold_within_rad": hold_within_rad}
        return cls(read_tool_pose, light_to_tool, arm_base=arm_base, light_on=light_on, room_lit=room_lit, **hold)

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

    @property
    def lighting(self) -> Lighting:
        """The lights' state now."""
        return Lighting(light_on=self.light_on, room_lit=self.room_lit)


class SimulatedLightSwitch(LightSwitch):
    """The light switch of the simulated rig: it tells the :class:`SimWorld` the lights' state."""

    name = "simulated light switch"

    def __init__(self, world: SimWorld):
        super().__init__()
        self.world = world
        self.state = world.lighting

    def set(self, lighting: Lighting) -> None:
        self.world.light_on, self.world.room_lit = lighting.light_on, lighting.room_lit
        self.state = lighting
