"""The catalog: every run and every processing job, in one SQLite file next to the data.

The catalog lives at ``DATA_DIR/catalog.sqlite`` and outlives the daemon: after a restart
:meth:`Catalog.mark_interrupted` turns the runs the previous daemon left behind into
``interrupted`` ones, which can be resumed. It is shared by the daemon's threads (HTTP
handlers, the run engine) and by separate processing worker processes, which claim jobs
with :meth:`Catalog.claim_job` and prove they are alive with :meth:`Catalog.heartbeat`.

Portability: the schema uses plain SQL types (``TEXT``, ``INTEGER``, ``REAL``) and
``CHECK`` constraints only, so that it can move to PostgreSQL; SQLite-specific settings
are confined to ``PRAGMA`` statements at open. Times are stored as fixed-width UTC text,
``2026-11-21T13:45:01.123456Z``, so that comparing them as strings compares the times.

Concurrency: the file is in WAL mode (readers never wait for the writer), every write is
one ``BEGIN IMMEDIATE`` transaction (the write lock is taken at the start, so a
transaction never has to upgrade a read snapshot and fail with ``SQLITE_BUSY``), and
other processes holding the lock are waited for up to ``busy_timeout_s``. WAL needs a
local file system: do not put ``DATA_DIR`` on a network share.

Bad input is refused with a one-line :class:`CatalogError` that names the run or the job
and the states involved.
"""

from __future__ import annotations

import json
import math
import os
import re
import secrets
import sqlite3
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, computed_field

SCHEMA_VERSION = 2

RunState = Literal["queued", "running", "paused", "complete", "aborted", "failed", "interrupted"]
JobState = Literal["queued", "running", "complete", "failed"]

RUN_STATES: tuple[str, ...] = ("queued", "running", "paused", "complete", "aborted", "failed", "interrupted")
JOB_STATES: tuple[str, ...] = ("queued", "running", "complete", "failed")

#: Which state a run may go to from each state. ``failed -> running`` resumes a run after
#: a persistent device fault has been cleared; ``aborted`` and ``complete`` are final.
#: :meth:`Catalog.mark_interrupted` is the one path outside this table: at daemon start a
#: run left ``queued`` also becomes ``interrupted``.
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

#: The states of the one run a rig may have at a time (see :meth:`Catalog.active_run`).
ACTIVE_RUN_STATES: tuple[str, ...] = ("queued", "running", "paused")
#: A run entering one of these gets its ``finished_utc``; entering ``running`` clears it.
_FINISHING_RUN_STATES = ("complete", "aborted", "failed")

_TIME_FORMAT = "%Y-%m-%dT%H:%M:%S.%fZ"
_STEP_NAME = re.compile(r"[a-z][a-z0-9_]*\Z")


# --- errors ----------------------------------------------------------------------------
class CatalogError(ValueError):
    """A refused catalog operation (one line: the run or job, the states, the cause)."""


class UnknownRunError(CatalogError):
    """No run has this id."""

    def __init__(self, run_id: str):
        self.run_id = run_id
        super().__init__(f"unknown run {run_id!r}")

    def __reduce__(self):
        return (type(self), (self.run_id,))


class UnknownJobError(CatalogError):
    """No job has this id."""

    def __init__(self, job_id: str):
        self.job_id = job_id
        super().__init__(f"unknown job {job_id!r}")

    def __reduce__(self):
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

    def __init__(self, record_id: str, from_state: str, to_state: str, allowed=()):
        self.record_id = record_id
        self.from_state = from_state
        self.to_state = to_state
        self.allowed = tuple(sorted(allowed))
        targets = ", ".join(self.allowed) or "none, it is final"
        super().__init__(f"{record_id}: cannot go from {from_state} to {to_state} (from {from_state}: {targets})")

    def __reduce__(self):
        return (type(self), (self.record_id, self.from_state, self.to_state, self.allowed))


class ActiveRunError(CatalogError):
    """Another run is already queued, running or paused: one run at a time per rig."""

    def __init__(self, active_id: str, active_state: str, wanted: str):
        self.active_id = active_id
        self.active_state = active_state
        self.wanted = wanted
        super().__init__(f"cannot {wanted}: run {active_id} is {active_state} (one run at a time)")

    def __reduce__(self):
        return (type(self), (self.active_id, self.active_state, self.wanted))


class JobClaimError(CatalogError):
    """A worker reported on a job it no longer holds (requeued, claimed by another, or finished)."""

    def __init__(self, job_id: str, worker_id: str, state: str, claimed_by: str | None):
        self.job_id = job_id
        self.worker_id = worker_id
        self.state = state
        self.claimed_by = claimed_by
        super().__init__(f"job {job_id} is {state}, claimed by {claimed_by or 'nobody'}, not by {worker_id}")

    def __reduce__(self):
        return (type(self), (self.job_id, self.worker_id, self.state, self.claimed_by))


# --- records ---------------------------------------------------------------------------
class _Record(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class RunRecord(_Record):
    """One run, as the catalog holds it. Times are timezone-aware UTC."""

    id: str
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


# --- schema ----------------------------------------------------------------------------
def _in_list(states) -> str:
    return ", ".join(f"'{s}'" for s in states)


# One tuple of statements per schema version; version N is _MIGRATIONS[N - 1]. Never edit
# a released entry: append a new one. ``seq`` orders rows (newest first, oldest queued job
# first) even when two share a timestamp; it is MAX(seq) + 1 taken inside the write
# transaction (PostgreSQL would use a sequence instead).
_MIGRATIONS: tuple[tuple[str, ...], ...] = (
    (
        f"""CREATE TABLE runs (
            id TEXT PRIMARY KEY,
            seq INTEGER NOT NULL UNIQUE,
            created_utc TEXT NOT NULL,
            updated_utc TEXT NOT NULL,
            state TEXT NOT NULL CHECK (state IN ({_in_list(RUN_STATES)})),
            preset TEXT,
            path TEXT,
            n_positions INTEGER NOT NULL CHECK (n_positions >= 1),
            positions_done INTEGER NOT NULL CHECK (positions_done >= 0 AND positions_done <= n_positions),
            current_position INTEGER,
            exposures_per_position INTEGER,
            started_utc TEXT,
            finished_utc TEXT,
            last_error TEXT,
            request_json TEXT NOT NULL,
            seconds_per_position REAL
        )""",
        "CREATE INDEX runs_state ON runs (state)",
        f"""CREATE TABLE jobs (
            id TEXT PRIMARY KEY,
            seq INTEGER NOT NULL UNIQUE,
            run_id TEXT NOT NULL REFERENCES runs (id),
            created_utc TEXT NOT NULL,
            updated_utc TEXT NOT NULL,
            state TEXT NOT NULL CHECK (state IN ({_in_list(JOB_STATES)})),
            steps TEXT NOT NULL,
            options_json TEXT NOT NULL,
            progress REAL NOT NULL CHECK (progress >= 0 AND progress <= 1),
            claimed_by TEXT,
            heartbeat_utc TEXT,
            error TEXT,
            result_dir TEXT
        )""",
        "CREATE INDEX jobs_state_seq ON jobs (state, seq)",
        "CREATE INDEX jobs_run ON jobs (run_id)",
    ),
    # 2: a job's result files by kind, a note for people (why it waits, what it did),
    # and the time before which a job put back in the queue is not claimed again.
    (
        "ALTER TABLE jobs ADD COLUMN artifacts_json TEXT NOT NULL DEFAULT '{}'",
        "ALTER TABLE jobs ADD COLUMN message TEXT",
        "ALTER TABLE jobs ADD COLUMN not_before_utc TEXT",
    ),
)
assert len(_MIGRATIONS) == SCHEMA_VERSION

_RUN_COLUMNS = (
    "id, created_utc, updated_utc, state, preset, path, n_positions, positions_done, current_position, "
    "exposures_per_position, started_utc, finished_utc, last_error, request_json, seconds_per_position"
)
_JOB_COLUMNS = (
    "id, run_id, created_utc, updated_utc, state, steps, options_json, progress, claimed_by, heartbeat_utc, "
    "error, result_dir, artifacts_json, message, not_before_utc"
)


# --- helpers ---------------------------------------------------------------------------
def _fmt(t: datetime) -> str:
    return t.strftime(_TIME_FORMAT)


def _parse(text: str | None) -> datetime | None:
    return None if text is None else datetime.strptime(text, _TIME_FORMAT).replace(tzinfo=UTC)


def _to_json(value: dict, what: str) -> str:
    if not isinstance(value, dict):
        raise CatalogError(f"{what} must be a JSON object (a dict), not {type(value).__name__}")
    try:
        return json.dumps(value, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise CatalogError(f"{what} is not plain JSON: {exc}") from None


def _check_int(name: str, value, lo: int, hi: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise CatalogError(f"{name} must be an integer, not {value!r}")
    if value < lo or (hi is not None and value > hi):
        bounds = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        raise CatalogError(f"{name} must be {bounds}, not {value}")
    return value


def _check_real(name: str, value, lo: float, hi: float | None = None) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise CatalogError(f"{name} must be a finite number, not {value!r}")
    if value < lo or (hi is not None and value > hi):
        bounds = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        raise CatalogError(f"{name} must be {bounds}, not {value}")
    return float(value)


def _check_text(name: str, value) -> str:
    if not isinstance(value, str) or not value.strip() or "\n" in value:
        raise CatalogError(f"{name} must be a non-empty one-line string, not {value!r}")
    return value


def _normalise_steps(steps) -> str:
    if not isinstance(steps, str):
        raise CatalogError(f"steps must be a comma-separated string such as 'hdr,sources', not {steps!r}")
    names = [s.strip() for s in steps.split(",")]
    for name in names:
        if not _STEP_NAME.match(name):
            raise CatalogError(f"steps {steps!r}: {name!r} is not a step name (lowercase letters, digits, _)")
    if len(set(names)) != len(names):
        raise CatalogError(f"steps {steps!r} names a step twice")
    return ",".join(names)


def _run_from_row(row: sqlite3.Row) -> RunRecord:
    return RunRecord(
        id=row["id"],
        created_utc=_parse(row["created_utc"]),
        updated_utc=_parse(row["updated_utc"]),
        state=row["state"],
        preset=row["preset"],
        path=row["path"],
        n_positions=row["n_positions"],
        positions_done=row["positions_done"],
        current_position=row["current_position"],
        exposures_per_position=row["exposures_per_position"],
        started_utc=_parse(row["started_utc"]),
        finished_utc=_parse(row["finished_utc"]),
        last_error=row["last_error"],
        request=json.loads(row["request_json"]),
        seconds_per_position=row["seconds_per_position"],
    )


def _job_from_row(row: sqlite3.Row) -> JobRecord:
    return JobRecord(
        id=row["id"],
        run_id=row["run_id"],
        created_utc=_parse(row["created_utc"]),
        updated_utc=_parse(row["updated_utc"]),
        state=row["state"],
        steps=row["steps"],
        options=json.loads(row["options_json"]),
        progress=row["progress"],
        claimed_by=row["claimed_by"],
        heartbeat_utc=_parse(row["heartbeat_utc"]),
        error=row["error"],
        result_dir=row["result_dir"],
        artifacts=json.loads(row["artifacts_json"]),
        message=row["message"],
        not_before_utc=_parse(row["not_before_utc"]),
    )


def _utc_now() -> datetime:
    return datetime.now(UTC)


# --- the catalog -----------------------------------------------------------------------
class Catalog:
    """The catalog of runs and processing jobs in one SQLite file.

    Parameters
    ----------
    path : str or Path
        The database file (``DATA_DIR/catalog.sqlite``); created with its schema if
        missing, migrated if older. Its folder must exist. ``":memory:"`` gives a
        private in-memory catalog (tests).
    clock : callable, optional
        Returns the current time as a timezone-aware ``datetime`` (UTC by default);
        tests inject one they advance by hand.
    busy_timeout_s : float, optional
        How long a write waits for another process holding the write lock before
        ``sqlite3.OperationalError: database is locked``.

    Raises
    ------
    CatalogError
        The file cannot be opened as a catalog, or its schema is newer than this program's.

    Notes
    -----
    One connection per :class:`Catalog`, shared by the threads of the process under a
    lock (``check_same_thread=False``). Every operation is a few indexed statements that
    take well under a millisecond, at a rate of a few per position or per HTTP poll, so
    serialising them costs nothing, whereas a connection per thread would leave one open
    connection behind for every thread of the web server's pool. Within a process the
    lock also means that threads never compete for SQLite's write lock, so "database is
    locked" can only come from another process, which ``busy_timeout`` and
    ``BEGIN IMMEDIATE`` handle. Other processes (workers) open their own
    :class:`Catalog`; one opened before a ``fork`` refuses to be used in the child.
    """

    def __init__(
        self,
        path: str | Path,
        clock: Callable[[], datetime] = _utc_now,
        *,
        busy_timeout_s: float = 10.0,
    ):
        self.path = str(path)
        self._clock = clock
        self._lock = threading.RLock()
        self._pid = os.getpid()
        busy_timeout_s = _check_real("busy_timeout_s", busy_timeout_s, 0.0)
        try:
            conn = sqlite3.connect(self.path, timeout=busy_timeout_s, isolation_level=None, check_same_thread=False)
        except sqlite3.Error as exc:
            raise CatalogError(f"cannot open catalog {self.path}: {exc}") from None
        conn.row_factory = sqlite3.Row
        self._conn: sqlite3.Connection | None = conn
        try:
            conn.execute(f"PRAGMA busy_timeout = {int(busy_timeout_s * 1000)}")
            mode = conn.execute("PRAGMA journal_mode = WAL").fetchone()[0]
            if mode.lower() not in ("wal", "memory"):
                raise CatalogError(f"cannot open catalog {self.path}: journal mode is {mode}, not wal")
            conn.execute("PRAGMA foreign_keys = ON")
            self._migrate()
        except sqlite3.Error as exc:
            conn.close()
            self._conn = None
            raise CatalogError(f"cannot open catalog {self.path}: {exc}") from None
        except BaseException:
            conn.close()
            self._conn = None
            raise

    # --- plumbing ------------------------------------------------------------------
    def __repr__(self) -> str:
        return f"Catalog({self.path!r})"

    def __enter__(self) -> Catalog:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Close the connection; the catalog cannot be used afterwards. Idempotent."""
        with self._lock:
            if self._conn is not None and os.getpid() == self._pid:
                self._conn.close()
            self._conn = None

    def _connection(self) -> sqlite3.Connection:
        if os.getpid() != self._pid:
            raise CatalogError(
                f"catalog {self.path} was opened in process {self._pid}: open a new Catalog in process {os.getpid()}"
            )
        if self._conn is None:
            raise CatalogError(f"catalog {self.path} is closed")
        return self._conn

    @contextmanager
    def _read(self) -> Iterator[sqlite3.Connection]:
        with self._lock:
            yield self._connection()

    @contextmanager
    def _write(self) -> Iterator[sqlite3.Connection]:
        """One write transaction, holding SQLite's write lock from its start."""
        with self._lock:
            conn = self._connection()
            conn.execute("BEGIN IMMEDIATE")
            try:
                yield conn
            except BaseException:
                if conn.in_transaction:  # SQLite may already have rolled back (disk full, I/O error)
                    conn.execute("ROLLBACK")
                raise
            conn.execute("COMMIT")

    def _now(self) -> datetime:
        now = self._clock()
        if not isinstance(now, datetime) or now.tzinfo is None or now.utcoffset() is None:
            raise CatalogError(f"the catalog's clock must return a timezone-aware datetime, not {now!r}")
        return now.astimezone(UTC)

    def _migrate(self) -> None:
        with self._write() as conn:
            conn.execute(
                "CREATE TABLE IF NOT EXISTS schema_version (version INTEGER PRIMARY KEY, applied_utc TEXT NOT NULL)"
            )
            version = conn.execute("SELECT MAX(version) FROM schema_version").fetchone()[0] or 0
            if version > SCHEMA_VERSION:
                raise CatalogError(
                    f"catalog {self.path} has schema version {version}, newer than this program's {SCHEMA_VERSION}"
                )
            stamp = _fmt(self._now())
            for number in range(version + 1, SCHEMA_VERSION + 1):
                for statement in _MIGRATIONS[number - 1]:
                    conn.execute(statement)
                conn.execute("INSERT INTO schema_version (version, applied_utc) VALUES (?, ?)", (number, stamp))

    @staticmethod
    def _new_id(conn: sqlite3.Connection, table: str, prefix: str, now: datetime) -> str:
        while True:
            candidate = f"{prefix}-{now:%Y%m%d-%H%M%S}-{secrets.token_hex(2)}"
            if conn.execute(f"SELECT 1 FROM {table} WHERE id = ?", (candidate,)).fetchone() is None:
                return candidate

    @staticmethod
    def _next_seq(conn: sqlite3.Connection, table: str) -> int:
        return conn.execute(f"SELECT COALESCE(MAX(seq), 0) + 1 FROM {table}").fetchone()[0]

    @staticmethod
    def _other_active(conn: sqlite3.Connection, run_id: str | None) -> sqlite3.Row | None:
        """The active run other than ``run_id`` (any active run if None)."""
        return conn.execute(
            f"SELECT id, state FROM runs WHERE state IN ({_in_list(ACTIVE_RUN_STATES)}) AND id <> ? "
            "ORDER BY seq DESC LIMIT 1",
            ("" if run_id is None else run_id,),
        ).fetchone()

    @staticmethod
    def _fetch_run(conn: sqlite3.Connection, run_id: str) -> RunRecord:
        row = conn.execute(f"SELECT {_RUN_COLUMNS} FROM runs WHERE id = ?", (run_id,)).fetchone()
        if row is None:
            raise UnknownRunError(run_id)
        return _run_from_row(row)

    @staticmethod
    def _fetch_job(conn: sqlite3.Connection, job_id: str) -> JobRecord:
        row = conn.execute(f"SELECT {_JOB_COLUMNS} FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None:
            raise UnknownJobError(job_id)
        return _job_from_row(row)

    # --- runs ----------------------------------------------------------------------
    def create_run(
        self,
        *,
        preset: str | None,
        path_for: Callable[[str], str | Path] | None,
        n_positions: int,
        request: dict,
    ) -> RunRecord:
        """Add a new run in state ``queued``.

        Parameters
        ----------
        preset : str or None
            Name of the preset the run was made from.
        path_for : callable or None
            Given the new run's id, returns the path of its run file (stored as text);
            called inside the write transaction. None: no path yet.
        n_positions : int
            Number of positions in the run's schedule (at least 1).
        request : dict
            The run request as the client sent it; stored as JSON.

        Returns
        -------
        RunRecord
            The new run, with an id such as ``run-20261121-134501-3f2a``.

        Raises
        ------
        ActiveRunError
            Another run is queued, running or paused.
        CatalogError
            A bad argument.
        """
        if preset is not None:
            _check_text("preset", preset)
        n_positions = _check_int("n_positions", n_positions, 1)
        request_json = _to_json(request, "the run request")
        with self._write() as conn:
            active = self._other_active(conn, None)
            if active is not None:
                raise ActiveRunError(active["id"], active["state"], "create a run")
            now = self._now()
            run_id = self._new_id(conn, "runs", "run", now)
            path = None if path_for is None else str(path_for(run_id))
            stamp = _fmt(now)
            conn.execute(
                "INSERT INTO runs (id, seq, created_utc, updated_utc, state, preset, path, n_positions, "
                "positions_done, request_json) VALUES (?, ?, ?, ?, 'queued', ?, ?, ?, 0, ?)",
                (run_id, self._next_seq(conn, "runs"), stamp, stamp, preset, path, n_positions, request_json),
            )
            return self._fetch_run(conn, run_id)

    def get_run(self, run_id: str) -> RunRecord:
        """The run with this id.

        Raises
        ------
        UnknownRunError
            No run has this id.
        """
        with self._read() as conn:
            return self._fetch_run(conn, run_id)

    def list_runs(self, limit: int = 100, state: str | None = None) -> list[RunRecord]:
        """The newest runs first, at most ``limit`` of them, only those in ``state`` if given."""
        limit = _check_int("limit", limit, 1)
        if state is not None and state not in RUN_STATES:
            raise CatalogError(f"unknown run state {state!r} (one of: {', '.join(RUN_STATES)})")
        where, params = ("WHERE state = ? ", (state, limit)) if state is not None else ("", (limit,))
        with self._read() as conn:
            rows = conn.execute(f"SELECT {_RUN_COLUMNS} FROM runs {where}ORDER BY seq DESC LIMIT ?", params)
            return [_run_from_row(row) for row in rows]

    def transition_run(self, run_id: str, new_state: str, *, error: str | None = None) -> RunRecord:
        """Move a run to ``new_state`` if :data:`ALLOWED_RUN_TRANSITIONS` allows it.

        The check and the change are one statement (``UPDATE ... WHERE state IN ...``): of
        two callers racing from the same state, exactly one wins. Entering ``running``
        sets ``started_utc`` the first time and clears ``finished_utc``; entering
        ``complete``, ``aborted`` or ``failed`` sets ``finished_utc``.

        Parameters
        ----------
        run_id : str
            The run.
        new_state : str
            One of :data:`RUN_STATES`.
        error : str, optional
            Stored as the run's ``last_error`` (kept otherwise, so that a resumed run still
            shows what stopped it).

        Returns
        -------
        RunRecord
            The run after the change.

        Raises
        ------
        UnknownRunError
            No run has this id.
        InvalidTransitionError
            The run's current state does not allow ``new_state``.
        ActiveRunError
            Resuming this run while another one is queued, running or paused.
        """
        if new_state not in RUN_STATES:
            raise CatalogError(f"{run_id}: unknown run state {new_state!r} (one of: {', '.join(RUN_STATES)})")
        if error is not None:
            _check_text("error", error)
        sources = [s for s, targets in ALLOWED_RUN_TRANSITIONS.items() if new_state in targets]
        with self._write() as conn:
            if new_state in ACTIVE_RUN_STATES:
                active = self._other_active(conn, run_id)
                if active is not None:
                    raise ActiveRunError(active["id"], active["state"], f"make {run_id} {new_state}")
            stamp = _fmt(self._now())
            if new_state == "running":
                finished = "NULL"
            elif new_state in _FINISHING_RUN_STATES:
                finished = ":now"
            else:
                finished = "finished_utc"
            started = "COALESCE(started_utc, :now)" if new_state == "running" else "started_utc"
            changed = conn.execute(
                f"UPDATE runs SET state = :new, updated_utc = :now, started_utc = {started}, "
                f"finished_utc = {finished}, last_error = COALESCE(:error, last_error) "
                f"WHERE id = :id AND state IN ({_in_list(sources) or 'NULL'})",
                {"new": new_state, "now": stamp, "error": error, "id": run_id},
            ).rowcount
            if changed == 0:
                current = self._fetch_run(conn, run_id).state
                raise InvalidTransitionError(run_id, current, new_state, ALLOWED_RUN_TRANSITIONS[current])
            return self._fetch_run(conn, run_id)

    def update_progress(
        self,
        run_id: str,
        *,
        positions_done: int,
        current_position: int | None,
        seconds_per_position: float | None = None,
        exposures_per_position: int | None = None,
    ) -> None:
        """Record a run's progress (accepted in any state: a late report is still true).

        Parameters
        ----------
        run_id : str
            The run.
        positions_done : int
            Positions finished so far, in ``[0, n_positions]``.
        current_position : int or None
            Index of the position being worked on, in ``[0, n_positions)``; None between
            positions or at the end.
        seconds_per_position : float, optional
            The caller's moving average of the time per position, for the ETA; None
            leaves the stored value unchanged.
        exposures_per_position : int, optional
            Exposures taken at each position; None leaves the stored value unchanged.

        Raises
        ------
        UnknownRunError
            No run has this id.
        CatalogError
            A value out of range for this run.
        """
        _check_int("positions_done", positions_done, 0)
        if current_position is not None:
            _check_int("current_position", current_position, 0)
        if seconds_per_position is not None:
            seconds_per_position = _check_real("seconds_per_position", seconds_per_position, 0.0)
        if exposures_per_position is not None:
            _check_int("exposures_per_position", exposures_per_position, 1)
        with self._write() as conn:
            row = conn.execute("SELECT n_positions FROM runs WHERE id = ?", (run_id,)).fetchone()
            if row is None:
                raise UnknownRunError(run_id)
            n = row["n_positions"]
            if positions_done > n:
                raise CatalogError(f"{run_id}: positions_done {positions_done} > n_positions {n}")
            if current_position is not None and current_position >= n:
                raise CatalogError(f"{run_id}: current_position {current_position} >= n_positions {n}")
            conn.execute(
                "UPDATE runs SET positions_done = ?, current_position = ?, "
                "seconds_per_position = COALESCE(?, seconds_per_position), "
                "exposures_per_position = COALESCE(?, exposures_per_position), updated_utc = ? WHERE id = ?",
                (
                    positions_done,
                    current_position,
                    seconds_per_position,
                    exposures_per_position,
                    _fmt(self._now()),
                    run_id,
                ),
            )

    def active_run(self) -> RunRecord | None:
        """The run that is queued, running or paused, if any (one run at a time per rig)."""
        with self._read() as conn:
            row = conn.execute(
                f"SELECT {_RUN_COLUMNS} FROM runs WHERE state IN ({_in_list(ACTIVE_RUN_STATES)}) "
                "ORDER BY seq DESC LIMIT 1"
            ).fetchone()
            return None if row is None else _run_from_row(row)

    def mark_interrupted(self) -> list[str]:
        """At daemon start: every run left queued, running or paused becomes ``interrupted``.

        Returns
        -------
        list of str
            The ids of those runs, oldest first.
        """
        with self._write() as conn:
            ids = [
                row["id"]
                for row in conn.execute(
                    f"SELECT id FROM runs WHERE state IN ({_in_list(ACTIVE_RUN_STATES)}) ORDER BY seq"
                )
            ]
            conn.execute(
                f"UPDATE runs SET state = 'interrupted', updated_utc = ? "
                f"WHERE state IN ({_in_list(ACTIVE_RUN_STATES)})",
                (_fmt(self._now()),),
            )
            return ids

    # --- jobs ----------------------------------------------------------------------
    def create_job(self, run_id: str, *, steps: str = "hdr,sources", options: dict | None = None) -> JobRecord:
        """Queue a processing job for a run.

        Parameters
        ----------
        run_id : str
            The run to process (in any state: a partial run can be processed too).
        steps : str
            Comma-separated step names, in order.
        options : dict, optional
            Options for the steps; stored as JSON.

        Returns
        -------
        JobRecord
            The new job, state ``queued``, with an id such as ``job-20261121-134501-a9c0``.

        Raises
        ------
        UnknownRunError
            No run has this id.
        """
        steps = _normalise_steps(steps)
        options_json = _to_json({} if options is None else options, "the job options")
        with self._write() as conn:
            if conn.execute("SELECT 1 FROM runs WHERE id = ?", (run_id,)).fetchone() is None:
                raise UnknownRunError(run_id)
            now = self._now()
            job_id = self._new_id(conn, "jobs", "job", now)
            stamp = _fmt(now)
            conn.execute(
                "INSERT INTO jobs (id, seq, run_id, created_utc, updated_utc, state, steps, options_json, progress) "
                "VALUES (?, ?, ?, ?, ?, 'queued', ?, ?, 0)",
                (job_id, self._next_seq(conn, "jobs"), run_id, stamp, stamp, steps, options_json),
            )
            return self._fetch_job(conn, job_id)

    def get_job(self, job_id: str) -> JobRecord:
        """The job with this id.

        Raises
        ------
        UnknownJobError
            No job has this id.
        """
        with self._read() as conn:
            return self._fetch_job(conn, job_id)

    def list_jobs(self, run_id: str | None = None, limit: int = 100) -> list[JobRecord]:
        """The newest jobs first, at most ``limit``, only those of ``run_id`` if given.

        Raises
        ------
        UnknownRunError
            ``run_id`` is given and no run has it.
        """
        limit = _check_int("limit", limit, 1)
        with self._read() as conn:
            if run_id is None:
                rows = conn.execute(f"SELECT {_JOB_COLUMNS} FROM jobs ORDER BY seq DESC LIMIT ?", (limit,))
            else:
                if conn.execute("SELECT 1 FROM runs WHERE id = ?", (run_id,)).fetchone() is None:
                    raise UnknownRunError(run_id)
                rows = conn.execute(
                    f"SELECT {_JOB_COLUMNS} FROM jobs WHERE run_id = ? ORDER BY seq DESC LIMIT ?", (run_id, limit)
                )
            return [_job_from_row(row) for row in rows]

    def claim_job(self, worker_id: str) -> JobRecord | None:
        """Take the oldest queued job that may run now: it becomes ``running``, claimed by ``worker_id``.

        Atomic across threads and processes (one ``BEGIN IMMEDIATE`` transaction): two
        workers never get the same job. Progress restarts at 0 and the heartbeat at now.
        A job put back with :meth:`release_job` is skipped until its ``not_before_utc``,
        so that it does not hold up the jobs queued after it.

        Returns
        -------
        JobRecord or None
            The claimed job, or None when no job is queued (or all wait).
        """
        _check_text("worker_id", worker_id)
        with self._write() as conn:
            stamp = _fmt(self._now())
            row = conn.execute(
                "SELECT id FROM jobs WHERE state = 'queued' AND (not_before_utc IS NULL OR not_before_utc <= ?) "
                "ORDER BY seq LIMIT 1",
                (stamp,),
            ).fetchone()
            if row is None:
                return None
            conn.execute(
                "UPDATE jobs SET state = 'running', claimed_by = ?, heartbeat_utc = ?, updated_utc = ?, "
                "progress = 0, error = NULL, not_before_utc = NULL WHERE id = ? AND state = 'queued'",
                (worker_id, stamp, stamp, row["id"]),
            )
            return self._fetch_job(conn, row["id"])

    def release_job(self, job_id: str, worker_id: str, *, message: str, retry_after_s: float = 0.0) -> JobRecord:
        """Put a running job back in the queue, untouched, to be claimed again later.

        For a job that cannot run yet (its run is still being acquired): it goes back to
        ``queued`` with ``message`` saying why, and no worker claims it before
        ``retry_after_s`` have passed.

        Raises
        ------
        UnknownJobError
            No job has this id.
        InvalidTransitionError
            The job is not running.
        JobClaimError
            Another worker holds the job.
        """
        _check_text("worker_id", worker_id)
        _check_text("message", message)
        retry_after_s = _check_real("retry_after_s", retry_after_s, 0.0)
        with self._write() as conn:
            now = self._now()
            changed = conn.execute(
                "UPDATE jobs SET state = 'queued', claimed_by = NULL, heartbeat_utc = NULL, progress = 0, "
                "message = ?, not_before_utc = ?, updated_utc = ? WHERE id = ? AND state = 'running' AND "
                "claimed_by = ?",
                (message, _fmt(now + timedelta(seconds=retry_after_s)), _fmt(now), job_id, worker_id),
            ).rowcount
            if changed == 0:
                job = self._fetch_job(conn, job_id)
                if job.state != "running":
                    raise InvalidTransitionError(job_id, job.state, "queued", ALLOWED_JOB_TRANSITIONS[job.state])
                raise JobClaimError(job_id, worker_id, job.state, job.claimed_by)
            return self._fetch_job(conn, job_id)

    def heartbeat(self, job_id: str, worker_id: str, progress: float | None = None, message: str | None = None) -> None:
        """A worker's proof of life on its running job, with its progress (0..1) and a note if given.

        Raises
        ------
        UnknownJobError
            No job has this id.
        JobClaimError
            The job is not running under ``worker_id`` (it was requeued as stale, perhaps
            claimed again by another worker, or finished): this worker should stop.
        """
        _check_text("worker_id", worker_id)
        if progress is not None:
            progress = _check_real("progress", progress, 0.0, 1.0)
        if message is not None:
            _check_text("message", message)
        with self._write() as conn:
            stamp = _fmt(self._now())
            changed = conn.execute(
                "UPDATE jobs SET heartbeat_utc = ?, updated_utc = ?, progress = COALESCE(?, progress), "
                "message = COALESCE(?, message) WHERE id = ? AND state = 'running' AND claimed_by = ?",
                (stamp, stamp, progress, message, job_id, worker_id),
            ).rowcount
            if changed == 0:
                job = self._fetch_job(conn, job_id)
                raise JobClaimError(job_id, worker_id, job.state, job.claimed_by)

    def finish_job(
        self,
        job_id: str,
        *,
        error: str | None = None,
        result_dir: str | Path | None = None,
        worker_id: str | None = None,
        artifacts: dict[str, str | Path] | None = None,
        message: str | None = None,
    ) -> JobRecord:
        """End a running job: ``complete`` (progress 1) without ``error``, ``failed`` with one.

        Parameters
        ----------
        job_id : str
            The job.
        error : str, optional
            Why it failed; its presence makes the job ``failed``.
        result_dir : str or Path, optional
            Where its results are.
        artifacts : dict, optional
            Its result files by kind (``report``, ``ies``, ``tm25``, ...): the files the
            daemon may serve for it.
        message : str, optional
            A note for people (replaces the last one).
        worker_id : str, optional
            If given, the job must be claimed by this worker (a worker whose job was
            requeued and claimed by another then cannot finish it).

        Returns
        -------
        JobRecord
            The job after the change.

        Raises
        ------
        UnknownJobError
            No job has this id.
        InvalidTransitionError
            The job is not running.
        JobClaimError
            ``worker_id`` is given and another worker holds the job.
        """
        if error is not None:
            _check_text("error", error)
        if worker_id is not None:
            _check_text("worker_id", worker_id)
        if message is not None:
            _check_text("message", message)
        files = None
        if artifacts is not None:
            if not isinstance(artifacts, dict) or not all(
                isinstance(k, str) and _STEP_NAME.match(k) for k in artifacts
            ):
                raise CatalogError(f"{job_id}: artifacts must map kinds (lowercase names) to file paths")
            files = _to_json({kind: str(path) for kind, path in artifacts.items()}, "the job artifacts")
        new_state = "complete" if error is None else "failed"
        with self._write() as conn:
            changed = conn.execute(
                "UPDATE jobs SET state = ?, error = ?, result_dir = COALESCE(?, result_dir), updated_utc = ?, "
                "progress = CASE WHEN ? = 'complete' THEN 1.0 ELSE progress END, "
                "artifacts_json = COALESCE(?, artifacts_json), message = COALESCE(?, message) "
                "WHERE id = ? AND state = 'running' AND (? IS NULL OR claimed_by = ?)",
                (
                    new_state,
                    error,
                    None if result_dir is None else str(result_dir),
                    _fmt(self._now()),
                    new_state,
                    files,
                    message,
                    job_id,
                    worker_id,
                    worker_id,
                ),
            ).rowcount
            if changed == 0:
                job = self._fetch_job(conn, job_id)
                if job.state != "running":
                    raise InvalidTransitionError(job_id, job.state, new_state, ALLOWED_JOB_TRANSITIONS[job.state])
                raise JobClaimError(job_id, worker_id, job.state, job.claimed_by)
            return self._fetch_job(conn, job_id)

    def requeue_stale_jobs(self, older_than_s: float) -> list[str]:
        """Running jobs without a heartbeat for more than ``older_than_s`` go back to ``queued``.

        Their worker is taken for dead: the claim is cleared and the next
        :meth:`claim_job` starts the job over.

        Returns
        -------
        list of str
            The ids of the requeued jobs, oldest first.
        """
        older_than_s = _check_real("older_than_s", older_than_s, 0.0)
        with self._write() as conn:
            now = self._now()
            cutoff = _fmt(now - timedelta(seconds=older_than_s))
            stale = "state = 'running' AND (heartbeat_utc IS NULL OR heartbeat_utc < ?)"
            ids = [row["id"] for row in conn.execute(f"SELECT id FROM jobs WHERE {stale} ORDER BY seq", (cutoff,))]
            conn.execute(
                f"UPDATE jobs SET state = 'queued', claimed_by = NULL, heartbeat_utc = NULL, updated_utc = ?, "
                f"message = 'requeued: its worker stopped sending heartbeats' WHERE {stale}",
                (_fmt(now), cutoff),
            )
            return ids
