"""Domain errors of the devices.

Every message is one line that names the device, the command and the cause, so that a
technician reading a failed run's status knows what to do without a traceback.
"""

from __future__ import annotations


class DeviceError(Exception):
    """A device refused or failed a command.

    Parameters
    ----------
    device : str
        Name of the device (from its profile or configuration).
    command : str
        What was asked of it (``move_to``, ``home``, ``capture``...).
    cause : str
        Why it failed, in the device's own words where it gave any.
    """

    def __init__(self, device: str, command: str, cause: str):
        self.device = device
        self.command = command
        self.cause = cause
        super().__init__(f"{device}: {command}: {cause}")


class LimitsError(DeviceError):
    """A target lies outside the soft limits; raised before anything is sent."""


class AlarmError(DeviceError):
    """The device reports an alarm (it has stopped by itself)."""

    def __init__(self, device: str, command: str, code: int, text: str):
        self.code = code
        self.text = text
        super().__init__(device, command, f"alarm {code:#06x}: {text}")


class DeviceTimeoutError(DeviceError):
    """The device did not answer, or did not finish, in time."""


class MoveInterruptedError(DeviceError):
    """The arm stopped before reaching its target (a stop command, an emergency stop)."""


class CommunicationError(DeviceError):
    """The link to the device failed (connection refused or dropped, garbled reply).

    Transient by nature: callers may retry.
    """


class RawFileError(DeviceError):
    """A raw file could not be decoded into a mosaic with its metadata."""
