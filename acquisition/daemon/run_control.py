"""What the daemon's requests and a run's thread share (``acquisition.daemon.engine``): the control
flags the requests set and the thread obeys, the signals that end a run's steps, the
progress counter that event streams wait on, and the errors of a request the engine refuses."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field


class RunEngineError(Exception):
    """A request the engine cannot honour (mapped to an HTTP status by the API)."""


class RunConflictError(RunEngineError):
    """The devices are busy, or the run is not in a state that allows the request."""


class Aborted(Exception):
    """Raised in the run thread at a checkpoint once the run is aborted."""


class OperatorStop(Exception):
    """Raised in the run thread when a stop of the arm cut its move short: the position is
    taken again once the run resumes."""


@dataclass
class Control:
    """Flags the HTTP side sets and the run thread obeys.

    ``stop`` is the serial number of the latest stop of the arm (``POST /arm/stop``): a move
    that ends short while it changes was stopped by the operator, and its position is taken
    again once the run resumes; any other move that ends short is a device fault.
    """

    pause: threading.Event = field(default_factory=threading.Event)
    abort: threading.Event = field(default_factory=threading.Event)
    wake: threading.Condition = field(default_factory=threading.Condition)
    stop: int = 0


class ProgressEvents:
    """A version counter that server-sent-event streams wait on."""

    def __init__(self):
        self._version = 0
        self._cond = threading.Condition()

    def publish(self) -> None:
        with self._cond:
            self._version += 1
            self._cond.notify_all()

    @property
    def version(self) -> int:
        return self._version

    def wait_newer(self, version: int, timeout: float) -> int:
        with self._cond:
            self._cond.wait_for(lambda: self._version != version, timeout=timeout)
            return self._version
