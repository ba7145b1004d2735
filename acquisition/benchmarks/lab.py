"""``mirrorgonio bench lab``: a lab under load, and the faults it meets.

Three rigs (three real daemons, each in a network namespace of its own, as on a machine of
its own), three workers that do not see the daemons' disks (each in a mount namespace where
the rigs' folders are an empty tmpfs: they fetch the run files and send the results back),
one PostgreSQL server for the catalog. Thirty processing jobs are queued through the daemons'
API, ten per rig, and processed while three faults happen, one after the other:

1. a worker is killed (SIGKILL) in the middle of a job, and started again five seconds later
   (as a supervisor would): its job is requeued once its heartbeats stop;
2. PostgreSQL restarts (a fast shutdown: every connection breaks);
3. one daemon's network is cut (its link down, both ways) for ``cut_s`` seconds.

What is reported: the jobs lost (not complete at the end), the jobs whose results were
recorded twice, the runs whose light model differs from a single-machine processing of the
same file, the time to recover from each fault, and the catalog's latency under the load
(a probe that reads the lab's run list and a job four times a second).

Needs root (network namespaces, mount namespaces) and PostgreSQL's server programs.
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx

from acquisition.benchmarks.speed_runs import simulated_run
from acquisition.daemon.catalog import Catalog, CatalogError, JobRecord
from acquisition.daemon.catalog.throwaway_server import ThrowawayPostgres
from acquisition.daemon.worker import job_processing_options
from drivers.contracts.rig import DEFAULT_RIG_PATH, load_rig
from processing import process_run, resolve_steps
from sim_devices.lights import LIGHTS_DIR

TOKEN = "bench-lab-token-0123456789"
LAYOUT = str(LIGHTS_DIR / "five-gaussians.toml")
JOB = {"steps": "hdr,sources", "layout": LAYOUT}
SUBNET = "10.77"  # rig k's link: SUBNET.k.1 (this side) and SUBNET.k.2 (its daemon)
EXPOSURES_S = (0.0002, 0.001, 0.005, 0.025)
#: The rigs' description: the demo rig (1000 x 656 pixels), and the positions of its sweep in
#: the first rig's runs (two more in each next rig's): a job of some seconds, so that the faults
#: happen while jobs run.
DEMO_RIG = DEFAULT_RIG_PATH.parent / "demo.toml"
RUN_POSITIONS = 8


#: Two light models are the same results when no number differs by more than this, relatively:
#: the same processing in two processes may sum in another order (their BLAS threads).
SAME_RESULTS_RTOL = 1e-6


def light_model_difference(a: Any, b: Any) -> float:
    """The largest relative difference between the numbers of two light models' parts (JSON
    data); infinity where anything else differs (a name, a length, a key)."""
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return math.inf
        return max((light_model_difference(a[k], b[k]) for k in a), default=0.0)
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return math.inf
        return max((light_model_difference(x, y) for x, y in zip(a, b, strict=True)), default=0.0)
    if isinstance(a, bool) or isinstance(b, bool):
        return 0.0 if type(a) is type(b) and a == b else math.inf
    numbers = (int, float)
    if isinstance(a, numbers) and isinstance(b, numbers):
        if a == b:
            return 0.0
        return abs(a - b) / max(abs(a), abs(b))
    return 0.0 if a == b else math.inf


class LabBenchError(RuntimeError):
    """The lab cannot be set up here (one line)."""


def _run(*command: str) -> None:
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise LabBenchError(f"{' '.join(command)}: {done.stderr.strip() or done.returncode}")


@dataclass
class Rig:
    """One rig of the lab: its daemon in its own network namespace."""

    index: int
    root: Path
    process: subprocess.Popen | None = None
    log: Path = field(init=False)

    def __post_init__(self) -> None:
        self.log = self.root / f"daemon-{self.name}.log"

    @property
    def name(self) -> str:
        return f"rig-{self.index}"

    @property
    def netns(self) -> str:
        return f"mg-lab-{self.index}"

    @property
    def link(self) -> str:
        return f"mglab{self.index}h"

    @property
    def url(self) -> str:
        return f"http://{SUBNET}.{self.index}.2:8000"

    @property
    def data_dir(self) -> Path:
        return self.root / "rigs" / self.name

    @property
    def source(self) -> Path:
        """The rig's own run file, which its runs are copies of (outside the rigs' folders)."""
        return self.root / f"{self.name}-source.h5"

    def connect(self) -> None:
        """The namespace and its link to this side (those a run stopped short left, deleted first)."""
        self.disconnect()
        inside = f"mglab{self.index}n"
        _run("ip", "netns", "add", self.netns)
        _run("ip", "link", "add", self.link, "type", "veth", "peer", "name", inside)
        _run("ip", "link", "set", inside, "netns", self.netns)
        _run("ip", "addr", "add", f"{SUBNET}.{self.index}.1/24", "dev", self.link)
        _run("ip", "link", "set", self.link, "up")
        _run("ip", "netns", "exec", self.netns, "ip", "addr", "add", f"{SUBNET}.{self.index}.2/24", "dev", inside)
        _run("ip", "netns", "exec", self.netns, "ip", "link", "set", inside, "up")
        _run("ip", "netns", "exec", self.netns, "ip", "link", "set", "lo", "up")
        # While the link is down its packets are dropped, as a cut cable drops them (without
        # this route they would follow the default route to whatever answers there).
        _run("ip", "route", "add", "blackhole", f"{SUBNET}.{self.index}.0/24", "metric", "4000")

    def start(self, catalog_url: str) -> None:
        self.data_dir.mkdir(parents=True, exist_ok=True)
        config = self.root / f"{self.name}.toml"
        config.write_text(
            f'data_dir = "{self.data_dir}"\nrig = "{DEMO_RIG}"\n'
            f'rig_name = "{self.name}"\ncatalog = "{catalog_url}"\npublic_url = "{self.url}"\n'
        )
        exe = Path(sys.executable).with_name("mirrorgonio")
        self.process = subprocess.Popen(
            ["ip", "netns", "exec", self.netns, str(exe), "serve", "--config", str(config)]
            + ["--host", f"{SUBNET}.{self.index}.2", "--port", "8000"],
            stdout=self.log.open("ab"),
            stderr=subprocess.STDOUT,
            env={**os.environ, "MG_TOKEN": TOKEN},
        )
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise LabBenchError(f"{self.name}'s daemon exited: {self.log.read_text()[-1500:]}")
            with contextlib.suppress(httpx.HTTPError):
                httpx.get(f"{self.url}/health", timeout=2)
                return
            time.sleep(0.2)
        raise LabBenchError(f"{self.name}'s daemon did not answer in 120 s")

    def cut(self, down: bool) -> None:
        _run("ip", "link", "set", self.link, "down" if down else "up")

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(20)
            except subprocess.TimeoutExpired:
                self.process.kill()

    def disconnect(self) -> None:
        subprocess.run(["ip", "link", "del", self.link], capture_output=True, check=False)
        subprocess.run(
            ["ip", "route", "del", "blackhole", f"{SUBNET}.{self.index}.0/24", "metric", "4000"],
            capture_output=True,
            check=False,
        )
        subprocess.run(["ip", "netns", "del", self.netns], capture_output=True, check=False)

    def results_uploads(self) -> Counter[str]:
        """Each job's results this daemon took (200 answers to PUT /jobs/JOB/results)."""
        text = self.log.read_text(errors="replace") if self.log.exists() else ""
        return Counter(re.findall(r'"PUT /jobs/(job-[\w-]+)/results\?[^"]*" 200', text))


@dataclass
class Worker:
    """A worker that sees none of the rigs' folders."""

    name: str
    root: Path
    hidden: Path
    catalog_url: str
    process: subprocess.Popen | None = None

    @property
    def log(self) -> Path:
        return self.root / f"{self.name}.log"

    def start(self) -> None:
        folder = self.root / "workers" / self.name
        folder.mkdir(parents=True, exist_ok=True)
        exe = Path(sys.executable).with_name("mirrorgonio")
        command = [str(exe), "worker", "--catalog", self.catalog_url, "--data-dir", str(folder)]
        command += ["--scheduler", "none", "--id", self.name, "--heartbeat", "1", "--stale-after", "10"]
        command += ["--poll", "0.5", "--wait", "2"]
        self.process = subprocess.Popen(
            ["unshare", "-m", "sh", "-c", f'mount -t tmpfs tmpfs "{self.hidden}" && exec "$0" "$@"', *command],
            stdout=self.log.open("ab"),
            stderr=subprocess.STDOUT,
            env={**os.environ, "MG_TOKEN": TOKEN},
        )

    def kill(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGKILL)
            self.process.wait(10)

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(30)
            except subprocess.TimeoutExpired:
                self.kill()


class LatencyProbe(threading.Thread):
    """The catalog's latency as a client sees it: the lab's run list and one job, read four
    times a second on a connection of its own."""

    def __init__(self, catalog_url: str, job_ids: list[str]):
        super().__init__(name="catalog-probe", daemon=True)
        self.catalog = Catalog(catalog_url)
        self.job_ids = job_ids
        self.samples_ms: list[float] = []
        self.failures: list[float] = []  # when each failed read happened
        self.stop = threading.Event()

    def run(self) -> None:
        k = 0
        while not self.stop.wait(0.25):
            started = time.perf_counter()
            try:
                self.catalog.list_runs(limit=100, rig=None)
                self.catalog.get_job(self.job_ids[k % len(self.job_ids)])
                self.samples_ms.append(1000 * (time.perf_counter() - started))
            except CatalogError:
                self.failures.append(time.monotonic())
            k += 1
        self.catalog.close()

    def summary(self) -> dict[str, Any]:
        samples = sorted(self.samples_ms)
        if not samples:
            return {"catalog_reads": 0, "catalog_read_failures": len(self.failures)}
        return {
            "catalog_reads": len(samples),
            "catalog_read_failures": len(self.failures),
            "catalog_latency_ms_p50": round(statistics.median(samples), 2),
            "catalog_latency_ms_p95": round(samples[int(0.95 * (len(samples) - 1))], 2),
            "catalog_latency_ms_max": round(samples[-1], 2),
        }


def _reference(run_file: Path, folder: Path) -> dict:
    """The light model's sources of a single-machine processing of ``run_file``."""
    folder.mkdir(parents=True, exist_ok=True)
    options = job_processing_options(JOB, resolve_steps(JOB["steps"]))  # as a worker takes a job
    report = process_run(run_file, folder, options)
    if report.light_model is None:
        raise LabBenchError(f"processing {run_file} wrote no light model")
    return json.loads(Path(report.light_model).read_text())["sources"]


def _queue_jobs(rigs: list[Rig], runs: dict[str, list[str]]) -> list[str]:
    jobs = []
    for rig in rigs:
        with httpx.Client(base_url=rig.url, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=30) as http:
            for run_id in runs[rig.name]:
                answer = http.post(f"/runs/{run_id}/process", json=JOB)
                if answer.status_code != 201:
                    raise LabBenchError(f"{rig.name}: POST /runs/{run_id}/process: {answer.status_code} {answer.text}")
                jobs.append(answer.json()["id"])
    return jobs


def _wait(condition: Callable[[], bool], timeout_s: float, poll_s: float = 0.2) -> float | None:
    """Seconds until ``condition()`` holds, None if it did not within ``timeout_s``."""
    started = time.monotonic()
    while time.monotonic() - started < timeout_s:
        with contextlib.suppress(CatalogError):
            if condition():
                return time.monotonic() - started
        time.sleep(poll_s)
    return None


def bench_lab(
    *,
    rigs: int = 3,
    workers: int = 3,
    runs: int = 30,
    cut_s: float = 30.0,
    timeout_s: float = 1800.0,
    workdir: Path | None = None,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Set the lab up, queue the jobs, inject the faults, and measure (the module's docstring)."""
    if os.geteuid() != 0:
        raise LabBenchError("bench lab needs root: each rig's daemon runs in a network namespace of its own")
    root = Path(workdir or tempfile.mkdtemp(prefix="mirrorgonio-lab-"))
    root.mkdir(parents=True, exist_ok=True)
    lab = [Rig(k + 1, root) for k in range(rigs)]
    server = ThrowawayPostgres(fast=False, listen="*", trusted=[f"{SUBNET}.0.0/16"])
    signal.signal(signal.SIGTERM, _interrupt)  # a stopped bench still takes its namespaces down
    started = time.monotonic()
    pool: list[Worker] = []
    probe: LatencyProbe | None = None
    try:
        url = server.create_database("lab")
        log(f"bench lab: {rigs} rigs, {workers} workers, {runs} jobs, in {root}")
        references = _make_sources(lab, root)
        log("  run files made, and each processed once on one machine (the reference)")
        for rig in lab:
            rig.connect()
            rig.start(f"postgresql://postgres@{SUBNET}.{rig.index}.1:{server.port}/lab")
        log(f"  {rigs} daemons up: {', '.join(r.url for r in lab)}")
        per_rig = _register_runs(lab, url, runs)
        job_ids = _queue_jobs(lab, per_rig)
        log(f"  {len(job_ids)} jobs queued through the daemons' API")
        probe = LatencyProbe(url, job_ids)
        probe.start()
        pool = [Worker(f"worker-{k + 1}", root, root / "rigs", url) for k in range(workers)]
        for worker in pool:
            worker.start()
        with Catalog(url) as watch:
            faults = {
                **_kill_a_worker(watch, pool, log),
                **_restart_postgres(watch, server, log),
                **_cut_a_rig(watch, lab[1 % rigs], cut_s, log),
            }
            finished = _wait(lambda: all(j.state in ("complete", "failed") for j in _jobs(watch)), timeout_s, 1.0)
            jobs = {j.id: j for j in _jobs(watch) if j.id in job_ids}
        elapsed = time.monotonic() - started
        probe.stop.set()
        probe.join(10)
        return {
            "benchmark": "lab",
            "rigs": rigs,
            "workers": workers,
            **_outcome(jobs, lab, pool, references),
            "all_done_s": None if finished is None else round(elapsed, 1),
            **faults,
            **probe.summary(),
        }
    finally:
        if probe is not None:
            probe.stop.set()
        for worker in pool:
            worker.stop()
        for rig in lab:
            rig.stop()
            rig.disconnect()
        server.close()


def _interrupt(*_: object) -> None:
    raise KeyboardInterrupt


def _jobs(watch: Catalog) -> list[JobRecord]:
    return watch.list_jobs(rig=None, limit=1000)


def _make_sources(lab: list[Rig], root: Path) -> dict[str, dict]:
    """Each rig's run file (some positions of the demo rig, a different number each, made
    through the daemon's run engine), and the light model's sources of a single-machine
    processing of it, by rig."""
    described = load_rig(DEMO_RIG)
    references = {}
    for rig in lab:
        made = simulated_run(described, EXPOSURES_S, positions=RUN_POSITIONS + 2 * rig.index, cache=None)
        shutil.move(made.path, rig.source)
        if made.temporary is not None:
            shutil.rmtree(made.temporary, ignore_errors=True)
        references[rig.name] = _reference(rig.source, root / "reference" / rig.name)
    return references


def _register_runs(lab: list[Rig], url: str, runs: int) -> dict[str, list[str]]:
    """``runs`` finished runs in the catalog, shared among the rigs, each a copy of its rig's
    run file in the rig's folder: the run ids by rig."""
    n_positions = len(load_rig(DEMO_RIG).tool_poses())
    per_rig: dict[str, list[str]] = {rig.name: [] for rig in lab}
    for k in range(runs):
        rig = lab[k % len(lab)]
        runs_dir = rig.data_dir / "runs"
        runs_dir.mkdir(parents=True, exist_ok=True)
        with Catalog(url, rig=rig.name) as catalog:
            record = catalog.create_run(
                preset="light-sweep",
                path_for=functools.partial(_run_path, runs_dir),
                n_positions=n_positions,
                request={},
            )
            shutil.copy(rig.source, _run_path(runs_dir, record.id))
            catalog.transition_run(record.id, "running")
            catalog.transition_run(record.id, "complete")
        per_rig[rig.name].append(record.id)
    return per_rig


def _outcome(jobs: dict[str, JobRecord], lab: list[Rig], pool: list[Worker], references: dict) -> dict[str, Any]:
    """What became of the jobs: lost, recorded twice, claimed again, their results against
    one machine's."""
    uploads: Counter[str] = Counter()
    for rig in lab:
        uploads.update(rig.results_uploads())
    differences = {
        job.run_id: light_model_difference(
            json.loads(Path(job.artifacts["light_model"]).read_text())["sources"], references[job.rig]
        )
        for job in jobs.values()
        if job.state == "complete"
    }
    complete = sum(j.state == "complete" for j in jobs.values())
    return {
        "jobs": len(jobs),
        "jobs_complete": complete,
        "jobs_lost": len(jobs) - complete,
        "jobs_failed": [f"{j.id}: {j.error}" for j in jobs.values() if j.state == "failed"],
        "jobs_recorded_twice": sum(n > 1 for n in uploads.values()),
        "jobs_claimed_more_than_once": sum(n > 1 for n in _claims(pool).values()),
        "results_differ_from_one_machine": sum(d >= SAME_RESULTS_RTOL for d in differences.values()),
        "results_identical_to_the_last_digit": sum(d == 0 for d in differences.values()),
        "results_largest_relative_difference": max(differences.values(), default=None),
    }


def _run_path(runs_dir: Path, run_id: str) -> Path:
    return runs_dir / f"{run_id}.h5"


def _claims(pool: list[Worker]) -> Counter[str]:
    """How many times each job was claimed, from the workers' logs."""
    counts: Counter[str] = Counter()
    for worker in pool:
        text = worker.log.read_text(errors="replace") if worker.log.exists() else ""
        counts.update(re.findall(r": claimed job (job-[\w-]+) ", text))
    return counts


# --- the faults -----------------------------------------------------------------------------
def _kill_a_worker(watch: Catalog, pool: list[Worker], log: Callable[[str], None]) -> dict[str, Any]:
    """A worker killed (SIGKILL) while its job is being processed (past its fetch: progress
    recorded), started again five seconds later as a supervisor would: how long until its job
    is taken again (its heartbeats stop, it is requeued and claimed) and complete."""
    busy: list[JobRecord] = []

    def a_busy_job() -> bool:
        busy[:] = [j for j in _jobs(watch) if j.state == "running" and j.progress > 0.05 and j.claimed_by]
        return bool(busy)

    if _wait(a_busy_job, 600) is None:
        raise LabBenchError("no job got past its fetch in 600 s: see the workers' logs")
    job = busy[0]
    victim = next(w for w in pool if w.name == job.claimed_by)
    killed_at = time.monotonic()
    victim.kill()
    log(f"  fault 1: {victim.name} killed (SIGKILL) in the middle of {job.id}")
    time.sleep(5)
    victim.start()

    def taken_again() -> bool:
        now = watch.get_job(job.id)
        return now.state == "complete" or (
            now.state == "running" and now.updated_utc > job.updated_utc and now.progress < job.progress
        )

    retaken = _wait(taken_again, 300, poll_s=0.1)
    retaken_s = None if retaken is None else time.monotonic() - killed_at
    again = _wait(lambda: watch.get_job(job.id).state == "complete", 600)
    out = {
        "worker_kill_job_taken_again_s": None if retaken_s is None else round(retaken_s, 1),
        "worker_kill_job_complete_s": None if again is None else round(time.monotonic() - killed_at, 1),
    }
    log(f"    its job was taken again {out['worker_kill_job_taken_again_s']} s after the kill")
    return out


def _restart_postgres(watch: Catalog, server: ThrowawayPostgres, log: Callable[[str], None]) -> dict[str, Any]:
    """PostgreSQL restarted (a fast shutdown: every connection breaks) while jobs run: how long
    it was down, and until the catalog answers and the next job completes."""
    if _wait(lambda: any(j.state == "running" for j in _jobs(watch)), 60) is None:
        raise LabBenchError("no job was running for PostgreSQL's restart: give the lab more runs (--runs)")
    before = sum(j.state == "complete" for j in _jobs(watch))
    restart_at = time.monotonic()
    server.restart()
    down_s = time.monotonic() - restart_at
    back = _wait(lambda: watch.list_runs(limit=1, rig=None) is not None, 120, poll_s=0.05)
    next_done = _wait(lambda: sum(j.state == "complete" for j in _jobs(watch)) > before, 600)
    out = {
        "postgres_restart_down_s": round(down_s, 1),
        "postgres_restart_catalog_back_s": None if back is None else round(down_s + back, 2),
        "postgres_restart_next_job_complete_s": None if next_done is None else round(time.monotonic() - restart_at, 1),
    }
    log(
        f"  fault 2: PostgreSQL restarted ({down_s:.1f} s down); the next job complete "
        f"{out['postgres_restart_next_job_complete_s']} s after"
    )
    return out


def _cut_a_rig(watch: Catalog, rig: Rig, cut_s: float, log: Callable[[str], None]) -> dict[str, Any]:
    """One rig's network cut (its link down, both ways) for ``cut_s`` while one of its jobs
    runs: how long after it comes back the daemon answers and the rig's next job completes."""

    def of_rig(state: str) -> int:
        return sum(j.state == state and j.rig == rig.name for j in _jobs(watch))

    if _wait(lambda: of_rig("running") > 0, 120) is None:
        raise LabBenchError(f"no job of {rig.name} was running for its network cut: give the lab more runs (--runs)")
    done_before = of_rig("complete")
    rig.cut(True)
    log(f"  fault 3: {rig.name}'s network cut for {cut_s:.0f} s")
    time.sleep(cut_s)
    rig.cut(False)
    restored_at = time.monotonic()
    answers = _wait(lambda: httpx.get(f"{rig.url}/health", timeout=2).status_code in (200, 503), 120)
    rig_next = _wait(lambda: of_rig("complete") > done_before, 600)
    out = {
        "network_cut_s": cut_s,
        "network_cut_daemon_answers_s": None if answers is None else round(answers, 2),
        "network_cut_next_job_of_the_rig_complete_s": None
        if rig_next is None
        else round(time.monotonic() - restored_at, 1),
    }
    log(f"    {rig.name} answered {out['network_cut_daemon_answers_s']} s after its network came back")
    return out
