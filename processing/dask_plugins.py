"""Dask worker plugins of the processing (imported only where Dask is in use).

A worker plugin is registered with the scheduler: it reaches the workers there now and
every worker that joins later (a ``dask worker`` started after the processing connected,
or one restarted by its nanny), which ``Client.run`` cannot.
"""

from __future__ import annotations

import gc
import logging
from collections.abc import Callable

from distributed import Worker, WorkerPlugin

log = logging.getLogger("mirrorgonio.compute")


class WarmUpPlugin(WorkerPlugin):
    """Run ``func()`` once on each worker as it joins: imports and compiled kernels, paid
    when a worker starts rather than in its first tasks. A failure is logged on the worker
    and leaves it to warm up in its first tasks; the worker runs on.

    Then the worker's objects, warmed up and long-lived (modules, Dask's, numba's and
    matplotlib's: some 220 000), are set aside from the cyclic garbage collector
    (:func:`gc.freeze`). A full collection walks every tracked object, and one comes about
    every other run of a 2000×1312 sweep; frozen, the worker's own 220 000 are not walked,
    only the objects made since (10-60 000), most of which it frees. What is frozen is never
    collected: the warm-up's own garbage is collected first.

    ``func`` must be importable on the workers (a module-level function). Registered
    under a name made from it, idempotently: a second processing that connects to the
    same cluster does not warm its workers again.
    """

    idempotent = True

    def __init__(self, func: Callable[[], None]) -> None:
        self.func = func
        self.name = f"mirrorgonio-warm-up:{func.__module__}.{func.__qualname__}"

    def setup(self, worker: Worker) -> None:
        try:
            self.func()
        except Exception as exc:  # noqa: BLE001 - a slower first task, not a broken worker
            log.warning("%s: warming up failed: %s", getattr(worker, "address", "worker"), exc)
        gc.collect()
        gc.freeze()
