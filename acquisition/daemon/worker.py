"""The processing worker: takes queued jobs from the catalog and processes their runs.

``mirrorgonio worker`` runs :class:`JobWorker` in a loop (``docs/daemon.md``, "Worker"):

1. put back in the queue the running jobs whose worker stopped sending heartbeats (it
   died: :meth:`~acquisition.daemon.catalog.Catalog.requeue_stale_jobs`);
2. claim the oldest queued job (atomic: two workers never get the same job);
3. if its run is still being acquired, put it back to wait (it is not failed), unless the
   job asked for ``partial``: then only the positions complete now are processed;
4. process the run (``processing.light_run.run.process_run``, positions in parallel on the
   worker's Dask cluster) while a thread sends a heartbeat with the progress every few
   seconds; the results go beside the run file. A worker that cannot see the run file at
   its path (another machine, no shared disk) fetches it from its rig's daemon first and
   sends the results back to it after (:mod:`acquisition.daemon.transfer`); a daemon it
   cannot reach puts the job back to wait;
5. record the job ``complete`` with its result files (report, IES, LDT, TM-25 ray file,
   light model, results file), or ``failed`` with the reason in one line, and go on with
   the next job.

A worker that finds its job was taken from it (its heartbeats stopped long enough for
another worker to requeue and claim it) abandons the job without recording anything.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import socket
import threading
import time
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

from acquisition.daemon.catalog import (
    ACTIVE_RUN_STATES,
    Catalog,
    CatalogError,
    CatalogUnavailableError,
    JobClaimError,
    JobRecord,
    RunRecord,
)
from acquisition.daemon.client_files import ClientFileError, load_client_file
from acquisition.daemon.models import JOB_OPTIONS
from acquisition.daemon.transfer import DaemonUnreachableError, RunFetcher
from drivers.contracts.runfile import RunFile, RunFileError
from processing import (
    Compute,
    ComputeError,
    CorruptRunError,
    HDRError,
    OptionsError,
    ProcessingError,
    ProcessingOptions,
    ProcessReport,
    ResultsError,
    Step,
    StepsError,
    layout_from_dict,
    overall_fraction,
    process_run,
    resolve_steps,
    skipped_line,
)
from processing import describe_progress as describe

log = logging.getLogger("mirrorgonio.worker")

#: The run file states of a run whose writer may still be adding positions.
ACQUIRING_FILE_STATES = ("created", "running", "paused")
#: The result files a job records, by kind: the daemon serves exactly these.
ARTIFACT_KINDS = ("report", "ies", "ldt", "tm25", "light_model", "results")


class JobLostError(RuntimeError):
    """This worker no longer holds the job it is processing."""


def one_line(exc: BaseException, limit: int = 1000) -> str:
    """An exception as the one-line reason a failed job records."""
    domain = (ProcessingError, RunFileError, ResultsError, HDRError, StepsError, ComputeError, CatalogError, OSError)
    text = " ".join(str(exc).split())
    if not isinstance(exc, domain) or not text:
        text = f"{type(exc).__name__}: {text}" if text else type(exc).__name__
    return text if len(text) <= limit else text[: limit - 1] + "…"


def writer_alive(run_path: str | Path) -> bool:
    """Whether a process holds the run file's writer lock (``RUN.h5.lock``) now.

    Probed with a non-blocking shared ``flock``, released at once; only called for a run
    the catalog no longer counts as being acquired (so no writer should be starting).
    """
    lock = Path(str(run_path) + ".lock")
    try:
        fd = os.open(lock, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError as exc:
        return exc.errno in (errno.EWOULDBLOCK, errno.EACCES)
    else:
        fcntl.flock(fd, fcntl.LOCK_UN)
        return False
    finally:
        os.close(fd)


def default_worker_id() -> str:
    return f"{socket.gethostname()}-{os.getpid()}"


class JobWorker:
    """Claims and processes jobs, one at a time, with a heartbeat while each runs.

    Parameters
    ----------
    catalog : Catalog
        The catalog (``DATA_DIR/catalog.sqlite``), opened in this process.
    compute : processing.parallel.Compute, optional
        Where the position tasks run (a Dask cluster); default: in this process.
    worker_id : str, optional
        How the catalog names this worker (default ``HOST-PID``).
    heartbeat_s : float
        Seconds between heartbeats while a job runs.
    stale_after_s : float
        A running job without a heartbeat for this long is taken for orphaned (its worker
        died) and requeued; keep it several heartbeats long.
    wait_s : float
        How long a job whose run is still being acquired waits before it is tried again.
    process : callable, optional
        ``process(job, run_path, steps, progress) -> (result_dir, artifacts, message)``, where
        ``progress(step, done, total)`` as ``process_run`` calls it; the default runs
        ``processing.light_run.run.process_run`` (tests substitute their own).
    fetcher : RunFetcher, optional
        Fetches the run files this worker cannot see at their paths from their rigs'
        daemons, and sends the results back; without one, such a job fails (no such file).
    rigs : list of str, optional
        Take only the jobs of these rigs (default: any rig's).
    """

    def __init__(
        self,
        catalog: Catalog,
        compute: Compute | None = None,
        *,
        worker_id: str | None = None,
        heartbeat_s: float = 5.0,
        stale_after_s: float = 60.0,
        wait_s: float = 10.0,
        process: Callable | None = None,
        fetcher: RunFetcher | None = None,
        rigs: list[str] | None = None,
    ):
        if heartbeat_s <= 0 or stale_after_s <= 0 or wait_s < 0:
            raise ValueError("heartbeat_s and stale_after_s must be > 0, wait_s >= 0")
        self.catalog = catalog
        self.compute = compute if compute is not None else Compute()
        self.worker_id = worker_id or default_worker_id()
        self.heartbeat_s = float(heartbeat_s)
        self.stale_after_s = float(stale_after_s)
        self.wait_s = float(wait_s)
        self._process = process or self._process_run
        self.fetcher = fetcher
        self.rigs = rigs
        self._progress: float | None = None
        self._note: str | None = None
        self._step: str | None = None
        self._steps_seen: set[str] = set()
        self._lost = threading.Event()

    # --- the loop ------------------------------------------------------------------------
    def run(
        self,
        stop: threading.Event | None = None,
        *,
        once: bool = False,
        poll_s: float = 2.0,
        on_job: Callable[[JobRecord], None] | None = None,
    ) -> int:
        """Process jobs until ``stop`` is set (or, with ``once``, until none can be claimed).

        Returns
        -------
        int
            The number of jobs this worker ended (complete or failed).
        """
        stop = stop or threading.Event()
        ended = 0
        waiting: set[str] = set()
        repeats = 0  # waiting jobs claimed again in a row, with nothing else to do in between
        while not stop.is_set():
            try:
                job = self.run_once()
            except CatalogUnavailableError as exc:  # the server restarts, the network is cut: try again
                log.warning("%s: the catalog cannot be reached: %s", self.worker_id, exc)
                stop.wait(poll_s)
                continue
            if job is not None and on_job is not None:
                on_job(job)
            if job is not None and job.state in ("complete", "failed"):
                ended += 1
                repeats = 0
                continue
            if job is None:
                if once:
                    break  # nothing left that can run now
            elif job.state == "queued":  # it waits for its run
                repeats = repeats + 1 if job.id in waiting else 0
                waiting.add(job.id)
                if once:
                    if repeats > len(waiting):
                        break  # only waiting jobs are left
                    continue
            stop.wait(poll_s)
        return ended

    def run_once(self) -> JobRecord | None:
        """Requeue orphaned jobs, claim one and handle it.

        Returns
        -------
        JobRecord or None
            The job after handling (``complete``, ``failed``, or ``queued`` again when it
            waits for its run), or None when no job could be claimed.
        """
        requeued = self.catalog.requeue_stale_jobs(self.stale_after_s)
        if requeued:
            log.warning("requeued jobs whose worker stopped sending heartbeats: %s", ", ".join(requeued))
        job = self.catalog.claim_job(self.worker_id, rigs=self.rigs)
        if job is None:
            return None
        log.info("%s: claimed job %s (run %s, steps %s)", self.worker_id, job.id, job.run_id, job.steps)
        return self.handle(job)

    # --- one job ---------------------------------------------------------------------------
    def handle(self, job: JobRecord) -> JobRecord:
        """Process one claimed job and record how it ended."""
        try:
            steps = resolve_steps(job.steps)
            run = self.catalog.get_run(job.run_id)
        except CatalogUnavailableError:
            raise  # not the job's fault: without heartbeats it is requeued, or claimed again by this worker
        except (StepsError, CatalogError) as exc:
            return self._fail(job, one_line(exc))
        remote = self.fetcher is not None and RunFetcher.is_remote(run)  # without a fetcher: processing says
        not_now = self._not_now(job, run, remote)
        if not_now is not None:
            return not_now
        self._progress, self._note, self._step = 0.0, None, None
        self._steps_seen.clear()
        self._lost.clear()
        stop = threading.Event()
        beat = threading.Thread(target=self._heartbeats, args=(job, stop), name=f"heartbeat-{job.id}", daemon=True)
        beat.start()
        keep_copy = False
        try:
            result_dir, artifacts, message = self._fetch_process_send(job, run, steps, remote)
        except (DaemonUnreachableError, CatalogUnavailableError) as exc:  # away for now: the job waits
            keep_copy = True  # the next try resumes the fetch where it stopped
            stop.set()
            return self._wait(job, f"waiting: {one_line(exc)}")
        except JobLostError:
            log.warning("%s: job %s was taken from this worker: abandoned", self.worker_id, job.id)
            return self.catalog.get_job(job.id)
        except Exception as exc:  # noqa: BLE001 - any failure is the job's, never the worker's
            reason = one_line(exc)
            if not isinstance(exc, ValueError | OSError):  # not a domain error: keep the traceback
                log.error("job %s: unexpected error", job.id, exc_info=True)
            if self._lost.is_set():
                return self.catalog.get_job(job.id)
            return self._fail(job, reason)
        finally:
            stop.set()
            beat.join()
            if remote and self.fetcher is not None and not keep_copy:
                self.fetcher.forget(run)
        if self._lost.is_set():
            log.warning("%s: job %s was taken from this worker: its results are not recorded", self.worker_id, job.id)
            return self.catalog.get_job(job.id)
        try:
            done = self._persistently(
                self.catalog.finish_job,
                job.id,
                worker_id=self.worker_id,
                result_dir=result_dir,
                artifacts=artifacts,
                message=message,
            )
        except JobClaimError as exc:
            log.warning("%s: %s", self.worker_id, exc)
            return self.catalog.get_job(job.id)
        log.info("job %s complete: %s; %s", job.id, message, ", ".join(f"{k} {v}" for k, v in artifacts.items()))
        return done

    def _not_now(self, job: JobRecord, run: RunRecord, remote: bool) -> JobRecord | None:
        """The job put back to wait or failed, if it cannot be processed now (its layout file
        cannot be read, its run is being acquired, it asks for partial processing of a run
        whose file is not on this disk: ``remote``); None when it can."""
        if job.options.get("layout") is not None:
            try:  # the client's path: read here, with a time limit, before the job is started
                load_client_file(str(job.options["layout"]), "layout", "layout file", _layout)
            except ClientFileError as exc:
                return self._fail(job, str(exc))
        acquiring = self._acquiring(run)
        if acquiring and not job.options.get("partial", False):
            return self._wait(
                job,
                f"waiting: run {run.id} is still being acquired ({acquiring}); "
                "ask for partial to process the positions complete so far",
            )
        if not run.path:
            return self._fail(job, f"run {run.id} has no run file")
        if acquiring and remote:
            return self._fail(
                job,
                f"partial processing needs the run file on the worker's disk: run {run.id} is still being acquired "
                f"on rig {run.rig}, and {run.path} is not here (a worker that shares that disk can process it)",
            )
        if acquiring and not _has_complete_position(Path(run.path)):
            return self._wait(
                job, f"waiting: run {run.id} is being acquired ({acquiring}) and has no complete position yet"
            )
        return None

    def _fetch_process_send(
        self, job: JobRecord, run: RunRecord, steps: tuple[Step, ...], remote: bool
    ) -> tuple[str | Path, dict[str, str], str]:
        """Process the run in place, or (``remote``) fetched from its daemon with the results sent
        back: (result folder, artifacts, message) as the daemon will serve them."""
        path = Path(str(run.path))
        if remote:
            assert self.fetcher is not None
            self._note = f"fetching run {run.id} from rig {run.rig}'s daemon"
            path = self.fetcher.fetch(run)
        result_dir, artifacts, message = self._process(job, path, steps, self._report_progress)
        files = {kind: str(file) for kind, file in artifacts.items()}
        if remote and not self._lost.is_set():
            assert self.fetcher is not None
            self._note = f"sending the results to rig {run.rig}'s daemon"
            result_dir, files = self.fetcher.send_results(job.id, self.worker_id, run, path, files)
        return result_dir, files, message

    def _acquiring(self, run: RunRecord) -> str:
        """Why the run is still being acquired ("" if it is not)."""
        if run.state in ACTIVE_RUN_STATES:
            return f"its state is {run.state}"
        if not run.path:
            return ""
        try:
            with RunFile.open(run.path) as f:
                status = f.status
        except (RunFileError, OSError):
            return ""  # the processing says what is wrong with the file
        if status in ACQUIRING_FILE_STATES and writer_alive(run.path):
            return f"its run file says {status} and a writer holds it"
        return ""

    def _wait(self, job: JobRecord, message: str) -> JobRecord:
        log.info("job %s: %s", job.id, message)
        return self._persistently(
            self.catalog.release_job, job.id, self.worker_id, message=message, retry_after_s=self.wait_s
        )

    def _fail(self, job: JobRecord, reason: str) -> JobRecord:
        log.warning("job %s failed: %s", job.id, reason)
        try:
            return self._persistently(self.catalog.finish_job, job.id, worker_id=self.worker_id, error=reason)
        except JobClaimError as exc:
            log.warning("%s: %s", self.worker_id, exc)
            return self.catalog.get_job(job.id)

    def _persistently(self, write: Callable[..., JobRecord], *args: Any, **kwargs: Any) -> JobRecord:
        """A job's end written to the catalog, retried while the catalog cannot be reached for as
        long as the job stays this worker's (``stale_after_s``: past that it is requeued anyway)."""
        deadline = time.monotonic() + self.stale_after_s
        while True:
            try:
                return write(*args, **kwargs)
            except CatalogUnavailableError as exc:
                if time.monotonic() > deadline:
                    raise
                log.warning("%s: recording job %s waits for the catalog: %s", self.worker_id, args[0], exc)
                time.sleep(min(2.0, self.heartbeat_s))

    def _report_progress(self, step: str, done: int, total: int) -> None:
        """``process_run``'s progress, kept for the next heartbeat: the job's ``step`` (the one
        started last: the light files end while the report, started after them, runs), its
        ``message`` in words and its share of the whole processing (which never goes back).
        Raises if the job was lost."""
        if self._lost.is_set():
            raise JobLostError("the job was requeued and claimed by another worker")
        self._progress = max(self._progress or 0.0, min(0.99, overall_fraction(step, done, total)))
        if done == 0 or step not in self._steps_seen:
            self._step = step
            self._steps_seen.add(step)
        if step == self._step:
            self._note = describe(step, done, total)

    def _heartbeats(self, job: JobRecord, stop: threading.Event) -> None:
        while not stop.wait(self.heartbeat_s):
            try:
                self.catalog.heartbeat(
                    job.id, self.worker_id, progress=self._progress, message=self._note, step=self._step
                )
            except JobClaimError as exc:
                log.warning("%s: %s", self.worker_id, exc)
                self._lost.set()
                return
            except CatalogError as exc:  # a busy or unreachable catalog: the next beat may pass
                log.warning("job %s: heartbeat failed: %s", job.id, exc)

    # --- the processing --------------------------------------------------------------------
    def _process_run(
        self, job: JobRecord, run_path: Path, steps: tuple[Step, ...], progress: Callable[[str, int, int], None]
    ) -> tuple[Path, dict[str, str | Path], str]:
        """Process the job's run beside its run file: (result folder, artifacts, message)."""
        options = job.options
        try:
            report = self._processed(run_path, steps, progress, options)
        except CorruptRunError as exc:  # the job's own name for the choice that processes the rest
            raise ProcessingError(exc.line("the job option ignore_corrupt")) from None
        artifacts = {"results": report.results_file}
        if report.light_model is not None:
            artifacts["light_model"] = report.light_model
        for kind in ("report", "ies", "ldt", "tm25"):
            if report.outputs.get(kind):
                artifacts[kind] = report.outputs[kind][0]
        seconds = report.timings.get("total", 0.0)
        message = (
            f"{report.positions} of {report.n_positions} positions"
            f"{' (partial: the run was still being acquired)' if report.partial and job.options.get('partial') else ''}"
            f" in {seconds:.1f} s on {report.compute}"
        )
        if report.skipped_corrupt:  # ignore_corrupt: what the run file failed to give back
            message += f"; {skipped_line(report.skipped_corrupt, 'ignore_corrupt')}"
        if report.quality is not None:  # the verdict first: a job's note is where the lab looks
            message = f"{report.quality.line()}; {message}"
        return run_path.parent, {k: str(v) for k, v in artifacts.items()}, message

    def _processed(
        self, run_path: Path, steps: tuple[Step, ...], progress: Callable[[str, int, int], None], options: dict
    ) -> ProcessReport:
        """``process_run`` with the job's options, its results beside the run file."""
        checked = job_processing_options(options, steps)
        return process_run(run_path, run_path.parent, checked, progress=progress, compute=self.compute)


def job_processing_options(options: dict, steps: tuple[Step, ...]) -> ProcessingOptions:
    """A job's options (as the API took them) and its resolved steps as the processing's options.

    Raises
    ------
    ProcessingError
        An option the processing refuses (one line, as the processing's own errors).
    """
    try:
        return ProcessingOptions.checked(
            **{o.name: options.get(o.public) for o in JOB_OPTIONS if o.name != "steps"},  # None: the default
            steps=steps,  # the job's steps as the worker resolved them
        )
    except OptionsError as exc:
        raise ProcessingError(str(exc)) from None


def _layout(text: str) -> list:
    """A layout file's text as its sources; ``ValueError`` if it is not one."""
    return layout_from_dict(tomllib.loads(text), "layout")


def _has_complete_position(path: Path) -> bool:
    try:
        with RunFile.open(path) as f:
            return bool(f.complete.any())
    except (RunFileError, OSError):
        return True  # let the processing report what is wrong with the file


def serve_jobs(
    catalog_url: str | Path,
    compute: Compute,
    *,
    stop: threading.Event | None = None,
    once: bool = False,
    poll_s: float = 2.0,
    on_job: Callable[[JobRecord], None] | None = None,
    fetch_to: Path | None = None,
    token: str | None = None,
    **options: Any,
) -> int:
    """Open the catalog and run a :class:`JobWorker` on it (``mirrorgonio worker``); run files
    not on this disk are fetched into ``fetch_to`` (with the daemons' ``token``) if given."""
    with contextlib.closing(Catalog(catalog_url)) as catalog:
        fetcher = RunFetcher(catalog.daemon_url, fetch_to, token) if fetch_to is not None else None
        worker = JobWorker(catalog, compute, fetcher=fetcher, **options)
        log.info("worker %s: jobs from %s, compute on %s", worker.worker_id, catalog.path, worker.compute.description)
        started = time.monotonic()
        ended = worker.run(stop, once=once, poll_s=poll_s, on_job=on_job)
        log.info("worker %s: %d jobs in %.0f s", worker.worker_id, ended, time.monotonic() - started)
        return ended
