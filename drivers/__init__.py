"""Device interfaces (an arm, a camera) and their real implementations.

This package depends on nothing else of the project: the acquisition daemon and the
simulated devices both build on it, never the other way round.
"""

from drivers.arm import Arm, ArmStatus, SoftLimits
from drivers.camera import Camera, RawFrame
from drivers.errors import (
    AlarmError,
    CommunicationError,
    DeviceError,
    DeviceTimeoutError,
    LimitsError,
    MoveInterruptedError,
    RawFileError,
)
from drivers.pose import Pose

__all__ = [
    "AlarmError",
    "Arm",
    "ArmStatus",
    "Camera",
    "CommunicationError",
    "DeviceError",
    "DeviceTimeoutError",
    "LimitsError",
    "MoveInterruptedError",
    "Pose",
    "RawFileError",
    "RawFrame",
    "SoftLimits",
]
