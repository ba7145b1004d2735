"""The demo's run: the daemon and the worker started, the sweep and its processing through the
REST API, everything stopped, the result scored (the steps :mod:`acquisition.demo` lists)."""

from __future__ import annotations

import contextlib
import json
import secrets
import signal
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any, NoReturn

import httpx
from rich.console import Console
from rich.progress import (
    BarColumn,
    Progress,
    TaskProgressColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from acquisition.daemon.catalog import Catalog
from acquisition.demo.folder import new_data_dir, shown, write_config
from acquisition.demo.processes import Child, DemoError, child_env, free_port
from acquisition.demo.summary import DemoResult
from acquisition.demo.truth import aperture_used, score_light_model, truth_and_layout
from drivers.contracts.rig import RIGS_DIR
from sim_devices.lights import TruthLight

#: The demo's default rig: the default geometry at half the resolution (rigs/demo.toml).
DEMO_RIG_PATH = RIGS_DIR / "demo.toml"
#: The bracket of ``mirrorgonio bench accuracy`` (its reference simulation), so that the
#: demo's accuracy can be compared with that benchmark's figures.
DEMO_EXPOSURES_S = (2e-5, 1e-4, 5e-4, 2.5e-3, 1.25e-2)
#: The accuracy target for a run with noise (``docs/measurement.md``, "The estimators").
TARGET_WITH_NOISE = 0.01
FINAL_RUN_STATES = ("complete", "aborted", "failed", "interrupted")
FINAL_JOB_STATES = ("complete", "failed")


@dataclass
class _Session:
    """What :func:`_shutdown` must stop or close, however the demo ends."""

    console: Console
    children: list[Child] = field(default_factory=list)
    client: httpx.Client | None = None
    run_id: str | None = None


def run_demo(
    *,
    root: Path = Path("demo-data"),
    rig: Path | None = None,
    positions: int | None = None,
    workers: int | None = None,
    keep: int = 1,
    truth_layout: bool = False,
    console: Console | None = None,
) -> DemoResult:
    """Run the whole chain once (:mod:`acquisition.demo`); raises :class:`DemoError` on failure.

    Parameters
    ----------
    root : Path
        Where demo folders go (one per call).
    rig : Path, optional
        The rig (default :data:`DEMO_RIG_PATH`).
    positions : int, optional
        Take only the first positions of the sweep (default: all).
    workers : int, optional
        Dask worker processes of the worker's local cluster (default: the cores).
    keep : int
        Older demo folders kept under ``root``.
    truth_layout : bool
        Give the worker the simulated truth's source layout; by default it finds the
        sources in the data, and each is scored against the nearest source found.
    """
    console = console or Console()
    started = time.perf_counter()
    rig_path = Path(rig or DEMO_RIG_PATH).resolve()
    rig_model, truth, layout = truth_and_layout(rig_path)
    folder = new_data_dir(Path(root), keep, note=lambda m: console.print(m, highlight=False)).resolve()
    config = write_config(folder, rig_path)
    cam = rig_model.camera
    frame = f"{cam.width}x{cam.height}"
    console.print(f"demo folder {folder}\nrig {rig_path} ({frame} frames), truth {truth.name}", highlight=False)

    session = _Session(console)
    interrupted = False
    with _sigterm_as_interrupt():
        try:
            daemon, worker = _start_children(session, config, folder, workers)
            run, acquire_s = _acquire(session, daemon, truth.name, positions)
            job, layout_note, process_s = _process(session, worker, layout if truth_layout else None)
            run_file, artifacts = _paths_from_catalog(folder / "data" / "catalog.sqlite", run["id"], job["id"])
            pids = {c.name: c.pid for c in session.children}
        except KeyboardInterrupt:
            interrupted = True
            raise
        finally:
            _shutdown(console, session.children, session.client, session.run_id, interrupted)

    if "light_model" not in artifacts:
        raise DemoError(f"job {job['id']} wrote no light model (artifacts: {', '.join(artifacts) or 'none'})")
    result = _scored(
        truth,
        data_dir=folder,
        rig=rig_path,
        run_id=run["id"],
        job_id=job["id"],
        positions=int(run["n_positions"]),
        frame=frame,
        run_file=run_file,
        artifacts=artifacts,
        target=TARGET_WITH_NOISE if rig_model.simulation.noise else None,
        acquire_s=acquire_s,
        process_s=process_s,
        total_s=time.perf_counter() - started,
        job_message=job.get("message") or "",
        pids=pids,
        layout=f"given to the worker: {shown(layout)}"
        if truth_layout and not layout_note
        else "found in the data by the worker",
    )
    (folder / "summary.json").write_text(json.dumps(result.to_json(), indent=2, allow_nan=True) + "\n")
    return result


def _scored(truth: TruthLight, **fields: Any) -> DemoResult:
    """The demo's result: ``fields`` and the light model the worker wrote scored against ``truth``."""
    light_model = fields["artifacts"]["light_model"]
    accuracy = score_light_model(light_model, truth)
    errors = [s.rms_rel_error for s in accuracy]
    worst = max(errors) if errors and all(e == e for e in errors) else float("nan")  # NaN: a source unscored
    return DemoResult(accuracy=accuracy, max_rms_rel_error=worst, aperture=aperture_used(light_model), **fields)


# --- the daemon and the worker ---------------------------------------------------------------------
def _start_children(session: _Session, config: Path, folder: Path, workers: int | None) -> tuple[Child, Child]:
    """The daemon, answering, then the worker; their pids and logs said."""
    daemon, port = _start_daemon(session, config, folder)
    worker = _start_worker(session, config, folder, workers)
    session.console.print(
        f"daemon pid {daemon.pid} on http://127.0.0.1:{port} (log {shown(daemon.log_path)}), "
        f"worker pid {worker.pid} (log {shown(worker.log_path)})",
        highlight=False,
    )
    return daemon, worker


def _start_daemon(session: _Session, config: Path, folder: Path) -> tuple[Child, int]:
    """``mirrorgonio serve`` with a random API token, and a client that carries it: the daemon
    and its port once it answers. A port another program took first is tried again (three times)."""
    token = secrets.token_urlsafe(24)
    with session.console.status("starting the daemon and the simulated devices"):
        for attempt in range(3):
            port = free_port()  # another program may take it before the daemon does: try again
            daemon = Child(
                "daemon",
                ["serve", "--config", str(config), "--port", str(port)],
                folder / "daemon.log",
                child_env(token),
            )
            session.children.append(daemon)
            # JSON, body or none: the daemon takes nothing else for a request that changes something.
            headers = {"Authorization": f"Bearer {token}", "Content-Type": "application/json"}
            session.client = httpx.Client(base_url=f"http://127.0.0.1:{port}", headers=headers, timeout=30.0)
            try:
                _wait_for_daemon(session.client, daemon)
                break
            except DemoError:
                if attempt == 2 or "address already in use" not in daemon.log_tail().lower():
                    raise
                session.client.close()
                daemon.stop(5.0)
                session.children.remove(daemon)
    return daemon, port


def _start_worker(session: _Session, config: Path, folder: Path, workers: int | None) -> Child:
    """``mirrorgonio worker``: it opens the catalog the daemon has created, and starts its Dask
    cluster while the sweep is acquired."""
    worker_args = ["worker", "--config", str(config), "--poll", "0.5", "--heartbeat", "1", "--id", "demo-worker"]
    if workers:
        worker_args += ["--workers", str(workers)]
    worker = Child("worker", worker_args, folder / "worker.log", child_env())
    session.children.append(worker)
    return worker


def _wait_for_daemon(client: httpx.Client, daemon: Child, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        daemon.check()
        try:
            client.get("/health", timeout=2.0)
            return
        except httpx.HTTPError:
            time.sleep(0.2)
    raise DemoError(
        f"the daemon did not answer within {timeout:.0f} s: see its log, {daemon.log_path}", daemon.log_tail()
    )


# --- the sweep and its processing, through the REST API ---------------------------------------------
def _answer(response: httpx.Response, what: str) -> dict:
    if response.status_code >= 400:
        try:
            detail = response.json().get("detail", response.text)
        except ValueError:
            detail = response.text
        raise DemoError(f"{what}: HTTP {response.status_code}: {' '.join(str(detail).split())}")
    return response.json()


def _progress_columns() -> tuple:
    return (
        TextColumn("{task.description:<10}"),
        BarColumn(bar_width=30),
        TaskProgressColumn(),
        TextColumn("{task.fields[note]:<18}"),
        TimeElapsedColumn(),
        TextColumn("eta"),
        TimeRemainingColumn(),
    )


def _acquire(session: _Session, daemon: Child, truth_name: str, positions: int | None) -> tuple[dict, float]:
    """The default light sweep (``POST /runs``), followed with a progress bar: the finished run,
    and the seconds it took."""
    console, client = session.console, session.client
    assert client is not None  # opened by _start_children
    started = time.perf_counter()
    body: dict = {
        "preset": "light-sweep",
        "bracket": {"mode": "fixed", "exposures_s": list(DEMO_EXPOSURES_S)},
        "operator": "mirrorgonio demo",
        "light_source": f"simulated: {truth_name}",
        "notes": "the default light sweep on the simulated rig",
    }
    if positions:
        body["count"] = int(positions)
    run = _answer(client.post("/runs", json=body), "POST /runs")
    run_id = session.run_id = run["id"]
    console.print(
        f"run {run_id}: {run['n_positions']} positions x {len(DEMO_EXPOSURES_S)} exposures (POST /runs)",
        highlight=False,
    )
    with Progress(*_progress_columns(), console=console, transient=False) as bar:
        task = bar.add_task("acquiring", total=run["n_positions"], note="")
        while True:
            daemon.check()
            run = _answer(client.get(f"/runs/{run_id}"), f"GET /runs/{run_id}")
            bar.update(
                task,
                completed=run["positions_done"],
                total=run["n_positions"],
                note=f"{run['positions_done']} of {run['n_positions']} positions",
            )
            if run["state"] in FINAL_RUN_STATES:
                break
            time.sleep(0.5)
    seconds = time.perf_counter() - started
    if run["state"] != "complete":
        raise DemoError(
            f"run {run_id} ended {run['state']}: {run.get('last_error') or 'no reason given'} "
            f"(daemon log {daemon.log_path})"
        )
    return run, seconds


def _process(session: _Session, worker: Child, layout: Path | None) -> tuple[dict, str, float]:
    """The run's processing queued for the worker (``POST /runs/{id}/process``) and followed
    with a progress bar: the finished job, a note when the daemon refused the layout, and the
    seconds it took."""
    console, client, run_id = session.console, session.client, session.run_id
    assert client is not None and run_id is not None  # opened by _start_children, set by _acquire
    started = time.perf_counter()
    job, layout_note = _post_job(client, run_id, layout)
    if layout_note:
        console.print(f"note: {layout_note}", highlight=False)
    job_id = job["id"]
    console.print(f"job {job_id}: {job['steps']} (POST /runs/{run_id}/process), for the worker", highlight=False)
    with Progress(*_progress_columns(), console=console, transient=False) as bar:
        task = bar.add_task("processing", total=1.0, note="queued")
        while True:
            worker.check()
            job = _answer(client.get(f"/jobs/{job_id}"), f"GET /jobs/{job_id}")
            note = job["state"] if job["state"] in FINAL_JOB_STATES else (job.get("message") or job["state"])
            bar.update(
                task, completed=1.0 if job["state"] == "complete" else job.get("progress") or 0.0, note=note[:30]
            )
            if job["state"] in FINAL_JOB_STATES:
                break
            time.sleep(0.5)
    seconds = time.perf_counter() - started
    if job["state"] != "complete":
        raise DemoError(f"job {job_id} failed: {job.get('error')} (worker log {worker.log_path})")
    return job, layout_note, seconds


def _post_job(client: httpx.Client, run_id: str, layout: Path | None) -> tuple[dict, str]:
    """Queue the run's processing with the rig's noise model (as ``bench accuracy`` does)
    and, if given, the truth's source layout. A daemon whose job requests do not take those
    options gets the job without them: the worker then finds the sources in the data, and
    each truth emitter is scored against the nearest source found (the note says so)."""
    what = f"POST /runs/{run_id}/process"
    request = {"steps": "hdr,sources", "noise": "rig"} | ({"layout": str(layout)} if layout is not None else {})
    response = client.post(f"/runs/{run_id}/process", json=request)
    if response.status_code == 422 and ("layout" in response.text or "noise" in response.text):
        response = client.post(f"/runs/{run_id}/process", json={"steps": "hdr,sources"})
        return _answer(response, what), (
            "this daemon's job requests take no layout or noise option: the worker finds "
            "the sources in the data, and each truth source is scored against the nearest found"
        )
    return _answer(response, what), ""


def _paths_from_catalog(catalog_path: Path, run_id: str, job_id: str) -> tuple[Path, dict[str, Path]]:
    """The run file and the job's result files (the API gives their URLs; the paths are in the catalog)."""
    with contextlib.closing(Catalog(catalog_path)) as catalog:
        run = catalog.get_run(run_id)
        job = catalog.get_job(job_id)
    if run.path is None:
        raise DemoError(f"run {run_id} has no run file in the catalog")
    return Path(run.path), {kind: Path(path) for kind, path in job.artifacts.items()}


# --- the end, however it comes -------------------------------------------------------------------
def _is_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _terminate_as_interrupt(signum: int, frame: FrameType | None) -> NoReturn:
    raise KeyboardInterrupt


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM raises KeyboardInterrupt inside (the main thread only), so that the demo stops
    its children as on Ctrl-C; the previous handler is restored on the way out."""
    previous = None
    if sys.platform != "win32" and _is_main_thread():
        previous = signal.signal(signal.SIGTERM, _terminate_as_interrupt)
    try:
        yield
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _shutdown(
    console: Console, children: list[Child], client: httpx.Client | None, run_id: str | None, interrupted: bool
) -> None:
    """Abort an unfinished run, then stop the worker and the daemon (in that order)."""
    if client is not None:
        if interrupted and run_id is not None:
            with contextlib.suppress(Exception):
                client.post(f"/runs/{run_id}/abort", timeout=5.0)
        client.close()
    if not children:
        return
    # A second Ctrl-C while stopping must not leave them running: finish stopping first.
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if _is_main_thread() else None
    try:
        with console.status("stopping the worker and the daemon"):
            for child in reversed(children):
                child.stop(timeout=30.0 if child.name == "worker" else 20.0)
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
    console.print("stopped the worker and the daemon" + (" (interrupted)" if interrupted else ""), highlight=False)
