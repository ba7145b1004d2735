"""The processing jobs in the catalog: queued, claimed by a worker, kept alive, finished."""

from __future__ import annotations

import re
from collections.abc import Sequence
from datetime import timedelta
from pathlib import Path

from acquisition.daemon.catalog.backends import Connection
from acquisition.daemon.catalog.database import (
    CatalogDatabase,
    check_int,
    check_real,
    check_rig,
    check_text,
    to_json,
)
from acquisition.daemon.catalog.errors import (
    CatalogError,
    InvalidTransitionError,
    JobClaimError,
    OtherRigError,
    UnknownJobError,
    UnknownRunError,
)
from acquisition.daemon.catalog.records import ALLOWED_JOB_TRANSITIONS, JobRecord, format_time, job_from_row
from acquisition.daemon.catalog.schema import JOB_COLUMNS

_STEP_NAME = re.compile(r"[a-z][a-z0-9_]*\Z")


def _normalise_steps(steps: object) -> str:
    """A job's comma-separated step names, stripped; a CatalogError for a bad or repeated name."""
    if not isinstance(steps, str):
        raise CatalogError(f"steps must be a comma-separated string such as 'hdr,sources', not {steps!r}")
    names = [s.strip() for s in steps.split(",")]
    for name in names:
        if not _STEP_NAME.match(name):
            raise CatalogError(f"steps {steps!r}: {name!r} is not a step name (lowercase letters, digits, _)")
    if len(set(names)) != len(names):
        raise CatalogError(f"steps {steps!r} names a step twice")
    return ",".join(names)


def _artifacts_json(job_id: str, artifacts: object) -> str:
    """A job's result files by kind, as stored; a CatalogError unless the kinds are lowercase names."""
    if not isinstance(artifacts, dict) or not all(isinstance(k, str) and _STEP_NAME.match(k) for k in artifacts):
        raise CatalogError(f"{job_id}: artifacts must map kinds (lowercase names) to file paths")
    return to_json({kind: str(path) for kind, path in artifacts.items()}, "the job artifacts")


class JobCatalog(CatalogDatabase):
    """The catalog's processing jobs (see :class:`acquisition.daemon.catalog.Catalog`)."""

    @staticmethod
    def _fetch_job(conn: Connection, job_id: str) -> JobRecord:
        row = conn.execute(f"SELECT {JOB_COLUMNS} FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None:
            raise UnknownJobError(job_id)
        return job_from_row(row)

    def create_job(self, run_id: str, *, steps: str = "hdr,sources", options: dict | None = None) -> JobRecord:
        """Queue a processing job for a run.

        Parameters
        ----------
        run_id : str
            The run to process (in any state: a partial run can be processed too), one of
            this rig's.
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
        OtherRigError
            The run is another rig's.
        """
        steps = _normalise_steps(steps)
        options_json = to_json({} if options is None else options, "the job options")
        with self._write() as conn:
            row = conn.execute("SELECT rig FROM runs WHERE id = ?", (run_id,)).fetchone()
            if row is None:
                raise UnknownRunError(run_id)
            if row["rig"] != self.rig:
                raise OtherRigError(run_id, row["rig"], self.rig, "queue a job for it")
            now = self._now()
            job_id = self._new_id(conn, "jobs", "job", now)
            stamp = format_time(now)
            conn.execute(
                "INSERT INTO jobs (id, seq, run_id, rig, created_utc, updated_utc, state, steps, options_json, "
                "progress) VALUES (?, ?, ?, ?, ?, ?, 'queued', ?, ?, 0)",
                (job_id, self._next_seq(conn, "jobs"), run_id, self.rig, stamp, stamp, steps, options_json),
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

    def list_jobs(self, run_id: str | None = None, limit: int = 100, *, rig: str | None = "") -> list[JobRecord]:
        """The newest jobs first, at most ``limit``, only those of ``run_id`` if given (of any rig),
        else of ``rig``: this rig (``""``, the default), another (its name), the whole lab (None).

        Raises
        ------
        UnknownRunError
            ``run_id`` is given and no run has it.
        """
        limit = check_int("limit", limit, 1)
        with self._read() as conn:
            if run_id is None and rig is None:
                rows = conn.execute(f"SELECT {JOB_COLUMNS} FROM jobs ORDER BY seq DESC LIMIT ?", (limit,))
            elif run_id is None:
                rows = conn.execute(
                    f"SELECT {JOB_COLUMNS} FROM jobs WHERE rig = ? ORDER BY seq DESC LIMIT ?",
                    (check_rig(rig) if rig else self.rig, limit),
                )
            else:
                if conn.execute("SELECT 1 FROM runs WHERE id = ?", (run_id,)).fetchone() is None:
                    raise UnknownRunError(run_id)
                rows = conn.execute(
                    f"SELECT {JOB_COLUMNS} FROM jobs WHERE run_id = ? ORDER BY seq DESC LIMIT ?", (run_id, limit)
                )
            return [job_from_row(row) for row in rows]

    def claim_job(self, worker_id: str, *, rigs: Sequence[str] | None = None) -> JobRecord | None:
        """Take the oldest queued job that may run now (of any rig, or of ``rigs`` if given): it
        becomes ``running``, claimed by ``worker_id``.

        Atomic across threads and processes: two workers never get the same job (SQLite: one
        ``BEGIN IMMEDIATE`` transaction; PostgreSQL: the row is locked by
        ``SELECT ... FOR UPDATE SKIP LOCKED``, so that concurrent claims take the next jobs
        instead of waiting). Progress restarts at 0 and the heartbeat at now.
        A job put back with :meth:`release_job` is skipped until its ``not_before_utc``,
        so that it does not hold up the jobs queued after it.

        Returns
        -------
        JobRecord or None
            The claimed job, or None when no job is queued (or all wait).
        """
        check_text("worker_id", worker_id)
        names = [check_rig(rig) for rig in rigs] if rigs is not None else []
        among = f" AND rig IN ({', '.join('?' * len(names))})" if rigs is not None else ""
        with self._write() as conn:
            stamp = format_time(self._now())
            row = conn.execute(
                "SELECT id FROM jobs WHERE state = 'queued' AND (not_before_utc IS NULL OR not_before_utc <= ?)"
                f"{among} ORDER BY seq LIMIT 1{self._open_backend().claim_lock}",
                (stamp, *names),
            ).fetchone()
            if row is None:
                return None
            conn.execute(
                "UPDATE jobs SET state = 'running', claimed_by = ?, heartbeat_utc = ?, updated_utc = ?, "
                "progress = 0, error = NULL, not_before_utc = NULL, step = NULL WHERE id = ? AND state = 'queued'",
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
        check_text("worker_id", worker_id)
        check_text("message", message)
        retry_after_s = check_real("retry_after_s", retry_after_s, 0.0)
        with self._write() as conn:
            now = self._now()
            changed = conn.execute(
                "UPDATE jobs SET state = 'queued', claimed_by = NULL, heartbeat_utc = NULL, progress = 0, step = NULL, "
                "message = ?, not_before_utc = ?, updated_utc = ? WHERE id = ? AND state = 'running' AND "
                "claimed_by = ?",
                (message, format_time(now + timedelta(seconds=retry_after_s)), format_time(now), job_id, worker_id),
            ).rowcount
            if changed == 0:
                job = self._fetch_job(conn, job_id)
                if job.state != "running":
                    raise InvalidTransitionError(job_id, job.state, "queued", ALLOWED_JOB_TRANSITIONS[job.state])
                raise JobClaimError(job_id, worker_id, job.state, job.claimed_by)
            return self._fetch_job(conn, job_id)

    def heartbeat(
        self,
        job_id: str,
        worker_id: str,
        progress: float | None = None,
        message: str | None = None,
        step: str | None = None,
    ) -> None:
        """A worker's proof of life on its running job, with its progress (0..1), a note and the
        processing's step (a name of ``processing.light_run.progress.STEPS``) if given.

        Raises
        ------
        UnknownJobError
            No job has this id.
        JobClaimError
            The job is not running under ``worker_id`` (it was requeued as stale, perhaps
            claimed again by another worker, or finished): this worker should stop.
        """
        check_text("worker_id", worker_id)
        if progress is not None:
            progress = check_real("progress", progress, 0.0, 1.0)
        if message is not None:
            check_text("message", message)
        if step is not None and not _STEP_NAME.match(step):
            raise CatalogError(f"step {step!r} is not a step name (lowercase letters, digits, _)")
        with self._write() as conn:
            stamp = format_time(self._now())
            changed = conn.execute(
                "UPDATE jobs SET heartbeat_utc = ?, updated_utc = ?, progress = COALESCE(?, progress), "
                "message = COALESCE(?, message), step = COALESCE(?, step) "
                "WHERE id = ? AND state = 'running' AND claimed_by = ?",
                (stamp, stamp, progress, message, step, job_id, worker_id),
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
            check_text("error", error)
        if worker_id is not None:
            check_text("worker_id", worker_id)
        if message is not None:
            check_text("message", message)
        files = None if artifacts is None else _artifacts_json(job_id, artifacts)
        new_state = "complete" if error is None else "failed"
        complete = new_state == "complete"
        held_by = (" AND claimed_by = ?", (worker_id,)) if worker_id is not None else ("", ())
        with self._write() as conn:
            changed = conn.execute(
                "UPDATE jobs SET state = ?, error = ?, result_dir = COALESCE(?, result_dir), updated_utc = ?, "
                f"progress = {'1.0' if complete else 'progress'}, step = {'NULL' if complete else 'step'}, "
                "artifacts_json = COALESCE(?, artifacts_json), message = COALESCE(?, message) "
                f"WHERE id = ? AND state = 'running'{held_by[0]}",
                (
                    new_state,
                    error,
                    None if result_dir is None else str(result_dir),
                    format_time(self._now()),
                    files,
                    message,
                    job_id,
                    *held_by[1],
                ),
            ).rowcount
            if changed == 0:
                job = self._fetch_job(conn, job_id)
                if job.state != "running":
                    raise InvalidTransitionError(job_id, job.state, new_state, ALLOWED_JOB_TRANSITIONS[job.state])
                assert worker_id is not None  # without a worker named, a running job always matches
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
        older_than_s = check_real("older_than_s", older_than_s, 0.0)
        with self._write() as conn:
            now = self._now()
            cutoff = format_time(now - timedelta(seconds=older_than_s))
            rows = conn.execute(
                "UPDATE jobs SET state = 'queued', claimed_by = NULL, heartbeat_utc = NULL, updated_utc = ?, "
                "step = NULL, message = 'requeued: its worker stopped sending heartbeats' "
                "WHERE state = 'running' AND (heartbeat_utc IS NULL OR heartbeat_utc < ?) RETURNING id, seq",
                (format_time(now), cutoff),
            )
            ids = [row["id"] for row in sorted(rows, key=lambda row: row["seq"])]
            return ids
