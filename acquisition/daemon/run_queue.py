"""The queue of runs, an object the run engine (``acquisition.daemon.engine``) owns: the runs
asked for while one is in progress wait in the catalog, in an order the operator may change,
and start one after the other.

- A run that **completes** starts the next queued run by itself.
- A run that **fails or is aborted** holds the queue, with the reason: the rig may need a
  person before the next run. So does a queued run that cannot start (its estimated size no
  longer fits in the free space, a file it names cannot be read): it stays queued.
- **After a restart** the queued runs stay queued and the queue is held: the daemon does not
  drive the rig by itself until the operator has dealt with the run it left interrupted.
- A held queue goes on when the operator **resumes** an interrupted or failed run (the queue
  continues once it completes) or **starts the queue** (``POST /queue/start``).

The hold and the order live in the catalog (``acquisition.daemon.catalog.queue``), so a restart keeps
both.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from pydantic import ValidationError

from acquisition.daemon.catalog import Catalog, CatalogError, RunRecord
from acquisition.daemon.catalog.pending import PendingEnds
from acquisition.daemon.models import RunRequest
from acquisition.daemon.run_control import ProgressEvents
from acquisition.daemon.run_plan import RunPlan
from acquisition.daemon.run_preflight import RunPreflight
from acquisition.daemon.storage import StorageError

log = logging.getLogger("mirrorgonio.runner")

#: Why a queued run that was taken out of the queue ended ``aborted`` (its ``last_error``).
REMOVED = "removed from the queue by the operator"


class RunQueue:
    """One rig's queue of runs, owned by its run engine.

    It uses of the engine only what it is given: the catalog that keeps the queue, the
    preflight that plans a queued run, the engine's lock (its methods marked "under the lock"
    are called with it held), and ``start``, which starts a planned run (the engine's: the run
    ``running``, its thread started) and returns its record.
    """

    def __init__(
        self,
        catalog: Catalog,
        preflight: RunPreflight,
        events: ProgressEvents,
        pending: PendingEnds,
        lock: threading.Lock,
        start: Callable[[RunRecord, RunPlan], RunRecord],
    ):
        self.catalog = catalog
        self.preflight = preflight
        self.events = events
        self.pending = pending
        self._lock = lock
        self._start = start
        self.closing = False  # the daemon shuts down: no queued run starts

    def release(self, rig_taken: bool) -> RunRecord | None:
        """Release the queue's hold; start its next run now unless ``rig_taken`` (under the lock).

        Returns
        -------
        RunRecord or None
            The run started, or None (the rig is busy, or nothing is queued).

        Raises
        ------
        RigError, ClientFileError, InsufficientStorageError, StorageUnavailableError
            The next run cannot start (its preflight): the queue is held again with the reason.
        """
        self.catalog.release_queue()
        self.events.publish()
        if rig_taken:
            return None
        return self.start_next(explicit=True)

    def reorder(self, run_ids: list[str]) -> list[RunRecord]:
        """The queued runs ``run_ids`` first, in that order (``Catalog.reorder_queue``)."""
        with self._lock:
            queued = self.catalog.reorder_queue(run_ids)
        self.events.publish()
        return queued

    def remove(self, run_id: str) -> RunRecord:
        """Take a queued run out of the queue: it ends ``aborted`` without having started.

        Raises
        ------
        NotQueuedError
            The run is not queued (it has started, ended, or was removed already): 409.
        """
        with self._lock:
            record = self.catalog.remove_from_queue(run_id, REMOVED)
        log.info("run %s removed from the queue", run_id)
        self.events.publish()
        return record

    def after_restart(self, interrupted: list[str]) -> None:
        """At daemon start: the runs still queued wait for the operator. The queue is held (its
        hold kept, if it was held already) until a run is resumed or the queue is started."""
        queued = self.catalog.queued_runs()
        if not queued or self.catalog.queue_hold() is not None:
            return
        why = f" (run {', '.join(interrupted)} interrupted)" if interrupted else ""
        self.catalog.hold_queue(f"the daemon restarted{why}: start the queue once the rig is ready")
        log.warning("the queue of %d runs is held: the daemon restarted%s", len(queued), why)

    def start_next(self, explicit: bool = False) -> RunRecord | None:
        """Start the first queued run, the rig being free (under the lock). A run that cannot
        start (its request, its references or its size no longer pass) stays queued and holds
        the queue with the reason; an ``explicit`` request (:meth:`release`) is also told."""
        queued = self.catalog.queued_runs()
        if not queued or self.closing:
            return None
        record = queued[0]
        try:
            request = RunRequest.model_validate(record.request)
            plan = self.preflight.plan(request)
            if not request.force:
                self.preflight.check_room(plan, len(plan.tool_poses))
        except (ValidationError, ValueError, StorageError) as exc:
            reason = f"run {record.id} cannot start: {exc}"
            log.warning("the queue is held: %s", reason)
            self.catalog.hold_queue(reason.replace("\n", " "))
            self.events.publish()
            if explicit:
                raise
            return None
        record = self._start(record, plan)
        log.info("run %s started from the queue: %s, %d positions", record.id, request.preset, len(plan.tool_poses))
        self.events.publish()
        return record

    def after_run(self, run_id: str, outcome: str, message: str) -> None:
        """The queue once run ``run_id`` has ended (under the lock, in the run's thread, as its
        last act): the next queued run starts if this one completed and the queue is not held;
        a run that failed or was aborted (or whose end the catalog could not record yet) holds it."""
        try:
            if not self.catalog.queued_runs() or self.catalog.queue_hold() is not None:
                return
            if self.closing:
                reason = f"the daemon shut down during run {run_id}"
            elif run_id in self.pending.held():
                reason = f"the catalog could not record how run {run_id} ended"
            elif outcome == "aborted":
                reason = f"run {run_id} was aborted"
            elif outcome != "complete":
                reason = f"run {run_id} {outcome}: {message or 'no reason given'}"
            else:
                self.start_next()
                return
            self.catalog.hold_queue(reason.replace("\n", " "))
            log.warning("the queue is held: %s", reason)
        except (CatalogError, StorageError) as exc:
            log.warning("the queue after run %s: %s", run_id, exc)
