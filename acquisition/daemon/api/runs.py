"""Runs: start, list, follow, control, download, and ask for processing."""

from __future__ import annotations

import asyncio
from pathlib import Path

from fastapi import APIRouter, HTTPException, Request, Response, status
from fastapi.responses import FileResponse, StreamingResponse

from acquisition.daemon.api.deps import (
    TOKEN_ERRORS,
    WRITE_ERRORS,
    CatalogDep,
    EngineDep,
    ReadTokenDep,
    Responses,
    RigQuery,
    SettingsDep,
    TokenDep,
    catalog_rig,
)
from acquisition.daemon.api.jobs import job_status
from acquisition.daemon.catalog import RunRecord
from acquisition.daemon.engine import RunEngine
from acquisition.daemon.models import (
    CalibrationOptions,
    JobRequest,
    JobStatus,
    Problem,
    ResumeRequest,
    RunRequest,
    RunStatus,
)
from acquisition.daemon.transfer import DIGEST_HEADER, repr_digest

router = APIRouter(prefix="/runs", tags=["runs"], dependencies=[ReadTokenDep], responses=TOKEN_ERRORS)
FINAL = ("complete", "aborted", "failed", "interrupted")
ERRORS: Responses = {404: {"model": Problem}, 409: {"model": Problem}}
# A storage that refuses the catalog's write, or a run that would not fit (docs/daemon.md).
STORAGE_ERRORS: Responses = {
    503: {"model": Problem, "description": "the data's storage cannot be written (read-only, an I/O error)"},
    507: {
        "model": Problem,
        "description": "not enough free space (the catalog's disk is full, or the run would not fit)",
    },
}
GUARDED_ERRORS: Responses = {
    **ERRORS,
    **WRITE_ERRORS,
    **STORAGE_ERRORS,
}  # and 401/403 from the token, 415 from the guard
# FastAPI's answer to a body it cannot read as JSON text at all (not UTF-8, say).
BODY_ERRORS: Responses = {400: {"model": Problem, "description": "the body cannot be read"}}


def run_status(record: RunRecord, engine: RunEngine | None = None) -> RunStatus:
    """The API's view of a run; with the engine, what it is doing now (``step``) and how it
    ended if the catalog could not record that yet."""
    if engine is not None:
        record = engine.pending.known(record)
    percent = 100.0 * record.positions_done / record.n_positions if record.n_positions else 0.0
    return RunStatus(
        id=record.id,
        rig=record.rig,
        read_only=engine is not None and record.rig != engine.catalog.rig,
        state=record.state,
        preset=record.preset,
        n_positions=record.n_positions,
        positions_done=record.positions_done,
        percent_done=round(percent, 2),
        current_position=record.current_position,
        eta_s=record.eta_s,
        last_error=record.last_error,
        created_utc=record.created_utc,
        started_utc=record.started_utc,
        finished_utc=record.finished_utc,
        exposures_per_position=record.exposures_per_position,
        file_url=f"/runs/{record.id}/file",
        # An ended run has no step, even if read just before it was resumed (a new thread's step).
        step=engine.step(record.id) if engine is not None and record.state not in FINAL else None,
        queue_position=record.queue_position,
    )


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=RunStatus,
    dependencies=[TokenDep],
    responses={
        201: {"model": RunStatus, "description": "started: the rig was free and no run waited"},
        202: {"model": RunStatus, "description": "queued behind the run in progress (its `queue_position`)"},
        409: {"model": Problem, "description": "the devices are held by a test shot, a jog or homing"},
        422: {"model": Problem},
        **BODY_ERRORS,
        **WRITE_ERRORS,
        **STORAGE_ERRORS,
    },
)
def start_run(body: RunRequest, engine: EngineDep, settings: SettingsDep, response: Response) -> RunStatus:
    """Start a run (201), or queue it (202) while another is in progress or runs wait: it starts
    by itself in its turn (``GET /queue``). A run whose estimated size exceeds the free space
    gets 507 with both, unless it says ``"force": true``."""
    if "ambient_exposures_s" not in body.calibration.model_fields_set:
        options = {**body.calibration.model_dump(), "ambient_exposures_s": settings.light.ambient_exposures_s}
        body = body.model_copy(update={"calibration": CalibrationOptions.model_validate(options)})
    if "bracket" not in body.model_fields_set:
        default = {"mode": "fixed", "exposures_s": settings.default_exposures_s}
        body = RunRequest.model_validate({**body.model_dump(exclude={"bracket"}), "bracket": default})
    record = engine.start_run(body)
    if record.state == "queued":
        response.status_code = status.HTTP_202_ACCEPTED
    return run_status(record, engine)


@router.get("", response_model=list[RunStatus], responses={400: {"model": Problem, "description": "a bad rig name"}})
def list_runs(catalog: CatalogDep, engine: EngineDep, limit: int = 100, rig: RigQuery = None) -> list[RunStatus]:
    """Runs, newest first: this rig's, another rig's (``rig=NAME``) or the whole lab's
    (``rig=all``), where rigs share a catalog. Other rigs' runs are read-only here."""
    return [run_status(r, engine) for r in catalog.list_runs(limit=max(1, min(limit, 1000)), rig=catalog_rig(rig))]


@router.get("/{run_id}", response_model=RunStatus, responses=ERRORS)
def get_run(run_id: str, catalog: CatalogDep, engine: EngineDep) -> RunStatus:
    """What happened to a run: state, percent done, ETA, current position, what it is doing now
    (``step``: the calibration frames, the sweep, or what the operator must do before resuming
    it), last error."""
    return run_status(catalog.get_run(run_id), engine)


@router.post("/{run_id}/pause", response_model=RunStatus, dependencies=[TokenDep], responses=GUARDED_ERRORS)
def pause(run_id: str, engine: EngineDep) -> RunStatus:
    """Pause between frames; 409 unless the run is running."""
    return run_status(engine.pause(run_id), engine)


@router.post(
    "/{run_id}/resume",
    response_model=RunStatus,
    dependencies=[TokenDep],
    responses={**GUARDED_ERRORS, **BODY_ERRORS},
)
def resume(run_id: str, engine: EngineDep, body: ResumeRequest | None = None) -> RunStatus:
    """Resume a paused run (one paused for the operator to switch the lights, once that is
    done), or continue an interrupted (daemon crash) or failed (device fault or full disk, now
    cleared) run from its first incomplete position or calibration set. What it has left must
    fit in the free space (else 507), unless the body says ``"force": true``. A resume clears
    ``last_error``."""
    return run_status(engine.resume(run_id, force=body is not None and body.force), engine)


@router.post("/{run_id}/abort", response_model=RunStatus, dependencies=[TokenDep], responses=GUARDED_ERRORS)
def abort(run_id: str, engine: EngineDep) -> RunStatus:
    """Stop the arm and end the run; every frame taken is kept. A queued run is taken out of
    the queue (as ``DELETE /queue/{run_id}``)."""
    return run_status(engine.abort(run_id), engine)


@router.get("/{run_id}/events", responses={200: {"content": {"text/event-stream": {}}}, **ERRORS})
async def events(run_id: str, request: Request, catalog: CatalogDep, engine: EngineDep) -> StreamingResponse:
    """Progress as server-sent events (``event: progress``), until the run ends."""
    catalog.get_run(run_id)  # 404 before the stream starts

    async def stream():
        version = None
        while True:
            if await request.is_disconnected():
                return
            current = engine.events.version
            if current != version:
                version = current
                record = await asyncio.to_thread(catalog.get_run, run_id)
                yield f"event: progress\ndata: {run_status(record, engine).model_dump_json()}\n\n"
                if record.state in FINAL:
                    return
            await asyncio.sleep(0.2)

    return StreamingResponse(stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"})


@router.get("/{run_id}/preview.png", responses={200: {"content": {"image/png": {}}}, **ERRORS})
def run_preview(run_id: str, request: Request, catalog: CatalogDep) -> Response:
    """The latest frame of this run, tone-mapped and downscaled."""
    catalog.get_run(run_id)
    made = request.app.state.previews.quick_look()
    if made is None or made[1] != run_id:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"run {run_id} has no frame in memory to preview")
    return Response(made[0], media_type="image/png", headers={"Cache-Control": "no-store"})


@router.get("/{run_id}/file", responses={200: {"content": {"application/x-hdf5": {}}}, **ERRORS})
def download(run_id: str, request: Request, catalog: CatalogDep, engine: EngineDep) -> FileResponse:
    """The run file (HDF5, ``docs/run-file.md``); refused while the run is being written. Its
    SHA-256 is in ``Repr-Digest``; ``Range`` resumes a cut download (with ``If-Range`` on the
    ``ETag``). Another rig's run is fetched from its own daemon."""
    record = engine.pending.known(catalog.get_run(run_id))
    if record.rig != catalog.rig:
        raise HTTPException(
            status.HTTP_404_NOT_FOUND,
            f"run {run_id} is rig {record.rig!r}'s: its file is with that rig's daemon"
            + (f" ({url})" if (url := catalog.daemon_url(record.rig)) else ""),
        )
    if record.state in ("running", "paused", "queued"):
        raise HTTPException(
            status.HTTP_409_CONFLICT, f"run {run_id} is {record.state}: the file is still being written"
        )
    path = Path(record.path) if record.path is not None else None
    if path is None or not path.exists():
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"run {run_id} has no run file")
    digest = request.app.state.digests.get(path)
    return FileResponse(
        path, media_type="application/x-hdf5", filename=path.name, headers={DIGEST_HEADER: repr_digest(digest)}
    )


@router.post(
    "/{run_id}/process",
    status_code=status.HTTP_201_CREATED,
    response_model=JobStatus,
    dependencies=[TokenDep],
    responses={**GUARDED_ERRORS, **BODY_ERRORS},
)
def process(run_id: str, catalog: CatalogDep, body: JobRequest | None = None) -> JobStatus:
    """Queue a processing job for the run (a worker takes it: ``mirrorgonio worker``). While the
    run is being acquired the job waits, unless it asks for ``partial``."""
    body = body or JobRequest()
    return job_status(catalog.create_job(run_id, steps=body.steps, options=body.options()))
