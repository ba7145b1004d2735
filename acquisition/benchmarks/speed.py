"""``mirrorgonio bench speed``: how fast the whole chain is, at two sensor sizes, in one run.

The runs
    The simulated default rig (``rigs/default.toml``: five Gaussian sources, diffraction,
    photon and read noise) at 2000x1312 and at 4000x2624 photosites (the same field of
    view: 5.9 µm and 2.95 µm pixels), each a full light sweep of 66 positions x 5
    exposures taken by the daemon's run engine with the simulated devices: the arm over
    Modbus, the camera rendering each position once (it keeps the rendering of the pose it
    is at) and exposing, writing and decoding a DNG per frame. Rendering is slow, so each
    run is made once and kept in a cache (``~/.cache/mirrorgonio/bench/``, one run file per
    key: a hash of the rig, the exposures, the positions and the creation code's version),
    and its creation time reported apart, from the cache's record.

The measurements (each at both sizes)
    ``acquire``
        The daemon's run engine taking a full run with zero-latency devices (the simulated
        arm with infinite speed, a camera that hands back the run's own frames): the time
        per frame, next to the camera's capture calls alone and to a plain h5py write of the
        same frames with the same chunks and filter. The difference with the camera alone
        is the daemon's overhead per frame.
    ``hdr``
        ``processing.hdr.brackets.merge_raw`` (the rig's noise model, as ``process`` runs it: one
        process, numba's threads) on the run's own brackets, next to HDRutils' merge and
        colour-hdri's ``image_stack_to_HDRI`` on the same brackets
        (:mod:`acquisition.benchmarks.hdr` prepares their inputs: not timed); a few
        positions spread over the sweep, medians per position.
    ``trace``
        ``processing.trace.trace_pixels``: the chief ray of every photosite of the frame
        to the light plane, at the middle position; rays per second.
    ``process``
        ``processing.light_run.run.process_run`` of the whole run, as ``mirrorgonio process``
        does it by default (a local Dask cluster, one worker process per core; steps hdr
        and sources, an OpenEXR and a PNG per position, the light model, IES, LDT, TM-25
        and the report), the sources' layout given (the truth's, as ``bench accuracy``
        does). Timed warm, as the read floor is: on one cluster that is up (as the
        ``worker`` daemon keeps one), after one untimed processing; the cluster's start,
        that first processing and one processing on a cluster started for it alone are
        reported apart (``measure_process``). Peak memory: a thread samples the
        resident memory of this process and of all its descendants (the Dask nanny and
        worker processes) every 50 ms; the peak of the sum is reported, with the peaks of
        this process alone and of the children alone.
    ``read``
        The input-bound floor: ``drivers.contracts.runfile.RunFile`` opened and every position's
        frames read (``run.frames(i)``, as each position task does), in one process. The
        run file (LZ4-compressed chunks) is read once untimed so that the page cache holds
        it, then timed: the figure is a warm read (decompression and copies, no disk).
        Processing reads the same warm file.

Timings are medians over ``repeat`` where a repeat is cheap (acquire, hdr, trace, read);
the whole-run processing is timed ``process_repeat`` times (default 3) after its untimed first. The machine's
load (``os.getloadavg``) is recorded before and after each size.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import resource
import shutil
import statistics
import tempfile
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: The reference bracket (``bench accuracy``'s): 2e-5 s to 12.5 ms, steps of 5.
EXPOSURES_S = (2e-5, 1e-4, 5e-4, 2.5e-3, 1.25e-2)
SIZES = ((2000, 1312), (4000, 2624))
POSITIONS = 66
#: Bump when the way the cached runs are made changes: older cache entries are then ignored.
CACHE_FORMAT = 1
TARGET = {"size": [2000, 1312], "process_s": 30.0, "over_read_floor": 3.0, "peak_memory_gb": 4.0}
DEFAULT_CACHE = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "mirrorgonio" / "bench"


class SpeedBenchError(ValueError):
    """Parameters the benchmark cannot run with (one line naming the option)."""


# --- the simulated runs, made once and cached ----------------------------------------------------
def rig_at_size(rig, width: int, height: int):
    """The rig with its sensor resampled to ``width`` x ``height``, the same field of view."""
    from acquisition.benchmarks.hdr import _rig_at_size

    return _rig_at_size(rig, width, height)


def cache_key(rig, exposures, positions: int) -> str:
    """A short hash of everything that makes a cached run what it is."""
    from drivers.contracts.rig import rig_to_toml_dict

    data = {
        "rig": rig_to_toml_dict(rig),
        "exposures_s": [float(t) for t in exposures],
        "positions": int(positions),
        "format": CACHE_FORMAT,
    }
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()[:16]


@dataclass
class CachedRun:
    path: Path
    key: str
    created_s: float  # wall time the run took to make (rendering included)
    from_cache: bool
    record: dict
    temporary: Path | None = None  # made without a cache: the folder to delete when done


def _acquire_run(rig, exposures, positions: int, workdir: Path) -> Path:
    """One run of the simulated rig through the daemon's run engine (the camera renders each
    pose once and exposes the bracket from it); the run file's path."""
    from acquisition.benchmarks.accuracy import take_run
    from acquisition.models import FixedBracket, RunRequest
    from acquisition.settings import load_settings

    settings = load_settings(None, data_dir=workdir / "data")
    settings.arm.simulated.speed_m_s = math.inf  # the motion is not what is measured here
    return take_run(
        settings,
        rig,
        RunRequest(
            count=positions,
            bracket=FixedBracket(exposures_s=list(exposures)),
            notes="bench speed: cached simulated run",
        ),
    )


def simulated_run(
    rig, exposures=EXPOSURES_S, positions: int = POSITIONS, cache: Path | None = DEFAULT_CACHE, log=None
) -> CachedRun:
    """The run file of ``rig``'s sweep: from ``cache`` when it holds one, else made (and kept
    there). ``cache=None``: made in a temporary folder (``CachedRun.temporary``, the caller's
    to delete)."""
    key = cache_key(rig, exposures, positions)
    if cache is not None:
        cache = Path(cache)
        run_path, record_path = cache / f"speed-{key}.h5", cache / f"speed-{key}.json"
        if run_path.is_file() and record_path.is_file():
            try:
                record = json.loads(record_path.read_text())
                return CachedRun(run_path, key, float(record["created_s"]), True, record)
            except (ValueError, KeyError, OSError):
                pass  # a damaged record: make the run again
        cache.mkdir(parents=True, exist_ok=True)
        work = Path(tempfile.mkdtemp(prefix=f"speed-{key}-", dir=cache))
    else:
        work = Path(tempfile.mkdtemp(prefix=f"mirrorgonio-speed-{key}-"))
        run_path, record_path = work / f"speed-{key}.h5", None
    cam = rig.camera
    if log:
        log(
            f"making the simulated run {cam.width}x{cam.height}, {positions} positions x {len(exposures)} exposures "
            f"(rendering each position once; cached as {run_path})"
        )
    started = time.perf_counter()
    try:
        made = _acquire_run(rig, exposures, positions, work)
        created_s = time.perf_counter() - started
        os.replace(made, run_path)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    if cache is not None:
        shutil.rmtree(work, ignore_errors=True)
    record = {
        "key": key,
        "created_s": round(created_s, 1),
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "width": cam.width,
        "height": cam.height,
        "pixel_pitch_m": cam.pixel_pitch_m,
        "positions": positions,
        "exposures_s": [float(t) for t in exposures],
        "truth": rig.simulation.truth,
        "run_file_bytes": run_path.stat().st_size,
        "load_avg_at_end": [round(v, 2) for v in os.getloadavg()],
        "how": "the daemon's run engine with the simulated arm (infinite speed) and camera (one rendering per "
        "position, every exposure drawn from it, DNG written and decoded)",
    }
    if record_path is not None:
        tmp = record_path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(record, indent=2))
        os.replace(tmp, record_path)
    return CachedRun(run_path, key, created_s, False, record, None if cache is not None else work)


# --- helpers --------------------------------------------------------------------------------------
def _load() -> list[float]:
    return [round(v, 2) for v in os.getloadavg()]


def _median(values) -> float:
    return float(statistics.median(values))


class MemorySampler:
    """Peak resident memory of this process and of all its descendants, sampled in a thread.

    Resident set sizes are summed over the processes at each sample (pages shared between
    processes, such as the libraries every Dask worker maps, are counted once per process:
    an upper bound of the physical memory). The page cache is not counted.
    """

    def __init__(self, interval_s: float = 0.05):
        import psutil

        self._psutil = psutil
        self.interval_s = interval_s
        self.me = psutil.Process()
        self.baseline_self = self.me.memory_info().rss
        self.peak_total = self.peak_self = self.peak_children = 0
        self.max_children = 0
        self.samples = 0
        self.list_every = max(1, round(1.0 / interval_s))
        self._kids, self._since_listed = [], 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="memory-sampler", daemon=True)

    def sample(self) -> None:
        psutil = self._psutil
        own = self.me.memory_info().rss
        children = 0
        # Listing the descendants reads every process's /proc entry: once a second is enough (the
        # cluster's processes live for the whole processing), the RSS of each every sample.
        if self._since_listed % self.list_every == 0:
            try:
                self._kids = self.me.children(recursive=True)
            except psutil.Error:
                self._kids = []
        kids = self._kids
        for child in kids:
            try:
                children += child.memory_info().rss
            except psutil.Error:  # ended between the listing and the look
                pass
        self.peak_self = max(self.peak_self, own)
        self.peak_children = max(self.peak_children, children)
        self.peak_total = max(self.peak_total, own + children)
        self.max_children = max(self.max_children, len(kids))
        self.samples += 1
        self._since_listed += 1

    def _loop(self) -> None:
        while not self._stop.is_set():
            self.sample()
            self._stop.wait(self.interval_s)

    def __enter__(self) -> MemorySampler:
        self.sample()
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self._since_listed = 0  # the last sample lists the descendants again
        self.sample()

    def report(self) -> dict:
        gb = 1e9
        return {
            "peak_total_gb": round(self.peak_total / gb, 3),
            "peak_this_process_gb": round(self.peak_self / gb, 3),
            "peak_children_gb": round(self.peak_children / gb, 3),
            "this_process_before_gb": round(self.baseline_self / gb, 3),
            "child_processes": self.max_children,
            "samples": self.samples,
            "sampling": f"psutil RSS of this process + all descendants every {1000 * self.interval_s:g} ms; "
            "the peak of the sum (shared pages counted per process)",
        }


@contextmanager
def _quiet_dask():
    import logging

    names = ("distributed", "distributed.worker", "distributed.nanny", "distributed.scheduler")
    saved = {n: logging.getLogger(n).level for n in names}
    for n in names:
        logging.getLogger(n).setLevel(logging.ERROR)
    try:
        yield
    finally:
        for n, level in saved.items():
            logging.getLogger(n).setLevel(level)


# --- 5. the read floor ----------------------------------------------------------------------------
def _read_all(run_path) -> tuple[int, int]:
    """Every complete position's frames, as the processing reads them; (frames, bytes)."""
    from drivers.contracts.runfile import RunFile

    frames = nbytes = 0
    with RunFile.open(run_path) as run:
        for i in run.completed_positions():
            data = run.frames(int(i))
            run.exposures(int(i))
            frames += data.shape[0]
            nbytes += data.nbytes
    return frames, nbytes


def read_position(index: int, run_path: str) -> int:
    """One position's frames read by a Dask task, as a position task opens and reads them."""
    from drivers.contracts.runfile import RunFile

    with RunFile.open(run_path) as run:
        return int(run.frames(index).nbytes)


def _timed_read(run_path) -> float:
    """Seconds of one :func:`_read_all`."""
    t0 = time.perf_counter()
    _read_all(run_path)
    return time.perf_counter() - t0


def measure_read(run_path: Path, repeat: int) -> dict:
    t0 = time.perf_counter()
    frames, nbytes = _read_all(run_path)  # warms the page cache
    cold = time.perf_counter() - t0
    times = [_timed_read(run_path) for _ in range(repeat)]
    read_s = _median(times)
    out = {
        "read_s": round(read_s, 4),
        "read_s_all": [round(t, 4) for t in times],
        "first_read_s": round(cold, 3),
        "frames": frames,
        "frame_bytes_total": nbytes,
        "run_file_bytes": Path(run_path).stat().st_size,
        "mb_per_s": round(nbytes / 1e6 / read_s, 1),
        "ms_per_frame": round(1000 * read_s / frames, 3),
        "how": "drivers.contracts.runfile.RunFile: every complete position's frames (run.frames(i)) and exposures, "
        "one process, in order; read once untimed to fill the page cache (first_read_s: that read, "
        "possibly from disk), then timed warm: read_s is the median of the warm reads (LZ4 decompression "
        "and copies, no disk)",
    }
    return out


def measure_parallel_read(run_path: Path, repeat: int, compute) -> dict:
    """The same reads as position tasks on the processing's cluster (warm)."""
    from drivers.contracts.runfile import RunFile

    with RunFile.open(run_path) as run:
        positions = [int(i) for i in run.completed_positions()]
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        compute.map_unordered(read_position, positions, str(run_path), on_result=lambda *_: None)
        times.append(time.perf_counter() - t0)
    return {
        "parallel_read_s": round(_median(times), 3),
        "parallel_read_s_all": [round(t, 3) for t in times],
        "parallel_read_how": f"the same reads as position tasks on the processing's cluster ({compute.description}): "
        "each task opens the run file and reads one position's frames; warm",
    }


# --- 4. whole-run processing ----------------------------------------------------------------------
def _process_once(run_path: Path, layout, compute, *, images: bool = True) -> dict:
    """One whole-run processing on ``compute`` into a fresh folder (deleted afterwards)."""
    from processing.light_run.run import process_run

    out_dir = Path(tempfile.mkdtemp(prefix="mirrorgonio-speed-out-"))
    try:
        before = _cpu_usage(compute)
        t0 = time.perf_counter()
        report = process_run(run_path, out_dir, steps=("hdr", "sources"), layout=layout, compute=compute, images=images)
        seconds = time.perf_counter() - t0
        used = {
            key: [a - b for a, b in zip(after, before[key], strict=True)]
            for key, after in _cpu_usage(compute).items()
            if key in before
        }
        outputs = {kind: len(paths) for kind, paths in report.outputs.items()}
        output_bytes = sum(f.stat().st_size for f in out_dir.rglob("*") if f.is_file())
    finally:
        shutil.rmtree(out_dir, ignore_errors=True)
    return {
        "process_s": seconds,
        "timings": report.timings,
        "task_stages": report.task_stages,
        "outputs": outputs,
        "output_bytes": output_bytes,
        "positions": report.positions,
        "estimator": report.estimator,
        "cpu": used,
    }


def _rusage() -> tuple[float, float, int]:
    """This process's user and system CPU seconds and minor page faults so far."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime, usage.ru_stime, usage.ru_minflt


def _cpu_usage(compute) -> dict[str, tuple[float, float, int]]:
    """:func:`_rusage` of this process (``"client"``) and of every Dask worker (by address)."""
    usage = {"client": _rusage()}
    if compute.dask:
        usage.update(compute.client.run(_rusage))
    return usage


def _cpu_report(runs: list[dict]) -> dict:
    """CPU seconds (user, system) and minor page faults per processing, medians over ``runs``:
    the client's and the workers' summed. Faults are worth watching on a VM that hands freed
    memory back to its host: 8 MB written into such pages took 12-20 ms, into reused ones
    2.5 ms (this machine, Firecracker with free page reporting)."""

    def median_of(pick) -> float:
        return _median([pick(run["cpu"]) for run in runs])

    def workers(cpu: dict, i: int) -> float:
        return sum(v[i] for k, v in cpu.items() if k != "client")

    return {
        "client_user_s": round(median_of(lambda c: c["client"][0]), 2),
        "client_system_s": round(median_of(lambda c: c["client"][1]), 2),
        "client_minor_faults": int(median_of(lambda c: c["client"][2])),
        "workers_user_s": round(median_of(lambda c: workers(c, 0)), 2),
        "workers_system_s": round(median_of(lambda c: workers(c, 1)), 2),
        "workers_minor_faults": int(median_of(lambda c: workers(c, 2))),
        "how": "getrusage(RUSAGE_SELF) of this process and of each worker (Client.run) before and after each "
        "timed processing; medians of the sums",
    }


def measure_process(
    run_path: Path,
    rig,
    repeat: int,
    scheduler: str,
    workers: int | None,
    read_floor_s: float,
    log=None,
    parallel_read_repeat: int = 3,
) -> dict:
    """Whole-run processing as a lab's processing runs it: on a cluster that is up (the
    ``worker`` daemon keeps one; ``process A.h5 B.h5 ...`` keeps one for its runs), warm
    (one untimed processing first, as the read floor is read once untimed), ``repeat`` times
    (median). Besides: the first processing (this process's imports, the workers' first
    tasks), one without the per-position images, and one on a cluster started for it alone."""
    from processing.light_run.position import warm_up_worker
    from processing.parallel import open_compute
    from sim_devices.lights import LIGHTS_DIR

    layout = LIGHTS_DIR / f"{rig.simulation.truth}.toml"

    def say(text: str) -> None:
        if log:
            log(text)

    runs, paired_reads, parallel_read, worker_peaks = [], [], None, {}
    with _quiet_dask(), MemorySampler() as memory:
        t0 = time.perf_counter()
        compute = open_compute(scheduler, workers=workers, warm_up=warm_up_worker)
        start_s = time.perf_counter() - t0
        try:
            first = _process_once(run_path, layout, compute)
            say(f"  first processing (untimed warm-up) {first['process_s']:.1f} s (cluster start {start_s:.1f} s)")
            for _ in range(repeat):
                # The floor read again just before each processing (the cluster idle): the host drifts
                # by ~10 % within minutes, and each processing is set against the floor of its moment.
                paired_reads.append(_timed_read(run_path))
                runs.append(_process_once(run_path, layout, compute))
                say(
                    f"  processed in {runs[-1]['process_s']:.1f} s "
                    f"({runs[-1]['process_s'] / paired_reads[-1]:.2f}x the "
                    f"read just before it, {paired_reads[-1]:.2f} s); stages {runs[-1]['timings']}"
                )
            without_images = _process_once(run_path, layout, compute, images=False)
            if compute.dask:  # the reads alone on the same cluster, its workers warm
                parallel_read = measure_parallel_read(run_path, parallel_read_repeat, compute)
            try:
                worker_peaks = compute.worker_peak_rss()
            except Exception:  # noqa: BLE001 - a figure we can do without
                worker_peaks = {}
            description = compute.description
        finally:
            t0 = time.perf_counter()
            compute.close()
            stop_s = time.perf_counter() - t0
    # A cluster started for one processing, as a single `mirrorgonio process RUN.h5` does (this
    # process's imports are paid by now; the workers' are not, beyond the warm-up).
    with _quiet_dask():
        t0 = time.perf_counter()
        compute = open_compute(scheduler, workers=workers, warm_up=warm_up_worker)
        fresh_start_s = time.perf_counter() - t0
        try:
            fresh = _process_once(run_path, layout, compute)
        finally:
            compute.close()
    say(f"  on a cluster started for it: {fresh['process_s']:.1f} s (its start {fresh_start_s:.1f} s)")
    times = [run["process_s"] for run in runs]
    process_s = _median(times)
    memory_report = memory.report()
    median_run = sorted(runs, key=lambda run: run["process_s"])[len(runs) // 2]
    positions = median_run["positions"]
    ratio = lambda seconds: round(seconds / read_floor_s, 2) if read_floor_s > 0 else None  # noqa: E731
    paired = [run / read for run, read in zip(times, paired_reads, strict=True) if read > 0]
    out = {
        "process_s": round(process_s, 2),
        "process_s_all": [round(t, 2) for t in times],
        "ms_per_position": round(1000 * process_s / positions, 1),
        "positions": positions,
        "first_process_s": round(first["process_s"], 2),
        "process_s_fresh_cluster": round(fresh["process_s"], 2),
        "fresh_cluster_over_read_floor": ratio(fresh["process_s"]),
        "cluster_start_s": round(start_s, 2),
        "fresh_cluster_start_s": round(fresh_start_s, 2),
        "cluster_stop_s": round(stop_s, 2),
        "stages_s": median_run["timings"],
        "task_ms_per_position": {k: round(1000 * v / positions, 1) for k, v in median_run["task_stages"].items()},
        "compute": description,
        "estimator": median_run["estimator"],
        "peak_memory_gb": memory_report["peak_total_gb"],
        "memory": memory_report,
        "worker_peak_rss_gb": {k: round(v / 1e9, 3) for k, v in worker_peaks.items()},
        "cpu_per_processing": _cpu_report(runs),
        "outputs": median_run["outputs"],
        "output_bytes": median_run["output_bytes"],
        "over_read_floor": round(_median(paired), 2) if paired else None,
        "over_read_floor_all": [round(r, 2) for r in paired],
        "paired_read_s_all": [round(t, 4) for t in paired_reads],
        "over_separate_read_floor": ratio(process_s),
        "process_s_without_images": round(without_images["process_s"], 2),
        "without_images_over_read_floor": ratio(without_images["process_s"]),
        "how": "processing.light_run.run.process_run(run, out, steps=('hdr', 'sources'), layout=<the truth's layout>, "
        "compute=<open_compute(scheduler)>): noise model estimated (the default), per position the merge, "
        "an OpenEXR and a PNG, the chief rays, templates and unmixing; then the fits, the light model, IES, "
        "LDT, TM-25 and the HTML report. One cluster, started and warmed as `process` and `worker` start it "
        "(cluster_start_s, not in the times); one untimed processing first (first_process_s: this process's "
        "imports, the workers' first tasks), as the read floor is read once untimed; process_s is the median "
        "of the next process_s_all, on the same cluster, each into a fresh folder under /tmp deleted "
        "afterwards. process_s_without_images: one more on it without the per-position OpenEXR and PNG "
        "(`process --no-images`). process_s_fresh_cluster: one processing on a cluster started for it alone "
        "(as one `mirrorgonio process RUN.h5` call; its start, fresh_cluster_start_s, apart). Peak memory over "
        "all of these. over_read_floor: the median over the timed processings of each one's time over a warm "
        "read of the floor made just before it (paired_read_s_all, the cluster idle), as the host drifts by "
        "~10 % within minutes; over_separate_read_floor: process_s over the read floor measured apart, "
        "before (read.read_s), against which the other ratios are taken.",
    }
    if parallel_read is not None:
        out.update(parallel_read)
        out["over_parallel_read"] = round(process_s / parallel_read["parallel_read_s"], 2)
    return out


# --- 3. chief rays ----------------------------------------------------------------------------------
def measure_trace(run_path: Path, repeat: int, block_pixels: int = 1 << 20) -> dict:
    from drivers.contracts.runfile import RunFile
    from processing.trace import RigGeometry, light_pose_at, trace_pixels

    with RunFile.open(run_path) as run:
        rig = run.header.rig
        middle = run.n_positions // 2
        measured = run.measured_pose(middle) if run.complete[middle] else None
        tool = measured if measured is not None else run.header.tool_poses[middle]
    geometry = RigGeometry.from_rig(rig)
    light = light_pose_at(geometry, tool)
    width, height = rig.camera.width, rig.camera.height
    rows_per_block = max(1, block_pixels // width)
    col_row = np.arange(width, dtype=float)
    first = min(height, rows_per_block)  # untimed: imports, the first touch of a block's memory
    trace_pixels(
        geometry,
        light,
        np.broadcast_to(col_row, (first, width)),
        np.broadcast_to(np.arange(first, dtype=float)[:, None], (first, width)),
    )
    times, hits, valid = [], 0, 0
    for _ in range(repeat):
        hits = valid = 0
        t0 = time.perf_counter()
        for r0 in range(0, height, rows_per_block):
            rows = np.arange(r0, min(height, r0 + rows_per_block), dtype=float)
            cols = np.broadcast_to(col_row, (rows.size, width))
            rays = trace_pixels(geometry, light, cols, np.broadcast_to(rows[:, None], (rows.size, width)))
            hits += int(np.count_nonzero(rays.hits_ball))
            valid += int(np.count_nonzero(rays.valid))
        times.append(time.perf_counter() - t0)
    trace_s = _median(times)
    n = width * height
    return {
        "rays": n,
        "trace_s": round(trace_s, 4),
        "trace_s_all": [round(t, 4) for t in times],
        "rays_per_s": round(n / trace_s),
        "rays_hitting_ball": hits,
        "rays_reaching_light_plane": valid,
        "position": middle,
        "how": f"processing.trace.trace_pixels: the chief ray of every photosite of the frame (ball or not) to the "
        f"light plane at the middle position, in blocks of {rows_per_block} rows (~{rows_per_block * width} "
        "rays, memory bounded), one process (numpy); one untimed block first; median over repeats",
    }


# --- 2. HDR merge next to its peers, on the run's own brackets -----------------------------------
def measure_hdr(run_path: Path, positions: int, repeat: int, peers: bool = True) -> dict:
    from acquisition.benchmarks.hdr import _colour_hdri, _Ctx, _hdrutils, _ours, _Sensor
    from drivers.contracts.runfile import RunFile

    with RunFile.open(run_path) as run:
        cam = run.header.rig.camera
        done = run.completed_positions()
        picks = sorted({int(done[int(k)]) for k in np.linspace(0, done.size - 1, min(positions, done.size)).round()})
        first = picks[0]
        exposures = np.asarray(run.exposures(first), float)
        black = run.black_level(first)[0]
        white = int(run.white_level(first)[0])
        cfa = run.cfa_pattern(first)[0]
        height, width = run.frame_shape
        if not np.allclose(black, black.flat[0]):
            raise SpeedBenchError(f"{run_path}: the peers take one black level, this run has one per CFA site")
        sensor = _Sensor(cfa, int(black.flat[0]), white, cam.gain_e_per_dn, cam.read_noise_e / cam.gain_e_per_dn, None)
        ctx = _Ctx(sensor, exposures, height, width)
        methods = {"mirrorgonio": _ours(ctx, "optimal")}
        if peers:
            methods["hdrutils"] = _hdrutils(ctx)
            methods["colour_hdri"] = _colour_hdri(ctx)
        else:
            methods.update(hdrutils="skipped (--no-peers)", colour_hdri="skipped (--no-peers)")
        usable = {name: m for name, m in methods.items() if not isinstance(m, str)}
        times = {name: [0.0] * repeat for name in usable}
        excluded = {name: [0.0] * repeat for name in usable}
        failed: dict[str, str] = {}
        for p, index in enumerate(picks):
            frames = run.frames(index)
            if not np.allclose(run.exposures(index), exposures):
                raise SpeedBenchError(f"{run_path}: position {index} has other exposures than position {first}")
            for name, m in usable.items():
                if name in failed:
                    continue
                try:
                    if p == 0:  # untimed: numba's JIT, the peers' lazy imports
                        m.run(m.prepare(frames))
                        if m.excluded:
                            m.excluded(None)
                    for r in range(repeat):
                        prepared = m.prepare(frames)
                        t0 = time.perf_counter()
                        m.run(prepared)
                        times[name][r] += time.perf_counter() - t0
                        if m.excluded:
                            t0 = time.perf_counter()
                            m.excluded(prepared)
                            excluded[name][r] += time.perf_counter() - t0
                        del prepared
                except Exception as exc:  # noqa: BLE001 - a peer failing is a result; ours is not
                    if name == "mirrorgonio":
                        raise
                    failed[name] = f"failed at position {index}: {type(exc).__name__}: {exc}"
            del frames
    n = len(picks)
    out_methods: dict[str, dict] = {}
    for name, m in methods.items():
        if isinstance(m, str):
            out_methods[name] = {"status": m, "ms_per_position": None}
            continue
        if name in failed:
            out_methods[name] = {"status": failed[name], "ms_per_position": None, "version": m.version}
            continue
        # Per repeat: the method's own time (HDRutils: its call minus the demosaic timed apart).
        own = [max(t - x, 0.0) for t, x in zip(times[name], excluded[name], strict=True)]
        entry = {
            "status": "ok",
            "ms_per_position": round(1000 * _median(own) / n, 2),
            "ms_per_position_all": [round(1000 * t / n, 2) for t in own],
            "version": m.version,
            "notes": m.notes,
        }
        if m.excluded:
            entry["ms_per_position_full_call"] = round(1000 * _median(times[name]) / n, 2)
            entry["excluded_part"] = m.excluded_what
            entry["excluded_ms_per_position"] = round(1000 * _median(excluded[name]) / n, 2)
        out_methods[name] = entry
    ours = out_methods["mirrorgonio"]["ms_per_position"]
    speedups = {
        name: (round(e["ms_per_position"] / ours, 2) if e.get("ms_per_position") and ours else None)
        for name, e in out_methods.items()
        if name != "mirrorgonio"
    }
    import numba

    return {
        "positions_merged": picks,
        "exposures_s": [float(f"{t:.6g}") for t in exposures],
        "methods": out_methods,
        "speedup_vs": speedups,
        "numba_threads": numba.get_num_threads(),
        "how": "the run's own brackets read from the run file (untimed); per method one untimed call on the first "
        "bracket, then every bracket merged `repeat` times; ms_per_position is the median over repeats of "
        "the total over the positions, divided by their number. mirrorgonio: processing.hdr.brackets.merge_raw "
        "(method optimal, the rig's noise model; numba, this process's threads). HDRutils: its merge only "
        "(the bilinear demosaic its call always runs is timed apart and subtracted, in its favour); "
        "colour-hdri: image_stack_to_HDRI. The peers' inputs are prepared untimed as in `bench hdr` "
        "(acquisition/benchmarks/hdr.py); errors against the truth are `bench hdr`'s subject, not this one's",
    }


# --- 1. acquisition overhead ---------------------------------------------------------------------
class _TimedCamera:
    """Wraps a camera and adds up the time its capture calls take."""

    def __init__(self, camera):
        self.camera = camera
        self.capture_s = 0.0
        self.calls = 0

    def capture(self, exposure_s: float):
        t0 = time.perf_counter()
        try:
            return self.camera.capture(exposure_s)
        finally:
            self.capture_s += time.perf_counter() - t0
            self.calls += 1

    def __getattr__(self, name):
        return getattr(self.camera, name)


def measure_acquire(run_path: Path, repeat: int, distinct_positions: int = 4) -> dict:
    from acquisition.benchmarks.acquire import _plain_h5py_write, timed_engine_run, zero_latency_arm
    from acquisition.devices import Devices
    from acquisition.models import FixedBracket, RunRequest
    from acquisition.settings import load_settings
    from drivers.contracts.runfile import RunFile
    from sim_devices.replay_camera import ReplayCamera

    with RunFile.open(run_path) as run:
        rig = run.header.rig
        done = run.completed_positions()
        exposures = [float(t) for t in run.exposures(int(done[0]))]
        picks = sorted(
            {int(done[int(k)]) for k in np.linspace(0, done.size - 1, min(distinct_positions, done.size)).round()}
        )
        frames = [run.frame(i, k) for i in picks for k in range(len(exposures))]
        positions = int(done.size)
    total = positions * len(exposures)
    frame_bytes = frames[0].mosaic.nbytes
    engine_times, capture_times, plain_times, file_bytes = [], [], [], 0
    request = RunRequest(count=positions, bracket=FixedBracket(exposures_s=exposures))
    with tempfile.TemporaryDirectory(prefix="mirrorgonio-speed-acquire-") as tmp, zero_latency_arm(rig) as arm:
        tmp = Path(tmp)
        for r in range(repeat):
            settings = load_settings(None, data_dir=tmp / f"engine-{r}")
            camera = _TimedCamera(ReplayCamera(frames))
            seconds, state = timed_engine_run(settings, rig, Devices(arm=arm, camera=camera), request)
            engine_times.append(seconds)
            capture_times.append(camera.capture_s)
            file_bytes = Path(state.path).stat().st_size
            Path(state.path).unlink()
            plain = tmp / f"plain-{r}.h5"
            plain_times.append(_plain_h5py_write(plain, frames, positions, len(exposures)))
            plain.unlink()
    engine_s, plain_s, capture_s = _median(engine_times), _median(plain_times), _median(capture_times)
    megabytes = total * frame_bytes / 1e6
    return {
        "positions": positions,
        "exposures_per_position": len(exposures),
        "frames": total,
        "engine_s": round(engine_s, 3),
        "engine_s_all": [round(t, 3) for t in engine_times],
        "engine_ms_per_frame": round(1000 * engine_s / total, 2),
        "camera_capture_ms_per_frame": round(1000 * capture_s / total, 4),
        "overhead_ms_per_frame": round(1000 * (engine_s - capture_s) / total, 2),
        "engine_mb_per_s": round(megabytes / engine_s, 1),
        "plain_h5py_ms_per_frame": round(1000 * plain_s / total, 2),
        "plain_h5py_mb_per_s": round(megabytes / plain_s, 1),
        "engine_over_plain_throughput": round(plain_s / engine_s, 3),
        "run_file_bytes": file_bytes,
        "how": "the daemon's run engine (acquisition.runner.RunEngine: catalog, run file, writer thread) takes a full "
        "run with the simulated arm at infinite speed over Modbus on loopback and a zero-latency camera that "
        f"hands back {len(frames)} frames of the cached run in turn (acquisition/benchmarks/acquire.py's "
        "set-up); camera_capture_ms_per_frame is the camera's capture calls alone, timed inside the run; "
        "overhead_ms_per_frame = (run time - capture time) / frames: what the daemon adds per frame (moves, "
        "checks, LZ4 compression and the HDF5 write, catalog updates). plain_h5py: the same frames written "
        "into one dataset with the same chunks and filter, as a floor",
    }


# --- the benchmark ---------------------------------------------------------------------------------
def parse_size(text: str) -> tuple[int, int]:
    """``WIDTHxHEIGHT`` -> (width, height), both even and at least 16."""
    try:
        w, h = (int(v) for v in text.lower().replace("×", "x").split("x"))
    except ValueError:
        raise SpeedBenchError(f"--sizes: {text!r} is not WIDTHxHEIGHT (e.g. 2000x1312)") from None
    if w < 16 or h < 16 or w % 2 or h % 2:
        raise SpeedBenchError(f"--sizes: {text!r}: width and height must be even and at least 16 (a Bayer mosaic)")
    return w, h


def bench_speed(
    *,
    rig_path=None,
    sizes=SIZES,
    positions: int = POSITIONS,
    exposures: int = len(EXPOSURES_S),
    repeat: int = 3,
    process_repeat: int = 3,
    hdr_positions: int = 8,
    peers: bool = True,
    scheduler: str = "local",
    workers: int | None = None,
    cache: Path | None = DEFAULT_CACHE,
    log=None,
) -> dict:
    """Measure the chain at every size in ``sizes``; see the module's description."""
    if not 1 <= exposures <= len(EXPOSURES_S):
        raise SpeedBenchError(f"--exposures: must be between 1 and {len(EXPOSURES_S)}, got {exposures}")
    if positions < 3:
        raise SpeedBenchError(f"--positions: must be at least 3 (the fits need samples), got {positions}")
    for name, value in (("repeat", repeat), ("process-repeat", process_repeat), ("hdr-positions", hdr_positions)):
        if value < 1:
            raise SpeedBenchError(f"--{name}: must be at least 1, got {value}")
    from drivers.contracts.rig import load_rig
    from drivers.contracts.version import __version__

    base = load_rig(rig_path)
    if positions > len(base.tool_poses()):
        raise SpeedBenchError(
            f"--positions: the rig's schedule has {len(base.tool_poses())} positions, not {positions}"
        )
    bracket = EXPOSURES_S[:exposures]
    started = time.perf_counter()
    say = log or (lambda _message: None)
    result: dict = {
        "benchmark": "speed",
        "rig": str(rig_path) if rig_path else "rigs/default.toml",
        "positions": positions,
        "exposures_s": list(bracket),
        "repeat": repeat,
        "process_repeat": process_repeat,
        "scheduler": scheduler,
        "cache": str(cache) if cache is not None else None,
        "load_avg_start": _load(),
        "machine": _machine(),
        "software_version": __version__,
        "sizes": {},
    }
    # The runs first (slow when not cached), then the measurements, size by size.
    runs = {}
    try:
        for width, height in sizes:
            rig = rig_at_size(base, width, height)
            runs[(width, height)] = (rig, simulated_run(rig, bracket, positions, cache, log=say))
        _measure(
            runs,
            result,
            repeat=repeat,
            process_repeat=process_repeat,
            hdr_positions=hdr_positions,
            peers=peers,
            scheduler=scheduler,
            workers=workers,
            say=say,
        )
    finally:
        for _rig, made in runs.values():
            if made.temporary is not None:
                shutil.rmtree(made.temporary, ignore_errors=True)
    result["load_avg_end"] = _load()
    result["target"] = _target(result)
    result["wall_s"] = round(time.perf_counter() - started, 1)
    result["markdown"] = markdown_table(result)
    return result


def _measure(
    runs: dict, result: dict, *, repeat, process_repeat, hdr_positions, peers, scheduler, workers, say
) -> None:
    for (width, height), (rig, made) in runs.items():
        label = f"{width}x{height}"
        entry: dict = {
            "width": width,
            "height": height,
            "pixel_pitch_um": round(rig.camera.pixel_pitch_m * 1e6, 4),
            "load_avg_before": _load(),
            "run": {
                "file": str(made.path),
                "bytes": made.path.stat().st_size,
                "from_cache": made.from_cache,
                "created_s": round(made.created_s, 1),
                "cache_key": made.key,
                "created_utc": made.record.get("created_utc"),
                "load_avg_when_made": made.record.get("load_avg_at_end"),
                "how": made.record.get("how"),
            },
        }
        say(f"{label}: read floor")
        entry["read"] = measure_read(made.path, repeat)
        say(f"{label}: whole-run processing ({scheduler})")
        entry["process"] = measure_process(
            made.path,
            rig,
            process_repeat,
            scheduler,
            workers,
            entry["read"]["read_s"],
            log=say,
            parallel_read_repeat=repeat,
        )
        say(f"{label}: chief rays")
        entry["trace"] = measure_trace(made.path, repeat)
        say(f"{label}: HDR merge" + (" next to HDRutils and colour-hdri" if peers else ""))
        entry["hdr"] = measure_hdr(made.path, hdr_positions, repeat, peers)
        say(f"{label}: acquisition")
        entry["acquire"] = measure_acquire(made.path, repeat)
        entry["load_avg_after"] = _load()
        result["sizes"][label] = entry


def _target(result: dict) -> dict:
    w, h = TARGET["size"]
    out = {
        "what": f"a full {POSITIONS}-position x 5-exposure run at {w}x{h} processed in <= {TARGET['process_s']:g} s "
        f"on this machine, within {TARGET['over_read_floor']:g}x of the read floor, under "
        f"{TARGET['peak_memory_gb']:g} GB"
    }
    entry = result["sizes"].get(f"{w}x{h}")
    if entry is None or result["positions"] != POSITIONS or len(result["exposures_s"]) != 5:
        out.update(
            measured=False,
            meets_target=None,
            note=f"not measured: needs the {w}x{h} size, {POSITIONS} positions and 5 exposures",
        )
        return out
    p = entry["process"]
    checks = {
        "process_s": p["process_s"] <= TARGET["process_s"],
        "over_read_floor": p["over_read_floor"] is not None and p["over_read_floor"] <= TARGET["over_read_floor"],
        "peak_memory_gb": p["peak_memory_gb"] < TARGET["peak_memory_gb"],
    }
    out.update(
        measured=True,
        process_s=p["process_s"],
        over_read_floor=p["over_read_floor"],
        peak_memory_gb=p["peak_memory_gb"],
        checks=checks,
        meets_target=all(checks.values()),
    )
    return out


def _spread(ratios: list[float]) -> str:
    """The range of a few ratios, as the table shows it beside their median: the host's noise."""
    return f"{min(ratios):.2f}–{max(ratios):.2f}× over {len(ratios)} runs" if len(ratios) > 1 else "one run"


def _fmt_s(seconds: float) -> str:
    if seconds >= 100:
        return f"{seconds:.0f} s"
    if seconds >= 1:
        return f"{seconds:.1f} s"
    return f"{1000 * seconds:.0f} ms"


def _fmt_rate(per_s: float) -> str:
    return f"{per_s / 1e6:.1f} M/s" if per_s >= 1e6 else f"{per_s / 1e3:.0f} k/s"


def markdown_table(result: dict) -> str:
    """The result as the README's table: one row per measurement, one column per size."""
    labels = list(result["sizes"])
    entries = [result["sizes"][k] for k in labels]
    n_pos, n_exp = result["positions"], len(result["exposures_s"])

    def peer(e, name):
        m = e["hdr"]["methods"].get(name, {})
        x = e["hdr"]["speedup_vs"].get(name)
        return (
            f"{name} {m['ms_per_position']:.0f} ms ({x:.1f}×)"
            if m.get("ms_per_position") and x
            else f"{name}: {m.get('status', 'n/a')}"
        )

    rows = [
        (
            "acquisition: daemon's run engine, zero-latency devices, per frame",
            [
                f"{e['acquire']['overhead_ms_per_frame']:.1f} ms over the camera's "
                f"{e['acquire']['camera_capture_ms_per_frame']:.2f} ms; "
                f"{e['acquire']['engine_over_plain_throughput']:.2f}× a plain h5py write's throughput"
                for e in entries
            ],
            "",
        ),
        (
            "HDR merge per position (same brackets; × = our speed-up)",
            [
                f"{e['hdr']['methods']['mirrorgonio']['ms_per_position']:.0f} ms; "
                + ", ".join(peer(e, p) for p in ("hdrutils", "colour_hdri"))
                for e in entries
            ],
            "",
        ),
        (
            "chief rays traced (full frame, one process)",
            [f"{_fmt_rate(e['trace']['rays_per_s'])} ({_fmt_s(e['trace']['trace_s'])} per frame)" for e in entries],
            "",
        ),
        (
            f"read floor: every frame of the {n_pos} × {n_exp} run, warm page cache",
            [
                f"{_fmt_s(e['read']['read_s'])} one process ({e['read']['mb_per_s']:.0f} MB/s)"
                + (
                    f"; {_fmt_s(e['process']['parallel_read_s'])} as tasks on the cluster"
                    if "parallel_read_s" in e["process"]
                    else ""
                )
                for e in entries
            ],
            "",
        ),
        (
            f"whole-run processing, {n_pos} × {n_exp} (hdr + sources + outputs), on a cluster that is up, warm",
            [
                f"{_fmt_s(e['process']['process_s'])} ({e['process']['over_read_floor']:.2f}× the read floor "
                "read just before "
                f"each, {_spread(e['process']['over_read_floor_all'])}; "
                f"{e['process']['over_separate_read_floor']:.2f}× the one "
                f"above)"
                for e in entries
            ],
            f"≤ {TARGET['process_s']:g} s and ≤ {TARGET['over_read_floor']:g}× the read floor at 2000×1312",
        ),
        (
            "the same on a cluster started for it alone (one `mirrorgonio process RUN.h5`)",
            [
                f"{_fmt_s(e['process']['process_s_fresh_cluster'])} "
                f"({e['process']['fresh_cluster_over_read_floor']:.1f}×) "
                f"+ {_fmt_s(e['process']['fresh_cluster_start_s'])} to start it"
                for e in entries
            ],
            "",
        ),
        (
            "the first processing on the cluster (untimed above: this process's imports)",
            [_fmt_s(e["process"]["first_process_s"]) for e in entries],
            "",
        ),
        (
            "the same without the per-position EXR and PNG (`--no-images`, one run)",
            [
                f"{_fmt_s(e['process']['process_s_without_images'])} "
                f"({e['process']['without_images_over_read_floor']:.1f}× the read floor)"
                for e in entries
            ],
            "",
        ),
        (
            "a position task's time, per position (read, merge, encode, write, images, masks, sources)",
            [
                " + ".join(
                    f"{e['process']['task_ms_per_position'].get(k, 0):.0f}"
                    for k in ("read", "merge", "encode", "write", "images", "masks", "sources")
                )
                + f" = {e['process']['task_ms_per_position'].get('tasks', 0):.0f} ms"
                for e in entries
            ],
            "",
        ),
        (
            "CPU per processing: user + system seconds, minor page faults (this process; workers)",
            [
                f"{c['client_user_s']:.1f} + {c['client_system_s']:.1f} s, {c['client_minor_faults'] / 1e3:.1f} k; "
                f"{c['workers_user_s']:.1f} + {c['workers_system_s']:.1f} s, {c['workers_minor_faults'] / 1e3:.1f} k"
                for c in (e["process"]["cpu_per_processing"] for e in entries)
            ],
            "",
        ),
        (
            "peak memory of the processing (this process + workers)",
            [f"{e['process']['peak_memory_gb']:.2f} GB" for e in entries],
            f"< {TARGET['peak_memory_gb']:g} GB at 2000×1312",
        ),
        (
            "making the simulated run (once, cached)",
            [
                f"{_fmt_s(e['run']['created_s'])} ({e['run']['bytes'] / 1e6:.0f} MB file"
                + (
                    f"; load {e['run']['load_avg_when_made'][0]:.1f} when made"
                    if e["run"].get("load_avg_when_made")
                    else ""
                )
                + ")"
                for e in entries
            ],
            "",
        ),
    ]
    target = result.get("target", {})
    verdict = {True: "met", False: "not met", None: "not measured"}[target.get("meets_target")]
    head = "| `bench speed` | " + " | ".join(k.replace("x", "×") for k in labels) + " | target |"
    lines = [head, "| --- | " + " | ".join("---" for _ in labels) + " | --- |"]
    for name, cells, goal in rows:
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {goal} |")
    loads = ", ".join(f"{e['load_avg_before'][0]:.1f}–{e['load_avg_after'][0]:.1f}" for e in entries)
    lines.append("")
    lines.append(
        f"Target ({target.get('what', '')}): **{verdict}**"
        + (
            f" — {', '.join(k for k, v in target['checks'].items() if not v)} missed"
            if target.get("checks") and not target.get("meets_target")
            else ""
        )
        + f". {result['process_repeat']} timed processing run(s) per size after an untimed one, other medians "
        f"over {result['repeat']}; "
        f"1-minute load average {loads} on {result['machine']['cpu_count']} cores; "
        f"{result['sizes'][labels[0]]['process']['compute'] if labels else ''}."
    )
    return "\n".join(lines)


def _machine() -> dict:
    import platform

    import psutil

    return {
        "cpu_count": os.cpu_count(),
        "memory_gb": round(psutil.virtual_memory().total / 1e9, 1),
        "python": platform.python_version(),
        "numpy": np.__version__,
    }
