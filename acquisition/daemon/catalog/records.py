"""What the catalog holds: the runs' and the jobs' states, the transitions allowed between
them, and the records a caller gets back (built from the table rows)."""

from __future__ import annotations

import json
from datetime import UTC, datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, computed_field

from acquisition.daemon.catalog.backends import Row

RunState = Literal["queued", "running", "paused", "complete", "aborted", "failed", "interrupted"]
JobState = Literal["queued", "running", "complete", "failed"]

RUN_STATES: tuple[str, ...] = ("queued", "running", "paused", "complete", "aborted", "failed", "interrupted")
JOB_STATES: tuple[str, ...] = ("queued", "running", "complete", "failed")

#: Which state a run may go to from each state. ``failed -> running`` resumes a run after
#: a persistent device fault has been cleared; ``aborted`` and ``complete`` are final.
#: ``queued -> aborted`` is a run taken out of the queue before it started.
ALLOWED_RUN_TRANSITIONS: dict[str, frozenset[str]] = {
    "queued": frozenset({"running", "aborted", "failed"}),
    "running": frozenset({"paused", "complete", "aborted", "failed", "interrupted"}),
    "paused": frozenset({"running", "aborted", "failed", "interrupted"}),
    "interrupted": frozenset({"running", "aborted", "failed"}),
    "failed": frozenset({"running"}),
    "aborted": frozenset(),
    "complete": frozenset(),
}

#: Which state a job may go to: ``running -> queued`` is :meth:`Catalog.requeue_stale_jobs`.
ALLOWED_JOB_TRANSITIONS: dict[str, frozenset[str]] = {
    "queued": frozenset({"running"}),
    "running": frozenset({"complete", "failed", "queued"}),
    "complete": frozenset(),
    "failed": frozenset(),
}

#: The states of a run not yet ended: waiting in the queue, or in progress.
ACTIVE_RUN_STATES: tuple[str, ...] = ("queued", "running", "paused")
#: The states of the one run a rig may have in progress at a time (see :meth:`Catalog.active_run`).
IN_PROGRESS_RUN_STATES: tuple[str, ...] = ("running", "paused")

#: Times are stored as fixed-width UTC text: compared as strings, they compare as times.
_TIME_FORMAT = "%Y-%m-%dT%H:%M:%S.%fZ"
#: The rig of a catalog that names none, and of the runs and jobs recorded before rigs had names.
DEFAULT_RIG = "default"


class _Record(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class RunRecord(_Record):
    """One run, as the catalog holds it. Times are timezone-aware UTC."""

    id: str
    rig: str = DEFAULT_RIG
    created_utc: datetime
    updated_utc: datetime
    state: RunState
    preset: str | None
    path: str | None
    n_positions: int
    positions_done: int
    current_position: int | None
    exposures_per_position: int | None
    started_utc: datetime | None
    finished_utc: datetime | None
    last_error: str | None
    request: dict[str, Any]
    seconds_per_position: float | None
    #: A queued run's place in the queue, from 1 (the next to start); None once it has left it.
    queue_position: int | None = None

    @computed_field  # type: ignore[prop-decorator]
    @property
    def eta_s(self) -> float | None:
        """Seconds left while running: positions left times the seconds per position."""
        if self.state != "running" or self.seconds_per_position is None:
            return None
        return (self.n_positions - self.positions_done) * self.seconds_per_position


class JobRecord(_Record):
    """One processing job of a run. Times are timezone-aware UTC."""

    id: str
    run_id: str
    rig: str = DEFAULT_RIG
    created_utc: datetime
    updated_utc: datetime
    state: JobState
    steps: str
    options: dict[str, Any]
    progress: float
    claimed_by: str | None
    heartbeat_utc: datetime | None
    error: str | None
    result_dir: str | None
    artifacts: dict[str, str] = {}
    message: str | None = None
    not_before_utc: datetime | None = None
    step: str | None = None


# --- times and rows ----------------------------------------------------------------------
def format_time(t: datetime) -> str:
    """A UTC time as the catalog stores it."""
    return t.strftime(_TIME_FORMAT)


def parse_time(text: str | None) -> datetime | None:
    """A stored time as a timezone-aware UTC datetime (None stays None)."""
    return None if text is None else datetime.strptime(text, _TIME_FORMAT).replace(tzinfo=UTC)


def parse_required_time(text: str) -> datetime:
    """A stored time of a NOT NULL column as a timezone-aware UTC datetime."""
    return datetime.strptime(text, _TIME_FORMAT).replace(tzinfo=UTC)


def run_from_row(row: Row) -> RunRecord:
    """The record of a row of ``runs`` selected with :data:`~acquisition.daemon.catalog.schema.RUN_COLUMNS`."""
    return RunRecord(
        id=row["id"],
        rig=row["rig"],
        created_utc=parse_required_time(row["created_utc"]),
        updated_utc=parse_required_time(row["updated_utc"]),
        state=row["state"],
        preset=row["preset"],
        path=row["path"],
        n_positions=row["n_positions"],
        positions_done=row["positions_done"],
        current_position=row["current_position"],
        exposures_per_position=row["exposures_per_position"],
        started_utc=parse_time(row["started_utc"]),
        finished_utc=parse_time(row["finished_utc"]),
        last_error=row["last_error"],
        request=json.loads(row["request_json"]),
        seconds_per_position=row["seconds_per_position"],
        queue_position=row["queue_position"],
    )


def job_from_row(row: Row) -> JobRecord:
    """The record of a row of ``jobs`` selected with :data:`~acquisition.daemon.catalog.schema.JOB_COLUMNS`."""
    return JobRecord(
        id=row["id"],
        run_id=row["run_id"],
        rig=row["rig"],
        created_utc=parse_required_time(row["created_utc"]),
        updated_utc=parse_required_time(row["updated_utc"]),
        state=row["state"],
        steps=row["steps"],
        options=json.loads(row["options_json"]),
        progress=row["progress"],
        claimed_by=row["claimed_by"],
        heartbeat_utc=parse_time(row["heartbeat_utc"]),
        error=row["error"],
        result_dir=row["result_dir"],
        artifacts=json.loads(row["artifacts_json"]),
        message=row["message"],
        not_before_utc=parse_time(row["not_before_utc"]),
        step=row["step"],
    )
