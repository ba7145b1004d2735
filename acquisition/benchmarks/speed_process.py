"""``bench speed``'s whole-run processing, and the read floor it is set against.

The read floor is the input-bound limit: the run file opened and every position's frames
read (``run.frames(i)``, as each position task does), in one process, warm (the file read
once untimed so that the page cache holds it: decompression and copies, no disk). The
processing is timed warm too, on a cluster that is up, as the ``worker`` daemon keeps one
(:func:`measure_process`).
"""

from __future__ import annotations

import logging
import shutil
import statistics
import tempfile
import time
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path

from acquisition.benchmarks.speed_resources import MemorySampler, cpu_report, cpu_usage
from drivers.contracts.rig import Rig
from drivers.contracts.runfile import RunFile
from processing.light_run.position import warm_up_worker
from processing.light_run.run import process_run
from processing.options import ProcessingOptions
from processing.parallel import Compute, open_compute
from processing.steps import Step
from sim_devices.lights import LIGHTS_DIR

#: How ``measure_process`` measures, as its JSON says.
PROCESS_HOW = (
    "processing.light_run.run.process_run(run, out, ProcessingOptions(steps=(hdr, sources), "
    "layout=<the truth's layout>), compute=<open_compute(scheduler)>): noise model estimated (the "
    "default), per position the merge, an OpenEXR and a PNG, the chief rays, templates and unmixing; "
    "then the fits, the light model, IES, "
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
    "before (read.read_s), against which the other ratios are taken."
)


@contextmanager
def _quiet_dask():
    """Dask's own loggers at ERROR inside (its start and stop chatter is not the benchmark's)."""
    names = ("distributed", "distributed.worker", "distributed.nanny", "distributed.scheduler")
    saved = {n: logging.getLogger(n).level for n in names}
    for n in names:
        logging.getLogger(n).setLevel(logging.ERROR)
    try:
        yield
    finally:
        for n, level in saved.items():
            logging.getLogger(n).setLevel(level)


# --- the read floor -------------------------------------------------------------------------------
def _read_all(run_path: Path) -> tuple[int, int]:
    """Every complete position's frames, as the processing reads them; (frames, bytes)."""
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
    with RunFile.open(run_path) as run:
        return int(run.frames(index).nbytes)


def _timed_read(run_path: Path) -> float:
    """Seconds of one :func:`_read_all`."""
    t0 = time.perf_counter()
    _read_all(run_path)
    return time.perf_counter() - t0


def measure_read(run_path: Path, repeat: int) -> dict:
    """The read floor: every frame of the run read in one process, warm (median over ``repeat``)."""
    t0 = time.perf_counter()
    frames, nbytes = _read_all(run_path)  # warms the page cache
    cold = time.perf_counter() - t0
    times = [_timed_read(run_path) for _ in range(repeat)]
    read_s = statistics.median(times)
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


def measure_parallel_read(run_path: Path, repeat: int, compute: Compute) -> dict:
    """The same reads as position tasks on the processing's cluster (warm)."""
    with RunFile.open(run_path) as run:
        positions = [int(i) for i in run.completed_positions()]
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        compute.map_unordered(read_position, positions, str(run_path), on_result=lambda *_: None)
        times.append(time.perf_counter() - t0)
    return {
        "parallel_read_s": round(statistics.median(times), 3),
        "parallel_read_s_all": [round(t, 3) for t in times],
        "parallel_read_how": f"the same reads as position tasks on the processing's cluster ({compute.description}): "
        "each task opens the run file and reads one position's frames; warm",
    }


# --- whole-run processing -------------------------------------------------------------------------
def _process_once(run_path: Path, layout: Path | None, compute: Compute, *, images: bool = True) -> dict:
    """One whole-run processing on ``compute`` into a fresh folder (deleted afterwards)."""
    out_dir = Path(tempfile.mkdtemp(prefix="mirrorgonio-speed-out-"))
    try:
        before = cpu_usage(compute)
        t0 = time.perf_counter()
        options = ProcessingOptions(steps=(Step.HDR, Step.SOURCES), layout=layout, images=images)
        report = process_run(run_path, out_dir, options, compute=compute)
        seconds = time.perf_counter() - t0
        used = {
            key: [a - b for a, b in zip(after, before[key], strict=True)]
            for key, after in cpu_usage(compute).items()
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


def measure_process(
    run_path: Path,
    rig: Rig,
    repeat: int,
    scheduler: str,
    workers: int | None,
    read_floor_s: float,
    log: Callable[[str], None] | None = None,
    parallel_read_repeat: int = 3,
) -> dict:
    """Whole-run processing as a lab's processing runs it: on a cluster that is up (the
    ``worker`` daemon keeps one; ``process A.h5 B.h5 ...`` keeps one for its runs), warm
    (one untimed processing first, as the read floor is read once untimed), ``repeat`` times
    (median). Besides: the first processing (this process's imports, the workers' first
    tasks), one without the per-position images, and one on a cluster started for it alone."""
    layout = LIGHTS_DIR / f"{rig.simulation.truth}.toml"
    say = log or (lambda _text: None)
    up = _on_a_cluster_that_is_up(run_path, layout, repeat, scheduler, workers, say, parallel_read_repeat)
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
    return _process_report(up, fresh, fresh_start_s, read_floor_s)


def _on_a_cluster_that_is_up(
    run_path: Path,
    layout: Path,
    repeat: int,
    scheduler: str,
    workers: int | None,
    say: Callable[[str], None],
    parallel_read_repeat: int,
) -> dict:
    """The processings on one cluster, memory sampled throughout: the untimed first, ``repeat``
    timed ones each after a read of the floor, one without images, the reads as tasks."""
    runs, paired_reads, parallel_read, worker_peaks = [], [], None, {}
    with _quiet_dask(), MemorySampler() as memory:
        t0 = time.perf_counter()
        compute = open_compute(scheduler, workers=workers, warm_up=warm_up_worker)
        start_s = time.perf_counter() - t0
        try:
            first = _process_once(run_path, layout, compute)
            say(f"  first processing (untimed warm-up) {first['process_s']:.1f} s (cluster start {start_s:.1f} s)")
            for _ in range(repeat):
                # The floor read again just before each processing (the cluster idle): the host's
                # speed drifts within minutes, and each processing is set against the floor of its moment.
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
    return {
        "runs": runs,
        "paired_reads": paired_reads,
        "first": first,
        "without_images": without_images,
        "parallel_read": parallel_read,
        "worker_peaks": worker_peaks,
        "description": description,
        "start_s": start_s,
        "stop_s": stop_s,
        "memory": memory.report(),
    }


def _process_report(up: dict, fresh: dict, fresh_start_s: float, read_floor_s: float) -> dict:
    """``measure_process``'s JSON from what the cluster that was up and the fresh one measured."""
    runs, paired_reads = up["runs"], up["paired_reads"]
    times = [run["process_s"] for run in runs]
    process_s = statistics.median(times)
    memory_report = up["memory"]
    median_run = sorted(runs, key=lambda run: run["process_s"])[len(runs) // 2]
    positions = median_run["positions"]
    ratio = lambda seconds: round(seconds / read_floor_s, 2) if read_floor_s > 0 else None  # noqa: E731
    paired = [run / read for run, read in zip(times, paired_reads, strict=True) if read > 0]
    out = {
        "process_s": round(process_s, 2),
        "process_s_all": [round(t, 2) for t in times],
        "ms_per_position": round(1000 * process_s / positions, 1),
        "positions": positions,
        "first_process_s": round(up["first"]["process_s"], 2),
        "process_s_fresh_cluster": round(fresh["process_s"], 2),
        "fresh_cluster_over_read_floor": ratio(fresh["process_s"]),
        "cluster_start_s": round(up["start_s"], 2),
        "fresh_cluster_start_s": round(fresh_start_s, 2),
        "cluster_stop_s": round(up["stop_s"], 2),
        "stages_s": median_run["timings"],
        "task_ms_per_position": {k: round(1000 * v / positions, 1) for k, v in median_run["task_stages"].items()},
        "compute": up["description"],
        "estimator": median_run["estimator"],
        "peak_memory_gb": memory_report["peak_total_gb"],
        "memory": memory_report,
        "worker_peak_rss_gb": {k: round(v / 1e9, 3) for k, v in up["worker_peaks"].items()},
        "cpu_per_processing": cpu_report(runs),
        "outputs": median_run["outputs"],
        "output_bytes": median_run["output_bytes"],
        "over_read_floor": round(statistics.median(paired), 2) if paired else None,
        "over_read_floor_all": [round(r, 2) for r in paired],
        "paired_read_s_all": [round(t, 4) for t in paired_reads],
        "over_separate_read_floor": ratio(process_s),
        "process_s_without_images": round(up["without_images"]["process_s"], 2),
        "without_images_over_read_floor": ratio(up["without_images"]["process_s"]),
        "how": PROCESS_HOW,
    }
    if up["parallel_read"] is not None:
        out.update(up["parallel_read"])
        out["over_parallel_read"] = round(process_s / up["parallel_read"]["parallel_read_s"], 2)
    return out
