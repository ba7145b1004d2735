"""Processing jobs: their state, and their result files to download.

A worker (``mirrorgonio worker``) records the files a job wrote, by kind; the daemon serves
exactly those files and nothing else: an unknown kind, a job without that file, or a file
that has gone (or left the job's result folder) is 404.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, HTTPException, status
from fastapi.responses import FileResponse

from acquisition.api.deps import CatalogDep
from acquisition.catalog import JobRecord
from acquisition.models import JobStatus, Problem

router = APIRouter(prefix="/jobs", tags=["jobs"])

#: How each kind of result file is served: media type, and whether a browser shows it.
ARTIFACT_TYPES: dict[str, tuple[str, bool]] = {
    "report": ("text/html; charset=utf-8", True),
    "ies": ("text/plain; charset=utf-8", False),
    "ldt": ("text/plain; charset=utf-8", False),
    "tm25": ("application/octet-stream", False),
    "light_model": ("application/json", False),
    "results": ("application/x-hdf5", False),
}


def artifact_url(job_id: str, kind: str) -> str:
    return f"/jobs/{job_id}/artifacts/{kind}"


def job_status(job: JobRecord) -> JobStatus:
    return JobStatus(id=job.id, run_id=job.run_id, state=job.state, steps=job.steps, options=job.options,
                     progress=job.progress, error=job.error, message=job.message, result_dir=job.result_dir,
                     claimed_by=job.claimed_by, heartbeat_utc=job.heartbeat_utc, created_utc=job.created_utc,
                     updated_utc=job.updated_utc,
                     artifacts={kind: artifact_url(job.id, kind) for kind in job.artifacts})  # fmt: skip


@router.get("", response_model=list[JobStatus], responses={404: {"model": Problem, "description": "unknown run_id"}})
def list_jobs(catalog: CatalogDep, run_id: str | None = None, limit: int = 100) -> list[JobStatus]:
    """Jobs, newest first (those of one run with ``run_id``)."""
    return [job_status(j) for j in catalog.list_jobs(run_id=run_id, limit=max(1, min(limit, 1000)))]


@router.get("/{job_id}", response_model=JobStatus, responses={404: {"model": Problem}})
def get_job(job_id: str, catalog: CatalogDep) -> JobStatus:
    """A job: state, progress, why it waits or failed, and its result files' URLs."""
    return job_status(catalog.get_job(job_id))


@router.get("/{job_id}/artifacts/{kind}", responses={
    200: {"content": {media: {} for media, _ in ARTIFACT_TYPES.values()},
          "description": "the file (the report opens in the browser, the others download)"},
    404: {"model": Problem, "description": "unknown job, or no such file recorded for it"}})  # fmt: skip
def download_artifact(job_id: str, kind: str, catalog: CatalogDep) -> FileResponse:
    """One of a job's result files: ``report`` (HTML), ``ies``, ``ldt``, ``tm25`` (ray file),
    ``light_model`` (JSON) or ``results`` (HDF5)."""
    job = catalog.get_job(job_id)
    recorded = job.artifacts.get(kind)
    if recorded is None:
        kinds = ", ".join(sorted(job.artifacts)) or "none yet"
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {job_id} has no {kind!r} file (it has: {kinds})")
    path = Path(recorded).resolve()
    inside = job.result_dir is None or path.is_relative_to(Path(job.result_dir).resolve())
    if not inside or not path.is_file():
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {job_id}: its {kind} file is no longer there")
    media, inline = ARTIFACT_TYPES.get(kind, ("application/octet-stream", False))
    return FileResponse(path, media_type=media, filename=path.name,
                        content_disposition_type="inline" if inline else "attachment")  # fmt: skip
