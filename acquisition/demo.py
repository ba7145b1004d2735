"""``mirrorgonio demo``: the whole chain on simulated devices, as a lab runs it.

1. A fresh data folder (``demo-data/YYYYmmdd-HHMMSS/``) with a ``daemon.toml``: the
   simulated rig (the simulated stage served over Modbus TCP on loopback and driven by the
   real ``ModbusArm``, the simulated camera writing DNG files), on a free loopback port,
   with a random API token.
2. ``mirrorgonio serve`` and ``mirrorgonio worker`` as child processes, each in its own
   session (a Ctrl-C in the terminal reaches only this program, which stops them in
   order); on Linux they also get SIGTERM should this program die.
3. The default light sweep through the REST API (``POST /runs`` with the token), followed
   with a progress bar; then ``POST /runs/{id}/process``, and the worker's job followed
   the same way. The worker finds the sources in the data, as it would for a lab's
   unknown lamp (``truth_layout=True`` gives it the simulated truth's layout instead).
4. The worker and the daemon are stopped (SIGTERM, then SIGKILL of their whole process
   group if they linger), also on Ctrl-C or an error: no process is left behind.
5. The light model the worker wrote is scored against the simulated truth as
   ``mirrorgonio bench accuracy`` scores it: ``RMS(I_fit − I_true) / max(I_true)`` per
   source over the θ range its samples cover.

Older demo folders are removed (the newest ``keep`` of them stay); only folders this
module made (they hold :data:`MARKER`) are ever removed.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

from drivers.contracts.rig import RIGS_DIR

#: The demo's default rig: the default geometry at half the resolution (rigs/demo.toml).
DEMO_RIG_PATH = RIGS_DIR / "demo.toml"
#: Every demo folder holds this file; only such folders are cleaned up.
MARKER = ".mirrorgonio-demo"
#: The bracket of ``mirrorgonio bench accuracy`` (its reference simulation), so that the
#: demo's accuracy can be compared with the README's figures.
DEMO_EXPOSURES_S = (2e-5, 1e-4, 5e-4, 2.5e-3, 1.25e-2)
#: The accuracy target of ``measurement.md`` for a run with noise.
TARGET_WITH_NOISE = 0.01
FINAL_RUN_STATES = ("complete", "aborted", "failed", "interrupted")
FINAL_JOB_STATES = ("complete", "failed")


class DemoError(RuntimeError):
    """The demo could not finish: one line naming the log to read; ``details``, the end of that log."""

    def __init__(self, message: str, details: str = ""):
        super().__init__(message)
        self.details = details


@dataclass
class SourceAccuracy:
    name: str
    rms_rel_error: float
    theta_min_deg: float
    theta_max_deg: float
    samples: int
    #: How far the source it was scored against lies from the truth's emitter (0 when the
    #: worker was given the truth's layout).
    offset_m: float = 0.0


@dataclass
class DemoResult:
    """What the demo made and measured (also written as ``summary.json`` in its folder)."""

    data_dir: Path
    rig: Path
    run_id: str
    job_id: str
    positions: int
    frame: str
    run_file: Path
    artifacts: dict[str, Path]
    accuracy: list[SourceAccuracy]
    max_rms_rel_error: float
    target: float | None
    acquire_s: float
    process_s: float
    total_s: float
    job_message: str = ""
    layout: str = ""
    #: The camera's aperture the sources were estimated with (the light model's provenance).
    aperture: str = ""
    pids: dict[str, int] = field(default_factory=dict)

    def to_json(self) -> dict:
        data = asdict(self)
        data["data_dir"], data["rig"], data["run_file"] = str(self.data_dir), str(self.rig), str(self.run_file)
        data["artifacts"] = {kind: str(path) for kind, path in self.artifacts.items()}
        return data


# --- the data folder -------------------------------------------------------------------------
def new_data_dir(root: Path, keep: int = 1, note: Callable[[str], None] = print) -> Path:
    """A fresh, timestamped demo folder under ``root``; older demo folders beyond ``keep`` removed."""
    root.mkdir(parents=True, exist_ok=True)
    previous = sorted(
        (p for p in root.iterdir() if p.is_dir() and (p / MARKER).is_file()),
        key=lambda p: ((p / MARKER).stat().st_mtime_ns, p.name),
    )  # oldest first
    for old in previous[: max(0, len(previous) - keep)]:
        shutil.rmtree(old, ignore_errors=True)
        note(f"removed an older demo folder: {old}")
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    folder, n = root / stamp, 1
    while folder.exists():
        n += 1
        folder = root / f"{stamp}-{n}"
    folder.mkdir()
    (folder / MARKER).write_text("made by `mirrorgonio demo`; removed by a later demo\n")
    return folder


def write_config(folder: Path, rig: Path) -> Path:
    """The daemon's configuration: the simulated rig, data in ``folder/data``."""
    path = folder / "daemon.toml"
    path.write_text(
        "# Written by `mirrorgonio demo` (docs/daemon.md). The token comes from MG_TOKEN.\n"
        f"data_dir = {json.dumps(str(folder / 'data'))}\n"
        f"rig = {json.dumps(str(rig))}\n"
        'host = "127.0.0.1"\n'
        "\n[arm]\n"
        'kind = "simulated"   # the simulated stage over Modbus TCP on loopback, through ModbusArm\n'
        "port = 0\n"
        "\n[arm.simulated]\n"
        "speed_m_s = 1.0\n"
        "accel_m_s2 = 10.0\n"
        "\n[camera]\n"
        'kind = "simulated"\n'
    )
    (folder / "data").mkdir(exist_ok=True)
    return path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# --- child processes -----------------------------------------------------------------------
def _parent_death_signal():
    """Linux: a function for the child, between fork and exec, that asks for SIGTERM when the
    demo dies (``prctl(PR_SET_DEATHSIG)``); looked up here, before the fork, so the child
    imports nothing."""
    if sys.platform != "linux":
        return None
    try:
        import ctypes

        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None

    def set_signal() -> None:  # pragma: no cover - runs in the child
        prctl(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG

    return set_signal


class Child:
    """A ``mirrorgonio`` subcommand in its own session (its process group is its pid), logging to a file."""

    def __init__(self, name: str, args: list[str], log: Path, env: dict[str, str]):
        self.name, self.log_path = name, log
        exe = Path(sys.executable).with_name("mirrorgonio")
        command = [str(exe)] if exe.exists() else [sys.executable, "-m", "acquisition.cli"]
        self._log = open(log, "ab")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen(
            command + args,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env=env,
            start_new_session=True,
            preexec_fn=_parent_death_signal(),
        )

    @property
    def pid(self) -> int:
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

    def log_tail(self, lines: int = 15) -> str:
        try:
            text = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join(text[-lines:])

    def check(self) -> None:
        if not self.alive():
            raise DemoError(
                f"the {self.name} exited (status {self.proc.returncode}): see its log, {self.log_path}", self.log_tail()
            )

    def _group_alive(self) -> bool:
        """Whether a process of its group still runs (zombies, which only wait to be reaped, do not count)."""
        proc = Path("/proc")
        if not proc.is_dir():
            try:
                os.killpg(self.proc.pid, 0)
                return True
            except (ProcessLookupError, PermissionError):
                return False
        for stat in proc.glob("[0-9]*/stat"):
            try:
                text = stat.read_text()
            except OSError:
                continue
            fields = text[text.rfind(")") + 2 :].split()  # state ppid pgrp ... (the name may hold spaces)
            if len(fields) > 2 and fields[0] != "Z" and fields[2] == str(self.proc.pid):
                return True
        return False

    def stop(self, timeout: float) -> None:
        """SIGTERM and wait; then SIGKILL whatever is left of its process group (Dask workers too)."""
        try:
            if self.alive():
                self.proc.terminate()
                with contextlib.suppress(subprocess.TimeoutExpired):
                    self.proc.wait(timeout)
            # The leader did not stop in time, or left processes of its group behind.
            deadline = time.monotonic() + 10.0
            while (self.alive() or self._group_alive()) and time.monotonic() < deadline:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(self.proc.pid, signal.SIGKILL)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    self.proc.wait(0.2)
        finally:
            self._log.close()


def _child_env(token: str | None = None) -> dict[str, str]:
    """This environment without the user's ``MG_*`` settings (the demo's file says everything)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("MG_")}
    env["PYTHONUNBUFFERED"] = "1"
    if token:
        env["MG_TOKEN"] = token
    return env


# --- the REST client -----------------------------------------------------------------------
def _wait_for_daemon(client, daemon: Child, timeout: float = 120.0) -> None:
    import httpx

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


def _answer(response, what: str) -> dict:
    if response.status_code >= 400:
        try:
            detail = response.json().get("detail", response.text)
        except ValueError:
            detail = response.text
        raise DemoError(f"{what}: HTTP {response.status_code}: {' '.join(str(detail).split())}")
    return response.json()


# --- scoring ---------------------------------------------------------------------------------
def score_light_model(light_model: Path, truth) -> list[SourceAccuracy]:
    """Each truth emitter against the fitted source of the same name (else the nearest one),
    scored as ``mirrorgonio bench accuracy`` does, over the θ its samples cover."""
    import math

    import numpy as np

    from acquisition.benchmarks.scoring import score_fit
    from processing.lightmodel import LightModel

    model = LightModel.load(light_model)
    by_name = {s.name: s for s in model.sources}
    scores = []
    for emitter in truth.emitters:
        source = by_name.get(emitter.name)
        if source is None:
            source = min(model.sources, key=lambda s: math.dist(s.centre_m, emitter.centre_m))
        offset = math.dist(source.centre_m, emitter.centre_m)
        theta = np.asarray(source.samples.get("theta", []), dtype=float)
        theta = theta[np.isfinite(theta)]
        if theta.size == 0:
            scores.append(SourceAccuracy(emitter.name, float("nan"), float("nan"), float("nan"), 0, offset))
            continue
        error, lo, hi = score_fit(source.fit, emitter, theta)
        scores.append(SourceAccuracy(emitter.name, error, lo, hi, int(theta.size), offset))
    return scores


def truth_and_layout(rig_path: Path):
    """The rig's simulated truth light and its TOML file (which also serves as the source layout)."""
    from drivers.contracts.rig import load_rig
    from sim_devices.lights import LIGHTS_DIR, load_truth

    rig = load_rig(rig_path)
    name = rig.simulation.truth
    path = Path(name) if Path(name).suffix else LIGHTS_DIR / f"{name}.toml"
    return rig, load_truth(name), path.resolve()


# --- the demo --------------------------------------------------------------------------------
def run_demo(
    *,
    root: Path = Path("demo-data"),
    rig: Path | None = None,
    positions: int | None = None,
    workers: int | None = None,
    keep: int = 1,
    truth_layout: bool = False,
    console=None,
) -> DemoResult:
    """Run the whole chain once (module docstring); raises :class:`DemoError` on failure.

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

    console = console or Console()
    started = time.perf_counter()
    rig_path = Path(rig or DEMO_RIG_PATH).resolve()
    rig_model, truth, layout = truth_and_layout(rig_path)
    folder = new_data_dir(Path(root), keep, note=lambda m: console.print(m, highlight=False)).resolve()
    config = write_config(folder, rig_path)
    token = secrets.token_urlsafe(24)
    cam = rig_model.camera
    frame = f"{cam.width}x{cam.height}"
    console.print(f"demo folder {folder}\nrig {rig_path} ({frame} frames), truth {truth.name}", highlight=False)

    children: list[Child] = []
    run_id = None
    client = None
    interrupted = False
    previous_term = None
    if sys.platform != "win32" and _is_main_thread():
        previous_term = signal.signal(signal.SIGTERM, _terminate_as_interrupt)
    try:
        with console.status("starting the daemon and the simulated devices"):
            for attempt in range(3):
                port = free_port()  # another program may take it before the daemon does: try again
                daemon = Child(
                    "daemon",
                    ["serve", "--config", str(config), "--port", str(port)],
                    folder / "daemon.log",
                    _child_env(token),
                )
                children.append(daemon)
                client = httpx.Client(
                    base_url=f"http://127.0.0.1:{port}", headers={"Authorization": f"Bearer {token}"}, timeout=30.0
                )
                try:
                    _wait_for_daemon(client, daemon)
                    break
                except DemoError:
                    if attempt == 2 or "address already in use" not in daemon.log_tail().lower():
                        raise
                    client.close()
                    daemon.stop(5.0)
                    children.remove(daemon)
        worker_args = ["worker", "--config", str(config), "--poll", "0.5", "--heartbeat", "1", "--id", "demo-worker"]
        if workers:
            worker_args += ["--workers", str(workers)]
        # The worker opens the catalog the daemon has now created, and starts its Dask
        # cluster while the sweep is acquired.
        worker = Child("worker", worker_args, folder / "worker.log", _child_env())
        children.append(worker)
        console.print(
            f"daemon pid {daemon.pid} on http://127.0.0.1:{port} (log {_shown(daemon.log_path)}), "
            f"worker pid {worker.pid} (log {_shown(worker.log_path)})",
            highlight=False,
        )

        # --- acquisition ------------------------------------------------------------------
        body: dict = {
            "preset": "light-sweep",
            "bracket": {"mode": "fixed", "exposures_s": list(DEMO_EXPOSURES_S)},
            "operator": "mirrorgonio demo",
            "light_source": f"simulated: {truth.name}",
            "notes": "the default light sweep on the simulated rig",
        }
        if positions:
            body["count"] = int(positions)
        t_acq = time.perf_counter()
        run = _answer(client.post("/runs", json=body), "POST /runs")
        run_id = run["id"]
        console.print(
            f"run {run_id}: {run['n_positions']} positions x {len(DEMO_EXPOSURES_S)} exposures (POST /runs)",
            highlight=False,
        )
        columns = (
            TextColumn("{task.description:<10}"),
            BarColumn(bar_width=30),
            TaskProgressColumn(),
            TextColumn("{task.fields[note]:<18}"),
            TimeElapsedColumn(),
            TextColumn("eta"),
            TimeRemainingColumn(),
        )
        with Progress(*columns, console=console, transient=False) as bar:
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
        acquire_s = time.perf_counter() - t_acq
        if run["state"] != "complete":
            raise DemoError(
                f"run {run_id} ended {run['state']}: {run.get('last_error') or 'no reason given'} "
                f"(daemon log {daemon.log_path})"
            )

        # --- processing -------------------------------------------------------------------
        t_proc = time.perf_counter()
        job, layout_note = _post_job(client, run_id, layout if truth_layout else None)
        if layout_note:
            console.print(f"note: {layout_note}", highlight=False)
        job_id = job["id"]
        console.print(f"job {job_id}: {job['steps']} (POST /runs/{run_id}/process), for the worker", highlight=False)
        with Progress(*columns, console=console, transient=False) as bar:
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
        process_s = time.perf_counter() - t_proc
        if job["state"] != "complete":
            raise DemoError(f"job {job_id} failed: {job.get('error')} (worker log {worker.log_path})")
        run_file, artifacts = _paths_from_catalog(folder / "data" / "catalog.sqlite", run_id, job_id)
        pids = {c.name: c.pid for c in children}
    except KeyboardInterrupt:
        interrupted = True
        raise
    finally:
        _shutdown(console, children, client, run_id, interrupted)
        if previous_term is not None:
            signal.signal(signal.SIGTERM, previous_term)

    if "light_model" not in artifacts:
        raise DemoError(f"job {job_id} wrote no light model (artifacts: {', '.join(artifacts) or 'none'})")
    accuracy = score_light_model(artifacts["light_model"], truth)
    errors = [s.rms_rel_error for s in accuracy]
    result = DemoResult(
        data_dir=folder,
        rig=rig_path,
        run_id=run_id,
        job_id=job_id,
        positions=int(run["n_positions"]),
        frame=frame,
        run_file=run_file,
        artifacts=artifacts,
        accuracy=accuracy,
        max_rms_rel_error=max(errors)
        if errors and all(e == e for e in errors)
        else float("nan"),  # NaN: a source unscored
        target=TARGET_WITH_NOISE if rig_model.simulation.noise else None,
        acquire_s=acquire_s,
        process_s=process_s,
        total_s=time.perf_counter() - started,
        job_message=job.get("message") or "",
        pids=pids,
        layout=f"given to the worker: {_shown(layout)}"
        if truth_layout and not layout_note
        else "found in the data by the worker",
        aperture=aperture_used(artifacts["light_model"]),
    )
    (folder / "summary.json").write_text(json.dumps(result.to_json(), indent=2, allow_nan=True) + "\n")
    return result


def aperture_used(light_model: Path) -> str:
    """The camera's aperture the light model's sources were estimated with, in words: fitted to
    the data (the worker's default when it searches for the sources) or the rig's."""
    from processing.lightmodel import LightModel

    aperture = LightModel.load(light_model).provenance.get("aperture_m", "")
    if isinstance(aperture, dict) and aperture.get("fitted_m") is not None:
        return (
            f"{1e3 * aperture['fitted_m']:.4g} mm, fitted to the data (the rig says "
            f"{1e3 * aperture['described_m']:.4g} mm)"
        )
    return str(aperture)


def _post_job(client, run_id: str, layout: Path | None) -> tuple[dict, str]:
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


def _is_main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


def _terminate_as_interrupt(signum, frame):
    raise KeyboardInterrupt


def _paths_from_catalog(catalog_path: Path, run_id: str, job_id: str) -> tuple[Path, dict[str, Path]]:
    """The run file and the job's result files (the API gives their URLs; the paths are in the catalog)."""
    from acquisition.catalog import Catalog

    with contextlib.closing(Catalog(catalog_path)) as catalog:
        run = catalog.get_run(run_id)
        job = catalog.get_job(job_id)
    return Path(run.path), {kind: Path(path) for kind, path in job.artifacts.items()}


def _shutdown(console, children: list[Child], client, run_id: str | None, interrupted: bool) -> None:
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


# --- the summary -----------------------------------------------------------------------------
def _shown(path: Path) -> str:
    """A path relative to the working folder when it is inside it (shorter to read and copy)."""
    path = Path(path)
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


ARTIFACT_LABELS = (
    ("report", "report (HTML)"),
    ("ies", "IES"),
    ("ldt", "EULUMDAT (LDT)"),
    ("tm25", "TM-25 ray file"),
    ("light_model", "light model (JSON)"),
    ("results", "HDR results"),
)


def print_summary(result: DemoResult, console) -> None:
    from rich.table import Table

    folder = result.run_file.parent
    console.print(f"\ndemo run {result.run_id}: {result.positions} positions, {result.frame} frames", highlight=False)
    console.print(f"files in {_shown(folder)}/", highlight=False, soft_wrap=True)

    def where(path: Path) -> str:
        return path.name if path.parent == folder else _shown(path)

    files = Table(show_header=True)
    files.add_column("what", no_wrap=True)
    files.add_column("file", overflow="fold")
    files.add_row("run file", where(result.run_file))
    for kind, label in ARTIFACT_LABELS:
        if kind in result.artifacts:
            files.add_row(label, where(result.artifacts[kind]))
    files.add_row("logs, settings", _shown(result.data_dir) + "/")
    files.add_row("source layout", result.layout)
    if result.aperture:
        files.add_row("camera aperture", result.aperture)
    console.print(files)

    target = result.target
    acc = Table(title="accuracy against the simulated truth", title_justify="left")
    acc.add_column("source", no_wrap=True)
    acc.add_column("error", justify="right", no_wrap=True)
    acc.add_column("θ covered", justify="right", no_wrap=True)
    acc.add_column("samples", justify="right", no_wrap=True)
    found = result.layout.startswith("found")
    if found:
        acc.add_column("found at", justify="right", no_wrap=True)  # the source's distance from the truth's
    for s in result.accuracy:
        cells = [
            s.name,
            f"{100 * s.rms_rel_error:.3f} %",
            f"{s.theta_min_deg:.1f}–{s.theta_max_deg:.1f}°",
            str(s.samples),
        ]
        acc.add_row(*cells, *([f"{1e6 * s.offset_m:.0f} µm off"] if found else []))
    verdict = ""
    if target is not None:
        ok = result.max_rms_rel_error <= target
        verdict = f" ({'within' if ok else '[red]above[/red]'} the {100 * target:g} % target)"
    acc.add_row(
        "[bold]max[/bold]",
        f"[bold]{100 * result.max_rms_rel_error:.3f} %[/bold]",
        "",
        "",
        *([""] if found else []),
        end_section=True,
    )
    console.print(acc)
    console.print(
        f"error = RMS(I_fit − I_true) / max(I_true) over the θ each source's samples cover; "
        f"max {100 * result.max_rms_rel_error:.3f} % of peak{verdict}",
        highlight=False,
    )

    times = Table(title="times", title_justify="left", show_header=False)
    times.add_column("step", no_wrap=True)
    times.add_column("seconds", justify="right", no_wrap=True)
    times.add_row("acquisition (REST run, simulated arm and camera)", f"{result.acquire_s:.1f} s")
    times.add_row("processing (worker job, Dask)", f"{result.process_s:.1f} s")
    times.add_row("whole demo", f"{result.total_s:.1f} s")
    console.print(times)
    if result.job_message:
        console.print(f"worker: {result.job_message}", highlight=False)
