"""The catalog's tables, as migrations from one schema version to the next."""

from __future__ import annotations

from collections.abc import Iterable

from acquisition.daemon.catalog.backends import Dialects
from acquisition.daemon.catalog.records import DEFAULT_RIG, JOB_STATES, RUN_STATES

SCHEMA_VERSION = 5


def sql_list(states: Iterable[str]) -> str:
    """States as the list of an SQL ``IN (...)``: ``'queued', 'running'``."""
    return ", ".join(f"'{s}'" for s in states)


# One tuple of statements per schema version; version N is MIGRATIONS[N - 1]. Never change
# what a released entry does: append a new one. A statement is SQL both databases run, or
# :class:`Dialects` where they differ. ``seq`` orders rows (newest first, oldest queued job
# first) even when two share a timestamp: MAX(seq) + 1 taken under SQLite's write lock, a
# sequence on PostgreSQL. ``DOUBLE PRECISION`` is SQLite's REAL (the same affinity) and
# PostgreSQL's 8-byte float (its REAL has 4).
MIGRATIONS: tuple[tuple[str | Dialects, ...], ...] = (
    (
        f"""CREATE TABLE runs (
            id TEXT PRIMARY KEY,
            seq INTEGER NOT NULL UNIQUE,
            created_utc TEXT NOT NULL,
            updated_utc TEXT NOT NULL,
            state TEXT NOT NULL CHECK (state IN ({sql_list(RUN_STATES)})),
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
            seconds_per_position DOUBLE PRECISION
        )""",
        "CREATE INDEX runs_state ON runs (state)",
        f"""CREATE TABLE jobs (
            id TEXT PRIMARY KEY,
            seq INTEGER NOT NULL UNIQUE,
            run_id TEXT NOT NULL REFERENCES runs (id),
            created_utc TEXT NOT NULL,
            updated_utc TEXT NOT NULL,
            state TEXT NOT NULL CHECK (state IN ({sql_list(JOB_STATES)})),
            steps TEXT NOT NULL,
            options_json TEXT NOT NULL,
            progress DOUBLE PRECISION NOT NULL CHECK (progress >= 0 AND progress <= 1),
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
    # 3: the step a running job's processing is in (processing.light_run.progress.STEPS),
    # kept when it fails (the step it failed in).
    ("ALTER TABLE jobs ADD COLUMN step TEXT",),
    # 4: the queue of runs: a queued run's place (ascending; the rank is its position), and
    # the queue's one row: why it is held (NULL: it runs on), and since when.
    (
        "ALTER TABLE runs ADD COLUMN queue_order INTEGER",
        "UPDATE runs SET queue_order = seq WHERE state = 'queued'",
        "CREATE TABLE run_queue (id INTEGER PRIMARY KEY CHECK (id = 1), held TEXT, held_utc TEXT)",
        "INSERT INTO run_queue (id) VALUES (1)",
    ),
    # 5: several rigs in one catalog: each run and job names its rig (those before, the
    # default one); each rig has a row with its queue's hold and where its daemon answers
    # (workers on other machines fetch run files from it); on PostgreSQL, seq from sequences.
    (
        f"ALTER TABLE runs ADD COLUMN rig TEXT NOT NULL DEFAULT '{DEFAULT_RIG}'",
        f"ALTER TABLE jobs ADD COLUMN rig TEXT NOT NULL DEFAULT '{DEFAULT_RIG}'",
        "CREATE INDEX runs_rig_state ON runs (rig, state)",
        "CREATE INDEX jobs_rig_seq ON jobs (rig, seq)",
        "CREATE TABLE rigs (rig TEXT PRIMARY KEY, held TEXT, held_utc TEXT, daemon_url TEXT, daemon_seen_utc TEXT)",
        f"INSERT INTO rigs (rig, held, held_utc) SELECT '{DEFAULT_RIG}', held, held_utc FROM run_queue",
        "DROP TABLE run_queue",
        *(
            statement
            for table in ("runs", "jobs")
            for statement in (
                Dialects(None, f"CREATE SEQUENCE {table}_seq"),
                Dialects(None, f"SELECT setval('{table}_seq', COALESCE((SELECT MAX(seq) FROM {table}), 0) + 1, false)"),
            )
        ),
    ),
)
assert len(MIGRATIONS) == SCHEMA_VERSION

#: The columns a run's record is built from (selected ``FROM runs``, unaliased: a queued run's
#: place in the queue is its rank among the queued runs), and a job's.
RUN_COLUMNS = (
    "id, rig, created_utc, updated_utc, state, preset, path, n_positions, positions_done, current_position, "
    "exposures_per_position, started_utc, finished_utc, last_error, request_json, seconds_per_position, "
    "CASE WHEN state = 'queued' THEN (SELECT COUNT(*) FROM runs AS ahead WHERE ahead.state = 'queued' "
    "AND ahead.rig = runs.rig AND ahead.queue_order <= runs.queue_order) END AS queue_position"
)
JOB_COLUMNS = (
    "id, run_id, rig, created_utc, updated_utc, state, steps, options_json, progress, claimed_by, heartbeat_utc, "
    "error, result_dir, artifacts_json, message, not_before_utc, step"
)
