"""The queue of runs: the runs waiting while one is in progress, their order, and the hold."""

from __future__ import annotations

from fastapi import APIRouter

from acquisition.daemon.api.deps import TOKEN_ERRORS, CatalogDep, EngineDep, ReadTokenDep, TokenDep
from acquisition.daemon.api.runs import BODY_ERRORS, GUARDED_ERRORS, run_status
from acquisition.daemon.catalog import Catalog
from acquisition.daemon.engine import RunEngine
from acquisition.daemon.models import QueueOrder, QueueStatus, RunStatus

router = APIRouter(prefix="/queue", tags=["queue"], dependencies=[ReadTokenDep], responses=TOKEN_ERRORS)


def queue_status(catalog: Catalog, engine: RunEngine) -> QueueStatus:
    hold = catalog.queue_hold()
    return QueueStatus(
        held=hold[0] if hold else None,
        held_utc=hold[1] if hold else None,
        runs=[run_status(record, engine) for record in catalog.queued_runs()],
    )


@router.get("", response_model=QueueStatus)
def get_queue(catalog: CatalogDep, engine: EngineDep) -> QueueStatus:
    """The queued runs, the next to start first, and why the queue is held (if it is)."""
    return queue_status(catalog, engine)


@router.put("", response_model=QueueStatus, dependencies=[TokenDep], responses={**GUARDED_ERRORS, **BODY_ERRORS})
def reorder(body: QueueOrder, catalog: CatalogDep, engine: EngineDep) -> QueueStatus:
    """Put the queued runs named first, in that order (the others follow in theirs); 409 if one
    of them is no longer queued, 404 if one does not exist."""
    engine.reorder_queue(body.run_ids)
    return queue_status(catalog, engine)


@router.post("/start", response_model=QueueStatus, dependencies=[TokenDep], responses=GUARDED_ERRORS)
def start(catalog: CatalogDep, engine: EngineDep) -> QueueStatus:
    """Release a held queue; its next run starts now if the rig is free, or when the run in
    progress completes. A next run that cannot start holds the queue again, and the answer says
    why (507 when it would not fit in the free space)."""
    engine.start_queue()
    return queue_status(catalog, engine)


@router.delete("/{run_id}", response_model=RunStatus, dependencies=[TokenDep], responses=GUARDED_ERRORS)
def remove(run_id: str, engine: EngineDep) -> RunStatus:
    """Take a queued run out of the queue: it ends ``aborted`` ("removed from the queue by the
    operator") without having started; 409 if it is not queued."""
    return run_status(engine.remove_queued(run_id), engine)
