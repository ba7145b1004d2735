"""The runs in the catalog: created, moved between states, their progress recorded."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from acquisition.daemon.catalog.backends import Connection, Row
from acquisition.daemon.catalog.database import CatalogDatabase, check_int, check_real, check_rig, check_text, to_json
from acquisition.daemon.catalog.errors import (
    ActiveRunError,
    CatalogError,
    InvalidTransitionError,
    OtherRigError,
    UnknownRunError,
)
from acquisition.daemon.catalog.records import (
    ALLOWED_RUN_TRANSITIONS,
    IN_PROGRESS_RUN_STATES,
    RUN_STATES,
    RunRecord,
    format_time,
    run_from_row,
)
from acquisition.daemon.catalog.schema import RUN_COLUMNS, sql_list

#: A run entering one of these gets its ``finished_utc``; entering ``running`` clears it.
_FINISHING_RUN_STATES = ("complete", "aborted", "failed")


class RunCatalog(CatalogDatabase):
    """The catalog's runs (see :class:`acquisition.daemon.catalog.Catalog`)."""

    def _other_active(self, conn: Connection, run_id: str | None) -> Row | None:
        """The run of this rig in progress other than ``run_id`` (any run in progress if None)."""
        return conn.execute(
            f"SELECT id, state FROM runs WHERE rig = ? AND state IN ({sql_list(IN_PROGRESS_RUN_STATES)}) AND id <> ? "
            "ORDER BY seq DESC LIMIT 1",
            (self.rig, "" if run_id is None else run_id),
        ).fetchone()

    @staticmethod
    def _fetch_run(conn: Connection, run_id: str) -> RunRecord:
        row = conn.execute(f"SELECT {RUN_COLUMNS} FROM runs WHERE id = ?", (run_id,)).fetchone()
        if row is None:
            raise UnknownRunError(run_id)
        return run_from_row(row)

    def _fetch_own_run(self, conn: Connection, run_id: str, wanted: str) -> RunRecord:
        """The run, if it is this rig's; an OtherRigError if another rig's (those are read-only here)."""
        run = self._fetch_run(conn, run_id)
        if run.rig != self.rig:
            raise OtherRigError(run_id, run.rig, self.rig, wanted)
        return run

    @property
    def _rig_lock(self) -> str:
        """The key a write holds where it checks and changes this rig's runs (their queue, the run in progress)."""
        return f"rig:{self.rig}"

    def create_run(
        self,
        *,
        preset: str | None,
        path_for: Callable[[str], str | Path] | None,
        n_positions: int,
        request: dict,
    ) -> RunRecord:
        """Add a new run in state ``queued``, at the end of the queue (whether it starts at once
        or waits for the runs ahead of it is the daemon's decision).

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
        CatalogError
            A bad argument.
        """
        if preset is not None:
            check_text("preset", preset)
        n_positions = check_int("n_positions", n_positions, 1)
        request_json = to_json(request, "the run request")
        with self._write(self._rig_lock) as conn:
            now = self._now()
            run_id = self._new_id(conn, "runs", "run", now)
            path = None if path_for is None else str(path_for(run_id))
            stamp = format_time(now)
            order = conn.execute("SELECT COALESCE(MAX(queue_order), 0) + 1 FROM runs WHERE rig = ?", (self.rig,))
            conn.execute(
                "INSERT INTO runs (id, seq, rig, created_utc, updated_utc, state, preset, path, n_positions, "
                "positions_done, request_json, queue_order) VALUES (?, ?, ?, ?, ?, 'queued', ?, ?, ?, 0, ?, ?)",
                (
                    run_id,
                    self._next_seq(conn, "runs"),
                    self.rig,
                    stamp,
                    stamp,
                    preset,
                    path,
                    n_positions,
                    request_json,
                    order.fetchone()[0],
                ),
            )
            return self._fetch_run(conn, run_id)

    def get_run(self, run_id: str) -> RunRecord:
        """The run with this id (of any rig).

        Raises
        ------
        UnknownRunError
            No run has this id.
        """
        with self._read() as conn:
            return self._fetch_run(conn, run_id)

    def list_runs(self, limit: int = 100, state: str | None = None, *, rig: str | None = "") -> list[RunRecord]:
        """The newest runs first, at most ``limit`` of them, only those in ``state`` if given.

        ``rig``: this rig's runs (``""``, the default), another rig's (its name), or the whole
        lab's (None).
        """
        limit = check_int("limit", limit, 1)
        if state is not None and state not in RUN_STATES:
            raise CatalogError(f"unknown run state {state!r} (one of: {', '.join(RUN_STATES)})")
        conditions, params = [], []
        if rig is not None:
            conditions.append("rig = ?")
            params.append(check_rig(rig) if rig else self.rig)
        if state is not None:
            conditions.append("state = ?")
            params.append(state)
        where = f"WHERE {' AND '.join(conditions)} " if conditions else ""
        with self._read() as conn:
            rows = conn.execute(f"SELECT {RUN_COLUMNS} FROM runs {where}ORDER BY seq DESC LIMIT ?", (*params, limit))
            return [run_from_row(row) for row in rows]

    def rigs(self) -> list[str]:
        """The rigs the catalog has runs of, and this one, by name."""
        with self._read() as conn:
            names = {row[0] for row in conn.execute("SELECT DISTINCT rig FROM runs")}
        return sorted(names | {self.rig})

    def transition_run(self, run_id: str, new_state: str, *, error: str | None = None) -> RunRecord:
        """Move a run to ``new_state`` if :data:`ALLOWED_RUN_TRANSITIONS` allows it.

        The check and the change are one statement (``UPDATE ... WHERE state IN ...``): of
        two callers racing from the same state, exactly one wins. Entering ``running``
        sets ``started_utc`` the first time and clears ``finished_utc`` and ``last_error``
        (a resumed run shows an error again only if a new one happens); entering
        ``complete``, ``aborted`` or ``failed`` sets ``finished_utc``.

        Parameters
        ----------
        run_id : str
            The run.
        new_state : str
            One of :data:`RUN_STATES`.
        error : str, optional
            Stored as the run's ``last_error`` (kept otherwise, so that a paused or ended
            run still shows what stopped it; cleared on entering ``running``).

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
            Starting or resuming this run while another one is running or paused.
        """
        if new_state not in RUN_STATES:
            raise CatalogError(f"{run_id}: unknown run state {new_state!r} (one of: {', '.join(RUN_STATES)})")
        if error is not None:
            check_text("error", error)
        sources = [s for s, targets in ALLOWED_RUN_TRANSITIONS.items() if new_state in targets]
        with self._write(self._rig_lock) as conn:
            self._fetch_own_run(conn, run_id, f"make it {new_state}")
            if new_state in IN_PROGRESS_RUN_STATES:
                active = self._other_active(conn, run_id)
                if active is not None:
                    raise ActiveRunError(active["id"], active["state"], f"make {run_id} {new_state}")
            stamp = format_time(self._now())
            if new_state == "running":
                finished: tuple[str, tuple[str, ...]] = ("NULL", ())
            elif new_state in _FINISHING_RUN_STATES:
                finished = ("?", (stamp,))
            else:
                finished = ("finished_utc", ())
            started = ("COALESCE(started_utc, ?)", (stamp,)) if new_state == "running" else ("started_utc", ())
            kept_error = "NULL" if new_state == "running" else "last_error"
            changed = conn.execute(
                f"UPDATE runs SET state = ?, queue_order = NULL, updated_utc = ?, started_utc = {started[0]}, "
                f"finished_utc = {finished[0]}, last_error = COALESCE(?, {kept_error}) "
                f"WHERE id = ? AND state IN ({sql_list(sources) or 'NULL'})",
                (new_state, stamp, *started[1], *finished[1], error, run_id),
            ).rowcount
            if changed == 0:
                current = self._fetch_run(conn, run_id).state
                raise InvalidTransitionError(run_id, current, new_state, ALLOWED_RUN_TRANSITIONS[current])
            return self._fetch_run(conn, run_id)

    def update_progress(
        self,
        run_id: str,
        *,
        positions_done: int | None = None,
        current_position: int | None,
        seconds_per_position: float | None = None,
        exposures_per_position: int | None = None,
    ) -> None:
        """Record a run's progress (accepted in any state: a late report is still true).

        Parameters
        ----------
        run_id : str
            The run.
        positions_done : int, optional
            Positions finished so far, in ``[0, n_positions]``; None leaves the stored value
            unchanged (the run file's writer counts them: another caller that read the count
            first would put back a stale one).
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
        if positions_done is not None:
            check_int("positions_done", positions_done, 0)
        if current_position is not None:
            check_int("current_position", current_position, 0)
        if seconds_per_position is not None:
            seconds_per_position = check_real("seconds_per_position", seconds_per_position, 0.0)
        if exposures_per_position is not None:
            check_int("exposures_per_position", exposures_per_position, 1)
        with self._write() as conn:
            n = self._fetch_own_run(conn, run_id, "record its progress").n_positions
            if positions_done is not None and positions_done > n:
                raise CatalogError(f"{run_id}: positions_done {positions_done} > n_positions {n}")
            if current_position is not None and current_position >= n:
                raise CatalogError(f"{run_id}: current_position {current_position} >= n_positions {n}")
            conn.execute(
                "UPDATE runs SET positions_done = COALESCE(?, positions_done), current_position = ?, "
                "seconds_per_position = COALESCE(?, seconds_per_position), "
                "exposures_per_position = COALESCE(?, exposures_per_position), updated_utc = ? WHERE id = ?",
                (
                    positions_done,
                    current_position,
                    seconds_per_position,
                    exposures_per_position,
                    format_time(self._now()),
                    run_id,
                ),
            )

    def active_run(self) -> RunRecord | None:
        """The run that is running or paused, if any (one run in progress at a time per rig;
        the queued runs wait: :meth:`~acquisition.daemon.catalog.queue.QueueCatalog.queued_runs`)."""
        with self._read() as conn:
            row = conn.execute(
                f"SELECT {RUN_COLUMNS} FROM runs WHERE rig = ? AND state IN ({sql_list(IN_PROGRESS_RUN_STATES)}) "
                "ORDER BY seq DESC LIMIT 1",
                (self.rig,),
            ).fetchone()
            return None if row is None else run_from_row(row)

    def mark_interrupted(self) -> list[str]:
        """At daemon start: every run of this rig left running or paused becomes ``interrupted``
        (the queued runs stay queued, in their order; other rigs' runs are theirs).

        Returns
        -------
        list of str
            The ids of those runs, oldest first.
        """
        in_progress = f"rig = ? AND state IN ({sql_list(IN_PROGRESS_RUN_STATES)})"
        with self._write(self._rig_lock) as conn:
            rows = conn.execute(f"SELECT id FROM runs WHERE {in_progress} ORDER BY seq", (self.rig,))
            ids = [row["id"] for row in rows]
            conn.execute(
                f"UPDATE runs SET state = 'interrupted', updated_utc = ? WHERE {in_progress}",
                (format_time(self._now()), self.rig),
            )
            return ids
