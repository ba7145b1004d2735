"""The catalog's errors: one line each, naming the run or the job and the states involved.

Each pickles with its arguments (``__reduce__``), so that it crosses a process boundary whole.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Self

from acquisition.daemon.storage import InsufficientStorageError, StorageUnavailableError


class CatalogError(ValueError):
    """A refused catalog operation (one line: the run or job, the states, the cause)."""


class UnknownRunError(CatalogError):
    """No run has this id."""

    def __init__(self, run_id: str):
        self.run_id = run_id
        super().__init__(f"unknown run {run_id!r}")

    def __reduce__(self) -> tuple[type[Self], tuple[object, ...]]:
        return (type(self), (self.run_id,))


class UnknownJobError(CatalogError):
    """No job has this id."""

    def __init__(self, job_id: str):
        self.job_id = job_id
        super().__init__(f"unknown job {job_id!r}")

    def __reduce__(self) -> tuple[type[Self], tuple[object, ...]]:
        return (type(self), (self.job_id,))


class InvalidTransitionError(CatalogError):
    """A run or job cannot go from its current state to the one asked for.

    Parameters
    ----------
    record_id : str
        The run's or the job's id.
    from_state, to_state : str
        The state it is in, and the state that was asked for.
    allowed : Iterable of str
        The states it may go to from ``from_state``.
    """

    def __init__(self, record_id: str, from_state: str, to_state: str, allowed: Iterable[str] = ()) -> None:
        self.record_id = record_id
        self.from_state = from_state
        self.to_state = to_state
        self.allowed = tuple(sorted(allowed))
        targets = ", ".join(self.allowed) or "none, it is final"
        super().__init__(f"{record_id}: cannot go from {from_state} to {to_state} (from {from_state}: {targets})")

    def __reduce__(self) -> tuple[type[Self], tuple[object, ...]]:
        return (type(self), (self.record_id, self.from_state, self.to_state, self.allowed))


class ActiveRunError(CatalogError):
    """Another run is already running or paused: one run in progress at a time per rig."""

    def __init__(self, active_id: str, active_state: str, wanted: str):
        self.active_id = active_id
        self.active_state = active_state
        self.wanted = wanted
        super().__init__(f"cannot {wanted}: run {active_id} is {active_state} (one run in progress at a time)")

    def __reduce__(self) -> tuple[type[Self], tuple[object, ...]]:
        return (type(self), (self.active_id, self.active_state, self.wanted))


class NotQueuedError(CatalogError):
    """A queue operation on a run that is not queued (it has started, ended or was removed)."""

    def __init__(self, run_id: str, state: str, wanted: str):
        self.run_id = run_id
        self.state = state
        self.wanted = wanted
        super().__init__(f"cannot {wanted}: run {run_id} is {state}, not queued")

    def __reduce__(self) -> tuple[type[Self], tuple[object, ...]]:
        return (type(self), (self.run_id, self.state, self.wanted))


class OtherRigError(CatalogError):
    """A change to a run of another rig: a daemon reads the lab's runs but changes only its own."""

    def __init__(self, run_id: str, run_rig: str, rig: str, wanted: str):
        self.run_id = run_id
        self.run_rig = run_rig
        self.rig = rig
        self.wanted = wanted
        super().__init__(f"cannot {wanted}: run {run_id} belongs to rig {run_rig!r}; rig {rig!r} can only read it")

    def __reduce__(self) -> tuple[type[Self], tuple[object, ...]]:
        return (type(self), (self.run_id, self.run_rig, self.rig, self.wanted))


class JobClaimError(CatalogError):
    """A worker reported on a job it no longer holds (requeued, claimed by another, or finished)."""

    def __init__(self, job_id: str, worker_id: str, state: str, claimed_by: str | None):
        self.job_id = job_id
        self.worker_id = worker_id
        self.state = state
        self.claimed_by = claimed_by
        super().__init__(f"job {job_id} is {state}, claimed by {claimed_by or 'nobody'}, not by {worker_id}")

    def __reduce__(self) -> tuple[type[Self], tuple[object, ...]]:
        return (type(self), (self.job_id, self.worker_id, self.state, self.claimed_by))


class CatalogFullError(CatalogError, InsufficientStorageError):
    """The catalog could not be written: its disk is full (``SQLITE_FULL``; HTTP 507)."""


class CatalogUnavailableError(CatalogError, StorageUnavailableError):
    """The catalog could not be read or written: read-only, an I/O error, locked by another
    process past the busy timeout, or damaged (HTTP 503)."""
