"""Processing jobs: their state and where their results are."""

from __future__ import annotations

from fastapi import APIRouter

from acquisition.api.deps import CatalogDep
from acquisition.catalog import JobRecord
from acquisition.models import JobStatus, Problem

router = APIRouter(prefix="/jobs", tags=["jobs"])


def job_status(job: JobRecord) -> JobStatus:
    return JobStatus(id=job.id, run_id=job.run_id, state=job.state, steps=job.steps, progress=job.progress,
                     error=job.error, result_dir=job.result_dir, created_utc=job.created_utc,
                     updated_utc=job.updated_utc)  # fmt: skip


@router.get("", response_model=list[JobStatus], responses={404: {"model": Problem, "description": "unknown run_id"}})
def list_jobs(catalog: CatalogDep, run_id: str | None = None, limit: int = 100) -> list[JobStatus]:
    return [job_status(j) for j in catalog.list_jobs(run_id=run_id, limit=max(1, min(limit, 1000)))]


@router.get("/{job_id}", response_model=JobStatus, responses={404: {"model": Problem}})
def get_job(job_id: str, catalog: CatalogDep) -> JobStatus:
    return job_status(catalog.get_job(job_id))
