"""Positions processed on real Dask clusters: a `dask scheduler` and `dask worker` processes on
loopback, and the default local cluster. Their results must equal the no-Dask path's."""

from __future__ import annotations

import json
import logging
import math
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import dask
import h5py
import hdf5plugin  # noqa: F401 - the results' filters
import numpy as np
import pytest
from conftest import free_port
from test_worker import LAYOUT, Data, captured  # noqa: F401 - the module fixture of three positions
from typer.testing import CliRunner

from acquisition.cli import app
from processing.options import ProcessingOptions
from processing.parallel import ComputeError, default_workers, open_compute

runner = CliRunner()


DASK = str(Path(sys.executable).with_name("dask"))


def _worker_argv(address: str, nworkers: int) -> list[str]:
    return [
        DASK,
        "worker",
        address,
        "--host",
        "127.0.0.1",
        "--nworkers",
        str(nworkers),
        "--nthreads",
        "1",
        "--no-dashboard",
        "--memory-limit",
        "2GB",
    ]


class _Programs:
    """Dask programs started as separate processes, each logging to a file; stopped in reverse."""

    def __init__(self, logs: Path):
        self.logs, self.procs = logs, []

    def start(self, name: str, argv: list[str]) -> None:
        log = open(self.logs / f"{name}.log", "wb")
        self.procs.append((subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT), log))

    def stop(self) -> None:
        for proc, log in reversed(self.procs):
            proc.terminate()
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)
            log.close()

    def scheduler(self) -> str:
        port = free_port()
        self.start("scheduler", [DASK, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"])
        time.sleep(0.5)
        return f"tcp://127.0.0.1:{port}"


@pytest.fixture(scope="module")
def scheduler(tmp_path_factory):
    """A Dask scheduler and two single-threaded worker processes, as separate programs."""
    from distributed import Client

    programs = _Programs(tmp_path_factory.mktemp("dask"))
    try:
        address = programs.scheduler()
        programs.start("worker", _worker_argv(address, 2))
        with Client(address, timeout=60) as client:
            client.wait_for_workers(2, timeout=120)
        yield address
    finally:
        programs.stop()


def test_workers_that_join_later_are_warmed_up_too(tmp_path):
    """The warm-up is a worker plugin: a worker started after the processing connected to
    the cluster loads the processing's modules as it joins, before any task of ours, and
    freezes its long-lived objects."""
    from processing.light_run.position import warm_up_worker

    def warmed() -> bool:
        """Imported, and the warmed-up objects set aside from the cyclic collector (the
        processing's own modules among them): a full collection walks only newer ones."""
        import gc

        module = sys.modules.get("processing.unmixing")
        frozen = gc.get_freeze_count() > 100_000 and not any(o is module for o in gc.get_objects())
        return "processing.unmixing" in sys.modules and "processing.images" in sys.modules and frozen

    programs = _Programs(tmp_path)
    try:
        address = programs.scheduler()
        programs.start("first-worker", _worker_argv(address, 1))
        with open_compute(address, warm_up=warm_up_worker) as compute:
            compute.client.wait_for_workers(1, timeout=120)
            first = set(compute.client.scheduler_info()["workers"])
            assert list(compute.client.run(warmed).values()) == [True]
            programs.start("later-worker", _worker_argv(address, 1))
            compute.client.wait_for_workers(2, timeout=120)
            later = set(compute.client.scheduler_info()["workers"]) - first
            assert len(later) == 1
            assert compute.client.run(warmed, workers=list(later)) == {later.pop(): True}
            # Registered once: a second processing connecting to the cluster keeps the one plugin.
            with open_compute(address, warm_up=warm_up_worker) as again:
                plugins = again.client.run_on_scheduler(lambda dask_scheduler: list(dask_scheduler.worker_plugins))
                assert [p for p in plugins if p.startswith("mirrorgonio-warm-up")] == [
                    "mirrorgonio-warm-up:processing.light_run.position.warm_up_worker"
                ]
    finally:
        programs.stop()


def _results(folder: Path, stem: str) -> dict:
    with h5py.File(folder / f"{stem}.results.h5", "r") as f:
        arrays = {name: f["hdr"][name][()] for name in ("radiance", "variance", "count", "saturated", "done")}
    model = json.loads((folder / f"{stem}.light.json").read_text())
    from processing.exports.tm25 import read_tm25

    _, rays = read_tm25(folder / f"{stem}.tm25ray")  # its header has the time it was written
    return {"arrays": arrays, "model": model, "ies": (folder / f"{stem}.ies").read_text(), "rays": np.asarray(rays)}


def _close(a, b, path="model") -> None:
    """Equal to the last digit: the position tasks run with one BLAS thread here as in a Dask
    worker (processing.parallel), so no least-squares sum is added up in another order."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), path
        for key in a:
            _close(a[key], b[key], f"{path}.{key}")
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _close(x, y, f"{path}[{i}]")
    elif isinstance(a, float) and isinstance(b, float):
        assert a == b or (math.isnan(a) and math.isnan(b)), (path, a, b)
    else:
        assert a == b, path


def _assert_same(a: dict, b: dict) -> None:
    for name, array in a["arrays"].items():  # the merge is the same to the bit
        np.testing.assert_array_equal(array, b["arrays"][name], err_msg=name)
    _close(a["model"], b["model"])
    assert a["ies"] == b["ies"]
    np.testing.assert_array_equal(a["rays"], b["rays"])


def _process(run: Path, out: Path, scheduler: str, *extra: str) -> str:
    result = runner.invoke(app, ["process", str(run), "--out", str(out), "--scheduler", scheduler, *extra])
    assert result.exit_code == 0, result.output
    return result.output


def test_a_run_processed_through_a_real_scheduler_equals_the_local_path(captured, scheduler, tmp_path):
    from distributed import Client

    _, _, run = captured
    # No layout: the sources are found in the data, by tasks on the cluster too.
    _process(run, tmp_path / "dask", scheduler)
    _process(run, tmp_path / "here", "none")
    _assert_same(_results(tmp_path / "dask", run.stem), _results(tmp_path / "here", run.stem))
    with Client(scheduler, timeout=30) as client:
        ran = client.run_on_scheduler(lambda dask_scheduler: sorted(dask_scheduler.task_prefixes))
        workers = client.run(lambda: __import__("os").getpid())
    for prefix in ("process_position", "noise_estimate_at", "layout_box_at", "candidate_strength_at"):
        assert prefix in ran, ran
    assert len(set(workers.values())) == 2  # two worker processes


def test_the_worker_command_on_a_real_scheduler(captured, scheduler, tmp_path):
    _, _, source = captured
    data = Data(tmp_path / "data")
    try:
        run = data.run(source)
        job = data.catalog.create_job(run.id, options={"layout": LAYOUT})
        result = runner.invoke(app, ["worker", "--data-dir", str(data.root), "--scheduler", scheduler, "--once"])
        assert result.exit_code == 0, result.output
        done = data.catalog.get_job(job.id)
        assert done.state == "complete", (done, result.output)
        assert f"on Dask scheduler {scheduler}: 2 workers" in done.message
        assert Path(done.artifacts["report"]).is_file() and Path(done.artifacts["tm25"]).is_file()
    finally:
        data.catalog.close()


def _sections(page: str) -> list[str]:
    """The report's sections (everything after the header, which names the paths and the compute)."""
    return page.split("<h2>")[1:]


def test_the_default_local_cluster_is_sized_to_the_machine_and_streams(captured, tmp_path, caplog):
    from processing.light_run.run import process_run

    _, _, run = captured
    from processing.light_run.position import warm_up_worker

    with open_compute(warm_up=warm_up_worker) as compute:  # the default: "local"
        assert compute.dask and compute.threads() == default_workers()
        # Warmed: every worker has the processing imported and its first kernels loaded.
        warmed = compute.client.run(lambda: "processing.unmixing" in sys.modules and "processing.images" in sys.modules)
        assert len(warmed) == default_workers() and all(warmed.values())
        assert compute.description == f"local Dask cluster: {default_workers()} worker processes x 1 thread"
        # The workers run with the local cluster's lean settings (no profiler, slow monitors)
        # and without Dask's MALLOC_TRIM_THRESHOLD_, which makes every large array an mmap;
        # with one malloc arena, set before the process starts, so that the executor thread's
        # arrays reuse the heap rather than fault in fresh pages.
        settings = compute.client.run(
            lambda: (
                dask.config.get("distributed.worker.profile.enabled"),
                dask.config.get("distributed.admin.tick.interval"),
                os.environ.get("MALLOC_TRIM_THRESHOLD_"),
                os.environ.get("MALLOC_ARENA_MAX"),
            )
        )
        assert set(settings.values()) == {(False, "500ms", None, "1")}
        assert compute.client.run_on_scheduler(lambda dask_scheduler: "stealing" in dask_scheduler.extensions) is False
        # Every task runs its numba kernels on its own thread alone (numba's setting is per thread).
        from processing.light_run.position import prepare_task

        def task_threads():
            import numba

            prepare_task()
            return numba.get_num_threads()

        assert compute.client.submit(task_threads, pure=False).result() == 1
        # Bounded: never more than four tasks per worker thread in flight.
        held = []
        compute.map_unordered(
            time.sleep, [0.05] * 12, on_result=lambda item, _: held.append(len(compute.client.futures))
        )
        assert len(held) == 12 and max(held) <= compute.max_in_flight() == 4 * default_workers()
        with caplog.at_level(logging.INFO, logger="mirrorgonio.processing"):
            options = ProcessingOptions.checked(steps="hdr,sources", layout=LAYOUT)
            report = process_run(run, tmp_path / "dask", options, compute=compute)
        assert not [r.message for r in caplog.records if "drawn" in r.message]  # the workers drew their sections
        # A truth that cannot travel to the workers: its sections are drawn here, the page the same.
        from processing.report.page import write_report

        lock = threading.Lock()

        def truth(source, theta):
            with lock:
                return None

        pages = []
        for where in (compute, None):
            with caplog.at_level(logging.INFO, logger="mirrorgonio.processing"):
                path = write_report(
                    tmp_path / f"truth-{where is None}.html",
                    report.model,
                    samples=report.samples,
                    report=report,
                    truth=truth,
                    compute=where,
                )
            pages.append(_sections(path.read_text()))
        assert pages[0] == pages[1]
        assert [r.message for r in caplog.records if "drawn" in r.message]
        assert report.compute == compute.description and report.timings["positions"] > 0
        peaks = compute.worker_peak_rss()
        assert len(peaks) == default_workers() and all(0 < p < 4 << 30 for p in peaks.values())
    process_run(run, tmp_path / "here", ProcessingOptions.checked(steps="hdr,sources", layout=LAYOUT))
    _assert_same(_results(tmp_path / "dask", run.stem), _results(tmp_path / "here", run.stem))
    # The report's sections drawn by the workers are the ones drawn here, figures and all.
    remote, local = ((tmp_path / where / f"{run.stem}.report.html").read_text() for where in ("dask", "here"))
    assert _sections(remote) == _sections(local) and len(_sections(local)) == 9
    # The EXR and PNG previews were written by the workers, one per position.
    assert sorted(p.name for p in (tmp_path / "dask" / f"{run.stem}.hdr").iterdir()) == sorted(
        p.name for p in (tmp_path / "here" / f"{run.stem}.hdr").iterdir()
    )


def test_bad_run_files_through_the_scheduler_are_one_line_errors(captured, scheduler, tmp_path):
    _, _, run = captured
    content = run.read_bytes()
    broken = tmp_path / "broken.h5"
    broken.write_bytes(content[: len(content) // 2])
    result = runner.invoke(app, ["process", str(broken), "--out", str(tmp_path / "out"), "--scheduler", scheduler])
    assert result.exit_code == 2 and result.output.startswith(f"error: {broken}: truncated or corrupt"), result.output
    assert len(result.output.strip().splitlines()) == 1
    # Garbage in the frames: the header reads, a task's read fails, its error comes back.
    garbage = tmp_path / "garbage.h5"
    third = len(content) // 3
    garbage.write_bytes(
        content[:third] + bytes(np.random.default_rng(1).integers(0, 256, third, dtype=np.uint8)) + content[2 * third :]
    )
    result = runner.invoke(
        app, ["process", str(garbage), "--out", str(tmp_path / "out"), "--scheduler", scheduler, "--layout", LAYOUT]
    )
    assert result.exit_code == 2 and result.output.startswith(f"error: {garbage}: "), result.output
    assert len(result.output.strip().splitlines()) == 1


def test_a_scheduler_that_is_not_there_is_one_line():
    address = f"tcp://127.0.0.1:{free_port()}"
    with pytest.raises(ComputeError, match=f"--scheduler {address}: cannot reach the Dask scheduler"):
        open_compute(address, timeout_s=2)
    with pytest.raises(ComputeError, match="is not 'local', 'none', 'synchronous' or a Dask scheduler address"):
        open_compute("my-cluster")
    result = runner.invoke(app, ["process", "x.h5", "--scheduler", address.replace("tcp", "udp")])
    assert result.exit_code == 2 and "--scheduler: 'udp://" in result.output
