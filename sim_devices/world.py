"""The simulated world shared by the simulated arm and camera.

The camera learns where the light is from here (the stage's true tool pose composed
with the light-to-tool transform), never from the acquisition code that drives them.
"""

from __future__ import annotations

from collections.abc import Callable

from drivers.pose import Pose


class SimWorld:
    """Where the light is, right now.

    Parameters
    ----------
    tool_pose : callable
        Returns the true pose of the arm's tool (normally ``SimulatedStage.true_pose``).
    light_to_tool : Pose
        The light's frame expressed in the tool's frame (fixed by the light's mount).
    """

    def __init__(self, tool_pose: Callable[[], Pose], light_to_tool: Pose | None = None):
        self._tool_pose = tool_pose
        self.light_to_tool = light_to_tool or Pose(0.0, 0.0, 0.0)

    def tool_pose(self) -> Pose:
        return self._tool_pose()

    def light_pose(self) -> Pose:
        return self._tool_pose().compose(self.light_to_tool)
