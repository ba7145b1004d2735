"""The queue of runs: the runs waiting in state ``queued``, in order, and whether the queue
is held (and why).

The order is each queued run's ``queue_order`` (ascending); its position, from 1, is its rank
among the queued runs (:data:`~acquisition.daemon.catalog.schema.RUN_COLUMNS`). The queue's hold is
a row of ``rigs`` per rig: its reason, or NULL (or no row) while the queue runs on. The daemon decides
when to hold and release it (``acquisition.daemon.engine``); the catalog keeps both across restarts.
"""

from __future__ import annotations

from datetime import datetime

from acquisition.daemon.catalog.database import CatalogDatabase, check_text
from acquisition.daemon.catalog.errors import CatalogError, NotQueuedError
from acquisition.daemon.catalog.records import RunRecord, format_time, parse_required_time, run_from_row
from acquisition.daemon.catalog.runs import RunCatalog
from acquisition.daemon.catalog.schema import RUN_COLUMNS


class QueueCatalog(RunCatalog, CatalogDatabase):
    """The catalog's queue of runs (see :class:`acquisition.daemon.catalog.Catalog`)."""

    def queued_runs(self) -> list[RunRecord]:
        """This rig's queued runs, the next to start first."""
        with self._read() as conn:
            rows = conn.execute(
                f"SELECT {RUN_COLUMNS} FROM runs WHERE rig = ? AND state = 'queued' ORDER BY queue_order, seq",
                (self.rig,),
            )
            return [run_from_row(row) for row in rows]

    def queue_hold(self) -> tuple[str, datetime] | None:
        """Why the queue is held and since when (a UTC datetime); None while it runs on."""
        with self._read() as conn:
            row = conn.execute("SELECT held, held_utc FROM rigs WHERE rig = ?", (self.rig,)).fetchone()
            return None if row is None or row["held"] is None else (row["held"], parse_required_time(row["held_utc"]))

    def hold_queue(self, reason: str) -> None:
        """Hold the queue: no queued run starts by itself until :meth:`release_queue`.

        Raises
        ------
        CatalogError
            ``reason`` is not one non-empty line.
        """
        check_text("reason", reason)
        with self._write() as conn:
            conn.execute(
                "INSERT INTO rigs (rig, held, held_utc) VALUES (?, ?, ?) "
                "ON CONFLICT (rig) DO UPDATE SET held = excluded.held, held_utc = excluded.held_utc",
                (self.rig, reason, format_time(self._now())),
            )

    def release_queue(self) -> None:
        """Let the queue run on (its next run starts once the rig is free)."""
        with self._write() as conn:
            conn.execute("UPDATE rigs SET held = NULL, held_utc = NULL WHERE rig = ?", (self.rig,))

    def register_daemon(self, url: str) -> None:
        """Record where this rig's daemon answers (``http://HOST:PORT``): workers that do not
        share its disk fetch its run files there and send the results back."""
        check_text("url", url)
        if not url.startswith(("http://", "https://")):
            raise CatalogError(f"the daemon's URL must be http:// or https://, not {url!r}")
        with self._write() as conn:
            conn.execute(
                "INSERT INTO rigs (rig, daemon_url, daemon_seen_utc) VALUES (?, ?, ?) "
                "ON CONFLICT (rig) DO UPDATE SET daemon_url = excluded.daemon_url, "
                "daemon_seen_utc = excluded.daemon_seen_utc",
                (self.rig, url.rstrip("/"), format_time(self._now())),
            )

    def daemon_url(self, rig: str) -> str | None:
        """Where rig ``rig``'s daemon said it answers, if it did."""
        with self._read() as conn:
            row = conn.execute("SELECT daemon_url FROM rigs WHERE rig = ?", (rig,)).fetchone()
            return None if row is None else row["daemon_url"]

    def reorder_queue(self, run_ids: list[str]) -> list[RunRecord]:
        """Put the queued runs ``run_ids`` first, in that order; the queued runs not named
        follow in their order (one queued meanwhile keeps its turn after them).

        Raises
        ------
        UnknownRunError
            No run has one of the ids.
        NotQueuedError
            One of the runs is no longer queued (it has started, or was removed).
        CatalogError
            An id is named twice.
        """
        if len(set(run_ids)) != len(run_ids):
            twice = next(run_id for run_id in run_ids if run_ids.count(run_id) > 1)
            raise CatalogError(f"run {twice!r} is named twice in the queue's order")
        with self._write(self._rig_lock) as conn:
            for run_id in run_ids:
                state = self._fetch_own_run(conn, run_id, "reorder the queue").state
                if state != "queued":
                    raise NotQueuedError(run_id, state, "reorder the queue")
            rest = [
                row["id"]
                for row in conn.execute(
                    "SELECT id FROM runs WHERE rig = ? AND state = 'queued' ORDER BY queue_order, seq", (self.rig,)
                )
                if row["id"] not in run_ids
            ]
            for order, run_id in enumerate([*run_ids, *rest], start=1):
                conn.execute("UPDATE runs SET queue_order = ? WHERE id = ?", (order, run_id))
        return self.queued_runs()

    def remove_from_queue(self, run_id: str, error: str) -> RunRecord:
        """Take a queued run out of the queue: it ends ``aborted`` with ``error`` as its
        ``last_error``, never having started. The queue's hold goes with its last run.

        Raises
        ------
        UnknownRunError
            No run has this id.
        NotQueuedError
            The run is not queued (it has started, ended, or was removed already).
        """
        check_text("error", error)
        with self._write(self._rig_lock) as conn:
            self._fetch_own_run(conn, run_id, "remove it from the queue")
            stamp = format_time(self._now())
            changed = conn.execute(
                "UPDATE runs SET state = 'aborted', queue_order = NULL, updated_utc = ?, finished_utc = ?, "
                "last_error = ? WHERE id = ? AND state = 'queued'",
                (stamp, stamp, error, run_id),
            ).rowcount
            record = self._fetch_run(conn, run_id)
            if changed == 0:
                raise NotQueuedError(run_id, record.state, "remove it from the queue")
            left = conn.execute("SELECT 1 FROM runs WHERE rig = ? AND state = 'queued' LIMIT 1", (self.rig,))
            if left.fetchone() is None:
                conn.execute("UPDATE rigs SET held = NULL, held_utc = NULL WHERE rig = ?", (self.rig,))
            return record
