"""Processing jobs: their state, and their result files to download.

A worker (``mirrorgonio worker``) records the files a job wrote, by kind; the daemon serves
exactly those files and nothing else: an unknown kind, a job without that file, or a file
that has gone (or left the job's result folder) is 404. The results are several files (the
index and one file per position, ``docs/results-file.md``): they download as one ZIP
archive, streamed, that unpacks to a results file that opens.
"""

from __future__ import annotations

import base64
import binascii
import html
import json
import re
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, HTTPException, Query, Request, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, Response, StreamingResponse

from acquisition.daemon.api.deps import (
    TOKEN_ERRORS,
    WRITE_ERRORS,
    CatalogDep,
    ReadTokenDep,
    RigQuery,
    TokenDep,
    catalog_rig,
)
from acquisition.daemon.api.guard import TAR_TYPE
from acquisition.daemon.catalog import JobClaimError, JobRecord, OtherRigError
from acquisition.daemon.models import JobStatus, PhotometrySummary, Problem, ReportFigure, ResultsReceived
from acquisition.daemon.storage import storage_error
from acquisition.daemon.transfer import unpack_results
from processing import Results, ResultsError

router = APIRouter(prefix="/jobs", tags=["jobs"], dependencies=[ReadTokenDep], responses=TOKEN_ERRORS)

#: How each kind of result file is served: media type, and whether a browser shows it.
ARTIFACT_TYPES: dict[str, tuple[str, bool]] = {
    "report": ("text/html; charset=utf-8", True),
    "ies": ("text/plain; charset=utf-8", False),
    "ldt": ("text/plain; charset=utf-8", False),
    "tm25": ("application/octet-stream", False),
    "light_model": ("application/json", False),
    "results": ("application/zip", False),  # the results file and its position files
}


def artifact_url(job_id: str, kind: str) -> str:
    return f"/jobs/{job_id}/artifacts/{kind}"


def job_status(job: JobRecord) -> JobStatus:
    return JobStatus(
        id=job.id,
        run_id=job.run_id,
        rig=job.rig,
        state=job.state,
        steps=job.steps,
        options=job.options,
        progress=job.progress,
        step=job.step,
        error=job.error,
        message=job.message,
        result_dir=job.result_dir,
        claimed_by=job.claimed_by,
        heartbeat_utc=job.heartbeat_utc,
        created_utc=job.created_utc,
        updated_utc=job.updated_utc,
        artifacts={kind: artifact_url(job.id, kind) for kind in job.artifacts},
    )


@router.get("", response_model=list[JobStatus], responses={404: {"model": Problem, "description": "unknown run_id"}})
def list_jobs(
    catalog: CatalogDep, run_id: str | None = None, limit: int = 100, rig: RigQuery = None
) -> list[JobStatus]:
    """Jobs, newest first: those of one run (``run_id``), else this rig's, another rig's
    (``rig=NAME``) or the whole lab's (``rig=all``)."""
    jobs = catalog.list_jobs(run_id=run_id, limit=max(1, min(limit, 1000)), rig=catalog_rig(rig))
    return [job_status(j) for j in jobs]


@router.get("/{job_id}", response_model=JobStatus, responses={404: {"model": Problem}})
def get_job(job_id: str, catalog: CatalogDep) -> JobStatus:
    """A job: state, progress, why it waits or failed, and its result files' URLs."""
    return job_status(catalog.get_job(job_id))


@router.get(
    "/{job_id}/artifacts/{kind}",
    responses={
        200: {
            "content": {media: {} for media, _ in ARTIFACT_TYPES.values()},
            "description": "the file (the report opens in the browser, the others download)",
        },
        404: {"model": Problem, "description": "unknown job, or no such file recorded for it"},
    },
)
def download_artifact(job_id: str, kind: str, catalog: CatalogDep) -> Response:
    """One of a job's result files: ``report`` (HTML), ``ies``, ``ldt``, ``tm25`` (ray file),
    ``light_model`` (JSON), or ``results``: a ZIP archive of the results file and its
    per-position files, which unpacks to a results file that opens."""
    job = catalog.get_job(job_id)
    recorded = job.artifacts.get(kind)
    if recorded is None:
        kinds = ", ".join(sorted(job.artifacts)) or "none yet"
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {job_id} has no {kind!r} file (it has: {kinds})")
    result_dir = Path(job.result_dir).resolve() if job.result_dir is not None else None
    path = _served_file(job, Path(recorded), result_dir, f"its {kind} file")
    media, inline = ARTIFACT_TYPES.get(kind, ("application/octet-stream", False))
    if kind == "results":
        members = [(file, file.relative_to(path.parent).as_posix()) for file in _results_files(job, path)]
        name = path.name.removesuffix(".h5") + ".zip"
        return StreamingResponse(
            zip_stream(members), media_type=media, headers={"Content-Disposition": f'attachment; filename="{name}"'}
        )
    return FileResponse(
        path, media_type=media, filename=path.name, content_disposition_type="inline" if inline else "attachment"
    )


#: A figure of the report (``processing.report.markup``): an embedded PNG, its alt text, its caption.
_FIGURE = re.compile(
    r'<figure>\s*<img src="data:image/png;base64,([A-Za-z0-9+/=]+)" alt="([^"]*)"[^>]*>\s*'
    r"<figcaption>(.*?)</figcaption>\s*</figure>",
    re.S,
)
_TAG = re.compile(r"<[^>]+>")


def _report_figures(job: JobRecord) -> list[tuple[str, str, str]]:
    """The figures of the job's report, in its order: (base64 PNG, alt text, caption as text)."""
    recorded = job.artifacts.get("report")
    if recorded is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {job.id} has no report (yet)")
    folder = Path(job.result_dir).resolve() if job.result_dir is not None else None
    text = _served_file(job, Path(recorded), folder, "its report").read_text(encoding="utf-8", errors="replace")
    return [
        (data, html.unescape(alt), " ".join(html.unescape(_TAG.sub("", caption)).split()))
        for data, alt, caption in _FIGURE.findall(text)
    ]


@router.get(
    "/{job_id}/figures",
    response_model=list[ReportFigure],
    responses={404: {"model": Problem, "description": "unknown job, or it has no report"}},
)
def report_figures(job_id: str, catalog: CatalogDep) -> list[ReportFigure]:
    """The figures of a job's report (the polar plots of the light, its photometric figures, …),
    each an image the page shows without opening the report."""
    figures = _report_figures(catalog.get_job(job_id))
    return [
        ReportFigure(index=k, alt=alt, caption=caption, url=f"/jobs/{job_id}/figures/{k}.png")
        for k, (_, alt, caption) in enumerate(figures)
    ]


@router.get(
    "/{job_id}/photometry",
    response_model=PhotometrySummary,
    responses={404: {"model": Problem, "description": "unknown job, or its light model has no photometry"}},
)
def photometry(job_id: str, catalog: CatalogDep) -> PhotometrySummary:
    """The whole light's photometric summary from the job's light model (flux, beam and field
    angles, peak, the share beyond the measured θ), for the page's results."""
    job = catalog.get_job(job_id)
    recorded = job.artifacts.get("light_model")
    if recorded is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {job.id} has no light model (yet)")
    folder = Path(job.result_dir).resolve() if job.result_dir is not None else None
    path = _served_file(job, Path(recorded), folder, "its light model")
    try:
        p = json.loads(path.read_text(encoding="utf-8"))["photometry"]
        near = p.get("near_field") or {}
        return PhotometrySummary(
            **{key: p[key] for key in PhotometrySummary.model_fields if key in p},
            peak_intensity=p["peak"]["intensity"],
            peak_gamma_deg=p["peak"]["gamma_deg"],
            peak_c_deg=p["peak"]["c_deg"],
            near_field_distance_m=near.get("distance_m"),
            near_field_difference_percent=near.get("max_difference_percent_of_peak"),
        )
    except (ValueError, KeyError, TypeError) as exc:
        raise HTTPException(
            status.HTTP_404_NOT_FOUND, f"job {job.id}: its light model holds no photometric summary ({exc})"
        ) from None


@router.get(
    "/{job_id}/figures/{index}.png",
    responses={200: {"content": {"image/png": {}}}, 404: {"model": Problem, "description": "no such figure"}},
)
def report_figure(job_id: str, index: int, catalog: CatalogDep) -> Response:
    """One figure of a job's report, as the PNG the report embeds."""
    figures = _report_figures(catalog.get_job(job_id))
    if not 0 <= index < len(figures):
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {job_id}: its report has {len(figures)} figures")
    try:
        png = base64.b64decode(figures[index][0], validate=True)
    except binascii.Error:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {job_id}: figure {index} cannot be read") from None
    return Response(png, media_type="image/png")


def _served_file(job: JobRecord, recorded: Path, folder: Path | None, what: str) -> Path:
    """``recorded`` resolved, if it is still a file inside ``folder`` (any, if None); else a 404
    saying ``what`` is no longer there."""
    path = recorded.resolve()
    if not (folder is None or path.is_relative_to(folder)) or not path.is_file():
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {job.id}: {what} is no longer there")
    return path


def _results_files(job: JobRecord, results_path: Path) -> list[Path]:
    """The results file and every file its data live in, each checked as :func:`_served_file`
    checks one, inside the results file's folder, before any byte is sent (a stream cannot
    turn into a 404 halfway)."""
    try:
        with Results.open(results_path) as results:
            files = results.files()
    except ResultsError as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {job.id}: {exc}") from None
    return [_served_file(job, file, results_path.parent, f"its results are incomplete: {file.name}") for file in files]


class _Chunks:
    """A write-only stream that hands out what was written to it (``zipfile`` writes to it
    without seeking: sizes and CRCs go in data descriptors)."""

    def __init__(self) -> None:
        self._parts: list[bytes] = []

    def write(self, data: bytes) -> int:
        self._parts.append(bytes(data))
        return len(data)

    def flush(self) -> None:
        pass

    def close(self) -> None:  # the file-like protocol ZipFile asks for; it never closes a stream it was given
        pass

    def take(self) -> bytes:
        out = b"".join(self._parts)
        self._parts.clear()
        return out


def zip_stream(members: list[tuple[Path, str]], block: int = 1 << 20) -> Iterator[bytes]:
    """A ZIP archive of ``members`` (path, name in the archive), stored as they are (the data
    are compressed already), produced a block at a time: memory stays at one block whatever
    the run's size. ZIP64 where a member or the archive needs it."""
    sink = _Chunks()
    with zipfile.ZipFile(sink, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as archive:
        for path, name in members:
            info = zipfile.ZipInfo.from_file(path, name)
            info.compress_type = zipfile.ZIP_STORED
            with path.open("rb") as source, archive.open(info, "w", force_zip64=info.file_size >= 1 << 31) as target:
                while data := source.read(block):
                    target.write(data)
                    if chunk := sink.take():
                        yield chunk
            if chunk := sink.take():
                yield chunk
    if chunk := sink.take():
        yield chunk


# --- results from a worker on another machine ---------------------------------------------
@router.put(
    "/{job_id}/results",
    response_model=ResultsReceived,
    dependencies=[TokenDep],
    responses={
        404: {"model": Problem},
        409: {"model": Problem, "description": "the job is not running under this worker"},
        403: {"model": Problem, "description": "the job is another rig's"},
        422: {"model": Problem, "description": "the archive cannot be read, or a member would land elsewhere"},
        503: {"model": Problem},
        507: {"model": Problem},
        **WRITE_ERRORS,
    },
    openapi_extra={"requestBody": {"content": {TAR_TYPE: {"schema": {"type": "string", "format": "binary"}}}}},
)
async def receive_results(
    job_id: str,
    request: Request,
    catalog: CatalogDep,
    worker_id: Annotated[str, Query(min_length=1, max_length=200, description="the worker that holds the job")],
) -> ResultsReceived:
    """A worker that does not share this daemon's disk sends its job's results (a tar archive,
    ``application/x-tar``): they are kept beside the run file, as a worker on this disk would
    have written them, and the answer says where each file is (for the job's artifacts)."""
    job = await run_in_threadpool(catalog.get_job, job_id)
    if job.state != "running" or job.claimed_by != worker_id:
        raise JobClaimError(job_id, worker_id, job.state, job.claimed_by)
    run = await run_in_threadpool(catalog.get_run, job.run_id)
    if run.rig != catalog.rig:
        raise OtherRigError(run.id, run.rig, catalog.rig, f"keep the results of job {job_id}")
    if not run.path:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"run {run.id} has no run file to keep results beside")
    run_path = Path(run.path)
    folder = run_path.parent
    archive = folder / f".upload-{job_id}.tar"
    try:
        with archive.open("wb") as out:
            async for chunk in request.stream():
                await run_in_threadpool(out.write, chunk)
        files = await run_in_threadpool(
            unpack_results, archive, folder, {run_path.name, run_path.name + ".lock", archive.name}
        )
    except OSError as exc:
        raise storage_error(exc, archive) from None
    finally:
        archive.unlink(missing_ok=True)
    return ResultsReceived(result_dir=str(folder), files=files)
