"""Runs' ends the catalog could not record when they happened (its disk full, its file system
read-only), kept in memory and recorded as soon as the catalog can be written again."""

from __future__ import annotations

import logging
import threading

from acquisition.daemon.catalog.errors import InvalidTransitionError
from acquisition.daemon.catalog.records import RunRecord
from acquisition.daemon.catalog.runs import RunCatalog
from acquisition.daemon.storage import StorageError

log = logging.getLogger("mirrorgonio.catalog")


class PendingEnds:
    """The ends (final state and error) of runs, recorded in ``catalog`` when it can be.

    A run never stays ``running`` with no thread behind it: its end is held here until the
    catalog takes it, and :meth:`known` shows it meanwhile. Thread-safe.
    """

    def __init__(self, catalog: RunCatalog):
        self.catalog = catalog
        self._ends: dict[str, tuple[str, str]] = {}
        self._lock = threading.Lock()

    def record(self, run_id: str, state: str, error: str) -> None:
        """Record run ``run_id``'s end now, or keep it for :meth:`save` if the catalog refuses."""
        with self._lock:
            self._ends[run_id] = (state, error)
        try:
            self.save()
        except StorageError as exc:
            log.warning("run %s is %s, but the catalog cannot record it yet: %s", run_id, state, exc)

    def save(self) -> None:
        """Record every end held in the catalog.

        Raises
        ------
        StorageError
            The catalog still cannot be written; the ends held stay.
        """
        with self._lock:
            for run_id, (state, error) in list(self._ends.items()):
                try:
                    if self.catalog.get_run(run_id).state != state:
                        self.catalog.transition_run(run_id, state, error=error or None)
                except InvalidTransitionError as exc:  # changed meanwhile, by another process
                    log.warning("run %s: its end (%s) is not recorded: %s", run_id, state, exc)
                del self._ends[run_id]

    def held(self) -> dict[str, tuple[str, str]]:
        """The ends not recorded yet: run id -> (state, error)."""
        with self._lock:
            return dict(self._ends)

    def known(self, record: RunRecord) -> RunRecord:
        """``record`` with its end if that is held here (what the catalog will say once written)."""
        end = self.held().get(record.id)
        if end is None:
            return record
        return record.model_copy(update={"state": end[0], "last_error": end[1] or record.last_error})
