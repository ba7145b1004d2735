"""`mirrorgonio worker`: jobs from the catalog, heartbeats, requeues, bad and live run files,
and the daemon's job endpoints that serve what the worker wrote.

The processing runs without Dask here (``scheduler none``); tests/test_dask.py runs it on
real Dask clusters.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import zipfile
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest
from conftest import REDUCED_RIG, unable, write_config

from acquisition.daemon.catalog import Catalog
from acquisition.daemon.worker import ARTIFACT_KINDS, JobLostError, JobWorker, one_line, writer_alive
from drivers.contracts.rig import load_rig
from drivers.contracts.runfile import PositionTimes, RunFile, RunFileWriter, RunHeader
from processing.exports.tm25 import read_tm25
from processing.light_run.errors import ProcessingError
from processing.results import Results, position_file_for
from sim_devices.camera import SimulatedCamera
from sim_devices.lights import LIGHTS_DIR
from sim_devices.world import SimWorld

EXPOSURES = [0.0002, 0.001, 0.005, 0.025]
POSITIONS = (20, 33, 45)
LATE = 27  # a position the live run adds last
LAYOUT = str(LIGHTS_DIR / "five-gaussians.toml")


@pytest.fixture(scope="module")
def captured(tmp_path_factory):
    """Brackets of three positions of the reduced rig, and a finished run file of them."""
    folder = tmp_path_factory.mktemp("frames")
    rig = load_rig(REDUCED_RIG)
    tools = rig.tool_poses()
    here = {"pose": tools[0]}
    camera = SimulatedCamera(rig, SimWorld(lambda: here["pose"]), folder / "spool", seed=3)
    frames = {}
    for index in (*POSITIONS, LATE):
        here["pose"] = tools[index]
        frames[index] = [camera.capture(t) for t in EXPOSURES]
    path = folder / "run-test.h5"
    with write_run(path, rig, frames, POSITIONS) as writer:
        writer.set_status("complete", "")
    return rig, frames, path


def write_run(path, rig, frames, positions, status="running") -> RunFileWriter:
    """A run file with ``positions`` complete, its writer still open (status ``status``)."""
    header = RunHeader(
        run_id=Path(path).stem,
        rig=rig,
        tool_poses=rig.tool_poses(),
        light_poses=rig.light_poses(),
        max_exposures=len(EXPOSURES),
        frame_shape=(rig.camera.height, rig.camera.width),
        bracket={"mode": "fixed", "exposures_s": EXPOSURES},
        metadata={},
        devices={},
        software_version="test",
        created_utc="2026-11-21T00:00:00+00:00",
        preset="light-sweep",
    )
    writer = RunFileWriter.create(path, header)
    for index in positions:
        writer.write_position(index, rig.tool_poses()[index], PositionTimes(0.0, 0.0, 0.0), frames[index])
    writer.set_status(status, "")
    return writer


class Data:
    """A data folder with a catalog, as the daemon keeps it."""

    def __init__(self, root: Path):
        self.root = root
        (root / "runs").mkdir(parents=True, exist_ok=True)
        self.catalog_path = root / "catalog.sqlite"
        self.later = timedelta(0)  # the catalog's clock runs this far ahead of the real one
        self.catalog = Catalog(self.catalog_path, clock=lambda: datetime.now(UTC) + self.later)

    def run(self, source: Path | None = None, state: str = "complete"):
        """A catalog run whose file is a copy of ``source`` (none: no file yet), brought to ``state``."""
        record = self.catalog.create_run(
            preset="light-sweep", path_for=lambda rid: self.root / "runs" / f"{rid}.h5", n_positions=66, request={}
        )
        if source is not None:
            shutil.copy(source, record.path)
        for step in {
            "complete": ["running", "complete"],
            "running": ["running"],
            "interrupted": ["running", "interrupted"],
            "aborted": ["aborted"],
        }[state]:
            record = self.catalog.transition_run(record.id, step)
        return record

    def worker(self, **options) -> JobWorker:
        options.setdefault("worker_id", "w-test")
        return JobWorker(self.catalog, **options)


@pytest.fixture()
def data(tmp_path):
    d = Data(tmp_path / "data")
    yield d
    d.catalog.close()


def test_a_worker_processes_a_job_and_records_its_result_files(captured, data):
    _, _, source = captured
    run = data.run(source)
    job = data.catalog.create_job(run.id, steps="hdr,trace,fit", options={"layout": LAYOUT})  # the old names
    done = data.worker().run_once()
    assert done.id == job.id and done.state == "complete", done
    assert done.error is None and done.progress == 1.0 and done.claimed_by == "w-test"
    folder = Path(run.path).parent
    assert done.result_dir == str(folder)  # beside the run
    assert set(done.artifacts) == set(ARTIFACT_KINDS)
    stem = Path(run.path).stem
    assert done.artifacts["report"] == str(folder / f"{stem}.report.html")
    assert done.artifacts["tm25"] == str(folder / f"{stem}.tm25ray")
    for path in done.artifacts.values():
        assert Path(path).is_file() and Path(path).stat().st_size > 100, path
    # The note leads with the verdict on the light model, then what was processed where.
    assert done.message.startswith("quality ok: the templates explain the sweep to "), done.message
    assert "; 3 of 66 positions in " in done.message and "this process" in done.message
    with Results.open(done.artifacts["results"]) as results:
        assert results.hdr_done.sum() == 3
    assert data.worker().run_once() is None  # nothing left


def test_bad_run_files_fail_their_job_in_one_line_and_the_queue_goes_on(captured, data, tmp_path):
    _, _, source = captured
    truncated = data.run(source)
    size = os.path.getsize(truncated.path)
    with open(truncated.path, "r+b") as f:
        f.truncate(size // 2)
    corrupt = data.run(source)
    with open(corrupt.path, "r+b") as f:  # garbage over the frames, the header intact
        f.seek(size // 3)
        f.write(np.random.default_rng(0).integers(0, 256, size // 3, dtype=np.uint8).tobytes())
    text = data.run()
    Path(text.path).write_text("not a run file\n")
    missing = data.run()  # no file at all
    good = data.run(source)
    jobs = [
        data.catalog.create_job(r.id, options={"layout": LAYOUT}) for r in (truncated, corrupt, text, missing, good)
    ]
    seen = []
    assert data.worker().run(once=True, on_job=seen.append) == 5
    assert [j.id for j in seen] == [j.id for j in jobs]
    ended = {j.id: data.catalog.get_job(j.id) for j in jobs}
    for job, run in zip(jobs[:4], (truncated, corrupt, text, missing), strict=True):
        failed = ended[job.id]
        assert failed.state == "failed" and failed.artifacts == {}, failed
        assert "\n" not in failed.error and run.path in failed.error, failed.error
    assert "truncated or corrupt" in ended[jobs[0].id].error
    assert "cannot read" in ended[jobs[1].id].error or "corrupt" in ended[jobs[1].id].error
    assert "not an HDF5 file" in ended[jobs[2].id].error
    assert "run file not found" in ended[jobs[3].id].error
    assert ended[jobs[4].id].state == "complete"


def test_a_job_for_a_run_being_acquired_waits_or_takes_the_complete_positions(captured, data):
    rig, frames, source = captured
    finished = data.run(source)  # queued after the live run's job: must not be held up by it
    live = data.run(state="running")
    writer = write_run(live.path, rig, frames, POSITIONS)
    try:
        waiting = data.catalog.create_job(live.id, options={"layout": LAYOUT})
        other = data.catalog.create_job(finished.id, options={"layout": LAYOUT})
        partial = data.catalog.create_job(live.id, options={"layout": LAYOUT, "partial": True})
        worker = data.worker(wait_s=60.0)
        assert worker.run(once=True) == 2  # the two that can run
        job = data.catalog.get_job(waiting.id)
        assert job.state == "queued" and job.error is None and job.claimed_by is None
        assert job.message.startswith(f"waiting: run {live.id} is still being acquired (its state is running)")
        assert data.catalog.get_job(other.id).state == "complete"
        done = data.catalog.get_job(partial.id)
        assert done.state == "complete" and "; 3 of 66 positions (partial" in done.message, done.message
        with Results.open(done.artifacts["results"]) as results:
            assert np.flatnonzero(results.hdr_done).tolist() == list(POSITIONS)
        # The acquisition ends: the waiting job runs once its wait is over, on every position.
        writer.write_position(LATE, rig.tool_poses()[LATE], PositionTimes(0.0, 0.0, 0.0), frames[LATE])
        writer.set_status("complete", "")
    finally:
        writer.close()
    data.catalog.transition_run(live.id, "complete")
    assert worker.run_once() is None  # still inside its wait
    data.later = timedelta(seconds=61)  # its wait is over (the catalog's clock, not a race with the processing)
    done = worker.run_once()
    assert done.id == waiting.id and done.state == "complete" and "; 4 of 66 positions in" in done.message


def test_a_run_file_still_held_by_its_writer_waits_even_if_the_catalog_gave_up_on_it(captured, data):
    rig, frames, _ = captured
    stuck = data.run(state="interrupted")  # e.g. a daemon restarted while another process still writes
    writer = write_run(stuck.path, rig, frames, POSITIONS[:1])
    try:
        assert writer_alive(stuck.path)
        job = data.catalog.create_job(stuck.id, steps="hdr")
        waited = data.worker(wait_s=0.0).run_once()
        assert waited.state == "queued" and "its run file says running and a writer holds it" in waited.message
    finally:
        writer.close()  # the writer is gone; the file still says "running"
    assert not writer_alive(stuck.path)
    with RunFile.open(stuck.path) as f:
        assert f.status == "running"
    done = data.worker().run_once()
    assert done.id == job.id and done.state == "complete" and done.message.startswith("1 of 66 positions")
    assert set(done.artifacts) == {"results"}  # hdr only


def test_a_live_run_with_nothing_complete_waits_even_for_a_partial_job(captured, data):
    rig, frames, _ = captured
    live = data.run(state="running")
    writer = write_run(live.path, rig, frames, ())
    try:
        data.catalog.create_job(live.id, options={"partial": True})
        waited = data.worker().run_once()
        assert waited.state == "queued" and "no complete position yet" in waited.message
    finally:
        writer.close()


def test_an_orphaned_job_is_requeued_and_taken_by_another_worker(captured, data):
    _, _, source = captured
    run = data.run(source)
    job = data.catalog.create_job(run.id, options={"layout": LAYOUT})
    assert data.catalog.claim_job("ghost").id == job.id  # a worker that then died
    worker = data.worker(worker_id="w2", stale_after_s=0.3)
    assert worker.run_once() is None  # its heartbeat is still fresh
    time.sleep(0.4)
    done = worker.run_once()
    assert done.id == job.id and done.state == "complete" and done.claimed_by == "w2"


def test_heartbeats_carry_the_progress_and_a_lost_job_is_abandoned(data, tmp_path):
    run = data.run(state="complete")
    data.catalog.create_job(run.id)
    seen = []

    def slow(job, path, steps, progress):
        for step in range(1, 6):
            time.sleep(0.12)
            progress("hdr", step, 10)
        seen.append(data.catalog.get_job(job.id))
        return tmp_path, {}, "slow work done"

    done = data.worker(heartbeat_s=0.05, process=slow).run_once()
    assert done.state == "complete" and done.message == "slow work done" and done.step is None
    beating = seen[0]
    assert beating.state == "running" and beating.step == "hdr" and beating.message.startswith("HDR merge: ")
    assert 0.05 + 0.4 * 0.3 <= beating.progress <= 0.05 + 0.4 * 0.5  # the merge's share of the whole, in part
    assert beating.heartbeat_utc > beating.created_utc

    # A job that fails keeps the step it failed in.
    data.catalog.create_job(run.id)

    def failing(job, path, steps, progress):
        progress("fits", 0, 1)
        time.sleep(0.15)
        raise ProcessingError("run.h5: the fit diverged")

    failed = data.worker(heartbeat_s=0.05, process=failing).run_once()
    assert (failed.state, failed.step, failed.error) == ("failed", "fits", "run.h5: the fit diverged")

    # Another worker takes the job over (this one was taken for dead): this one stops.
    stolen = data.catalog.create_job(run.id)

    def robbed(job, path, steps, progress):
        with Catalog(data.catalog_path) as other:
            assert other.requeue_stale_jobs(0) == [job.id]
            assert other.claim_job("thief").id == job.id
        for step in range(1, 50):
            time.sleep(0.05)
            progress("estimate", step, 50)  # raises JobLostError once a heartbeat found the job gone
        raise AssertionError("the worker did not notice")

    after = data.worker(heartbeat_s=0.05, process=robbed).run_once()
    assert after.id == stolen.id and after.state == "running" and after.claimed_by == "thief"


def test_a_killed_worker_process_leaves_its_job_to_the_next_worker(captured, data, tmp_path):
    _, _, source = captured
    run = data.run(source)
    job = data.catalog.create_job(run.id, options={"layout": LAYOUT})
    exe = Path(sys.executable).with_name("mirrorgonio")
    log = open(tmp_path / "worker-1.log", "wb")
    proc = subprocess.Popen(
        [
            str(exe),
            "worker",
            "--data-dir",
            str(data.root),
            "--scheduler",
            "none",
            "--id",
            "doomed",
            "--heartbeat",
            "0.2",
            "--poll",
            "0.1",
        ],
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    try:
        deadline = time.monotonic() + 60
        while data.catalog.get_job(job.id).state != "running":
            assert proc.poll() is None, (tmp_path / "worker-1.log").read_text()
            assert time.monotonic() < deadline, "the worker never claimed the job"
            time.sleep(0.02)
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
        log.close()
    orphan = data.catalog.get_job(job.id)
    assert orphan.state == "running" and orphan.claimed_by == "doomed"
    time.sleep(1.2)
    done = data.worker(worker_id="survivor", stale_after_s=1.0).run_once()
    assert done.id == job.id and done.state == "complete" and done.claimed_by == "survivor", done


def test_the_worker_command_once_and_its_errors(captured, data, tmp_path):
    from typer.testing import CliRunner

    from acquisition.cli import app

    _, _, source = captured
    run = data.run(source)
    job = data.catalog.create_job(run.id, options={"layout": LAYOUT})
    runner = CliRunner()
    result = runner.invoke(app, ["worker", "--data-dir", str(data.root), "--scheduler", "none", "--once"])
    assert result.exit_code == 0, result.output
    assert f"{job.id} complete ({run.id}): quality ok: " in result.output
    assert "; 3 of 66 positions" in result.output
    assert "  report: " in result.output and "  tm25: " in result.output
    missing = runner.invoke(app, ["worker", "--data-dir", str(tmp_path / "nope"), "--once"])
    assert missing.exit_code == 2 and "is not a folder" in missing.output
    bad = runner.invoke(app, ["worker", "--data-dir", str(data.root), "--scheduler", "udp://x", "--once"])
    assert bad.exit_code == 2 and bad.output.startswith("error: --scheduler: 'udp://x' is not")
    assert len(bad.output.strip().splitlines()) == 1


def wait_for_step(http, job_id: str, step: str, timeout_s: float = 5.0) -> str:
    """The job's ``step`` from ``GET /jobs/{id}`` once a heartbeat has recorded ``step`` (or the
    last one seen when the time is up)."""
    deadline = time.monotonic() + timeout_s
    while True:
        seen = http.get(f"/jobs/{job_id}").json()["step"]
        if seen == step or time.monotonic() > deadline:
            return seen
        time.sleep(0.01)


def test_one_line_reasons():

    assert one_line(ProcessingError("run.h5: position 3:\n  bad")) == "run.h5: position 3: bad"
    assert one_line(KeyError("x")) == "KeyError: 'x'"
    assert one_line(RuntimeError()) == "RuntimeError"
    assert len(one_line(ValueError("x" * 5000))) == 1000
    assert issubclass(JobLostError, RuntimeError)


# --- the daemon's job endpoints ----------------------------------------------------------
def test_the_daemon_serves_a_jobs_state_and_exactly_its_result_files(captured, data, tmp_path):
    from fastapi.testclient import TestClient

    from acquisition.daemon.app import create_app
    from acquisition.daemon.settings import load_settings

    _, _, source = captured
    run = data.run(source)
    live = data.run(state="running")
    settings = load_settings(None, data_dir=data.root, rig=REDUCED_RIG)
    with TestClient(create_app(settings), base_url="http://127.0.0.1") as http:
        bad = http.post(f"/runs/{run.id}/process", json={"steps": "hdr,dance"})
        assert bad.status_code == 422 and "unknown step 'dance'" in str(bad.json()["detail"])
        assert http.post(f"/runs/{run.id}/process", json={"steps": "hdr", "fit": "spline"}).status_code == 422
        assert (
            http.post(f"/runs/{run.id}/process", json={"fit_aperture": "yes"}).status_code == 422
        )  # auto, always or never
        assert http.post(f"/runs/{run.id}/process", json={"fit_sensor_distance": 1}).status_code == 422
        for field, value in (("rays", 10**9), ("rays", 10), ("lamp_lumens", -1), ("manufacturer", "Acme\nInc")):
            refused = http.post(f"/runs/{run.id}/process", json={field: value})
            assert refused.status_code == 422 and refused.json()["detail"][0]["loc"][-1] == field, (field, value)
        both = http.post(f"/runs/{run.id}/process", json={"lamp_lumens": 800, "candela_per_unit": 2.0})
        assert both.status_code == 422 and "give one" in str(both.json()["detail"])
        names = {"manufacturer": "Acme", "luminaire": "Spot 5", "lamp": "LED", "lamp_lumens": 850.0, "rays": 2000}
        queued = http.post(f"/runs/{run.id}/process", json={"steps": "hdr,sources", **names})
        assert queued.status_code == 201
        job = queued.json()
        assert (job["state"], job["steps"], job["options"], job["artifacts"]) == ("queued", "hdr,sources", names, {})
        assert job["step"] is None
        partial = http.post(f"/runs/{live.id}/process", json={"partial": True, "estimator": "templates"}).json()
        assert partial["options"] == {"partial": True, "estimator": "templates"} and partial["steps"] == "hdr,sources"
        assert http.get(f"/jobs/{job['id']}/artifacts/report").status_code == 404  # nothing yet

        # The job's step, as GET /jobs/{id} says it while the worker processes (each step seen
        # by the next heartbeat), in the processing's order.
        said: list[str] = []

        def watched(progress):
            def step_by_step(step, done, total):
                progress(step, done, total)
                if done == 0:
                    said.append(wait_for_step(http, job["id"], step))

            return step_by_step

        worker = data.worker(  # the worker's own processing, its progress watched on the way
            heartbeat_s=0.02,
            process=lambda job_, path, steps, progress: JobWorker._process_run(
                worker, job_, path, steps, watched(progress)
            ),
        )
        done = worker.run_once()  # the oldest job first
        assert done.id == job["id"] and done.state == "complete", done
        assert said == ["checksums", "noise", "hdr", "layout", "estimate", "fits", "exports", "report"]
        ies = Path(done.artifacts["ies"]).read_text()
        assert "[MANUFAC] Acme" in ies and "[LUMINAIRE] Spot 5" in ies and "[LAMP] LED" in ies
        assert read_tm25(done.artifacts["tm25"])[0]["n_rays"] == 2000
        status = http.get(f"/jobs/{job['id']}").json()
        assert status["state"] == "complete" and status["progress"] == 1.0 and status["claimed_by"] == "w-test"
        assert status["step"] is None  # complete: no step runs
        assert status["artifacts"] == {kind: f"/jobs/{job['id']}/artifacts/{kind}" for kind in ARTIFACT_KINDS}
        report = http.get(status["artifacts"]["report"])
        assert report.status_code == 200 and report.headers["content-type"].startswith("text/html")
        assert report.headers["content-disposition"].startswith("inline") and b"<html" in report.content[:500].lower()
        ies = http.get(status["artifacts"]["ies"])
        assert (
            ies.status_code == 200
            and ies.text.startswith("IES:LM-63")
            and "attachment" in ies.headers["content-disposition"]
        )
        assert ies.content == Path(done.artifacts["ies"]).read_bytes()
        rays = http.get(status["artifacts"]["tm25"])
        assert rays.status_code == 200 and rays.content == Path(done.artifacts["tm25"]).read_bytes()
        # The results download as one ZIP archive (the index and each position's file, stored),
        # which unpacks, anywhere, to a results file that reads the same numbers.
        archive = http.get(status["artifacts"]["results"])
        assert archive.status_code == 200 and archive.headers["content-type"] == "application/zip"
        results_path = Path(done.artifacts["results"])
        assert f'filename="{results_path.name.removesuffix(".h5")}.zip"' in archive.headers["content-disposition"]
        with zipfile.ZipFile(io.BytesIO(archive.content)) as unpacked:
            assert unpacked.testzip() is None
            with Results.open(results_path) as here:
                done_positions = np.flatnonzero(here.hdr_done)
                assert unpacked.namelist() == [results_path.name] + [
                    f"{results_path.name.removesuffix('.results.h5')}.hdr/position-{i:03d}.h5" for i in done_positions
                ]
                assert all(i.compress_type == zipfile.ZIP_STORED for i in unpacked.infolist())
                unpacked.extractall(tmp_path / "downloaded")
                with Results.open(tmp_path / "downloaded" / results_path.name) as there:
                    for i in done_positions:
                        np.testing.assert_array_equal(there.radiance(i), here.radiance(i))
                        np.testing.assert_array_equal(there.variance(i), here.variance(i))
        # A position file gone from the server: the download is refused whole, naming it.
        moved = position_file_for(results_path, int(done_positions[-1]))
        moved.rename(moved.with_suffix(".away"))
        incomplete = http.get(status["artifacts"]["results"])
        assert incomplete.status_code == 404 and f"{moved.name} is no longer there" in incomplete.json()["detail"]
        moved.with_suffix(".away").rename(moved)
        # Only the files the job recorded, nothing else.
        assert http.get(f"/jobs/{job['id']}/artifacts/catalog").status_code == 404
        assert http.get(f"/jobs/{job['id']}/artifacts/..%2F..%2Fcatalog.sqlite").status_code == 404
        assert http.get(f"/jobs/{job['id']}/artifacts/../../catalog.sqlite").status_code == 404
        assert http.get("/jobs/job-nope/artifacts/report").status_code == 404
        Path(done.artifacts["ldt"]).unlink()
        gone = http.get(status["artifacts"]["ldt"])
        assert gone.status_code == 404 and "no longer there" in gone.json()["detail"]
        listed = http.get("/jobs", params={"run_id": run.id}).json()
        assert [j["id"] for j in listed] == [job["id"]] and listed[0]["artifacts"] == status["artifacts"]


def test_the_results_archive_streams_a_block_at_a_time(tmp_path):
    """The ZIP stream never holds more than one block (plus a header) of a member, and is a
    valid archive of every member, byte for byte, under its name."""
    from acquisition.daemon.api.jobs import zip_stream

    rng = np.random.default_rng(7)
    members = []
    for name, size in (("a.results.h5", 3_000_000), ("a.hdr/position-000.h5", 1), ("a.hdr/position-002.h5", 0)):
        path = tmp_path / name.replace("/", "_")
        path.write_bytes(rng.integers(0, 256, size, dtype=np.uint8).tobytes())
        members.append((path, name))
    block = 64 * 1024
    chunks = list(zip_stream(members, block=block))
    assert max(len(c) for c in chunks) <= block + 200 and len(chunks) > 3_000_000 // block
    with zipfile.ZipFile(io.BytesIO(b"".join(chunks))) as archive:
        assert archive.testzip() is None and archive.namelist() == [name for _, name in members]
        for path, name in members:
            assert archive.read(name) == path.read_bytes()


def test_a_job_on_a_run_with_a_corrupt_frame_fails_in_one_line_or_skips_it_with_ignore_corrupt(captured, data):
    """Over REST: without ``ignore_corrupt`` the job fails at the checksum pass, naming the run,
    the position and the frame; with it the job completes without that position, says so, and
    its light model's provenance lists the frame."""
    import json

    from fastapi.testclient import TestClient
    from test_checksums import flip_bit

    from acquisition.daemon.app import create_app
    from acquisition.daemon.settings import load_settings

    rig, frames, _ = captured
    run = data.run(state="complete")
    with write_run(run.path, rig, frames, (*POSITIONS, LATE)) as writer:  # four positions: three left to fit
        writer.set_status("complete", "")
    flip_bit(run.path, 33, 2, bit=8 * 1000 + 3)
    settings = load_settings(None, data_dir=data.root, rig=REDUCED_RIG)
    with TestClient(create_app(settings), base_url="http://127.0.0.1") as http:
        strict = http.post(f"/runs/{run.id}/process", json={"steps": "hdr", "layout": LAYOUT}).json()
        lenient = http.post(
            f"/runs/{run.id}/process", json={"steps": "hdr,sources", "layout": LAYOUT, "ignore_corrupt": True}
        ).json()
        assert lenient["options"] == {"ignore_corrupt": True, "layout": LAYOUT}
        assert http.post(f"/runs/{run.id}/process", json={"ignore_corrupt": "yes"}).status_code == 422
        failed = data.worker().run_once()
        assert failed.id == strict["id"] and failed.state == "failed"
        assert failed.error == (
            f"{run.path}: position 33 frame 2 (exposure index 2, 0.005 s) fails its checksum (corrupt data: the "
            "stored bytes differ from those written); the job option ignore_corrupt processes the rest"
        )
        assert not Path(run.path).with_name(f"{run.id}.results.h5").exists()  # before any work
        done = data.worker().run_once()
        assert done.id == lenient["id"] and done.state == "complete", done
        status = http.get(f"/jobs/{done.id}").json()
        assert status["options"]["ignore_corrupt"] is True
        assert "; 3 of 66 positions in " in status["message"]
        assert status["message"].endswith(
            "; skipped positions 33 (ignore_corrupt): 1 corrupt frames: position 33 frame 2 (exposure index 2, "
            "0.005 s) fails its checksum (corrupt data: the stored bytes differ from those written)"
        )
    provenance = json.loads(Path(done.artifacts["light_model"]).read_text())["provenance"]
    assert provenance["skipped_corrupt"]["positions"] == [33]
    assert [(f["position"], f["frame"]) for f in provenance["skipped_corrupt"]["frames"]] == [(33, 2)]
    with Results.open(done.artifacts["results"]) as results:
        assert np.flatnonzero(results.hdr_done).tolist() == sorted((20, 45, LATE))


# --- a lab: rigs sharing a PostgreSQL catalog, a worker without their disks -----------------
TOKEN = "lab-token-0123456789abcdef"


def _lab_daemon(daemon_factory, tmp_path, url, rig):
    """A real daemon of rig ``rig`` on the shared catalog, with a data folder of its own."""
    data_dir = tmp_path / rig
    config = write_config(tmp_path / f"{rig}.toml", data_dir, extra="")
    text = config.read_text()
    config.write_text(f'rig_name = "{rig}"\ncatalog = "{url}"\n' + text)
    return daemon_factory(config, token=TOKEN), data_dir


def _finished_run(catalog, data_dir, source):
    run = catalog.create_run(
        preset="light-sweep", path_for=lambda rid: data_dir / "runs" / f"{rid}.h5", n_positions=66, request={}
    )
    Path(run.path).parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(source, run.path)
    catalog.transition_run(run.id, "running")
    return catalog.transition_run(run.id, "complete")


def _without_disk(data_dir: Path) -> list[str]:
    """The command prefix that runs a program in a mount namespace of its own where ``data_dir``
    is an empty tmpfs: a worker on another machine, which does not see the daemon's disk."""
    probe = subprocess.run(["unshare", "-m", "true"], capture_output=True, check=False)
    if probe.returncode != 0:
        unable(f"a worker without the daemon's disk needs a mount namespace: {probe.stderr.decode().strip()}")
    return ["unshare", "-m", "sh", "-c", f'mount -t tmpfs tmpfs "{data_dir}" && exec "$0" "$@"']


def test_a_worker_without_the_daemons_disk_fetches_the_run_and_sends_the_results_back(
    captured, tmp_path, postgres_server, daemon_factory
):
    from acquisition.benchmarks.lab import SAME_RESULTS_RTOL, light_model_difference

    _, _, source = captured
    url = postgres_server.create_database("lab_remote_worker")
    daemon, data_dir = _lab_daemon(daemon_factory, tmp_path, url, "rig-a")
    with Catalog(url, rig="rig-a") as rig_a:
        assert rig_a.daemon_url("rig-a") == daemon.url  # the daemon said where it answers
        run = _finished_run(rig_a, data_dir, source)
        remote_job = rig_a.create_job(run.id, steps="hdr,sources", options={"layout": LAYOUT})
        worker_dir = tmp_path / "worker-b"
        exe = Path(sys.executable).with_name("mirrorgonio")
        command = [str(exe), "worker", "--catalog", url, "--data-dir", str(worker_dir), "--scheduler", "none"]
        done_cli = subprocess.run(
            [*_without_disk(data_dir), *command, "--once", "--id", "w-remote"],
            capture_output=True,
            text=True,
            timeout=300,
            env={**os.environ, "MG_TOKEN": TOKEN},
            check=False,
        )
        assert done_cli.returncode == 0, done_cli.stdout + done_cli.stderr
        done = rig_a.get_job(remote_job.id)
        assert done.state == "complete" and done.claimed_by == "w-remote", (done, done_cli.stderr[-3000:])
        folder = Path(run.path).parent
        assert done.result_dir == str(folder)  # the daemon keeps the results with the run
        assert set(done.artifacts) == set(ARTIFACT_KINDS)
        for kind, path in done.artifacts.items():
            assert Path(path).parent == folder and Path(path).is_file(), (kind, path)
        assert not any(worker_dir.rglob("*.h5")), "the worker's copies are deleted once the daemon has the results"
        with daemon.client() as http:
            assert http.get(f"/jobs/{done.id}/artifacts/report").status_code == 200
            late = http.put(  # results for a job that is no longer running under that worker
                f"/jobs/{done.id}/results",
                params={"worker_id": "w-remote"},
                content=b"",
                headers={"Content-Type": "application/x-tar"},
            )
            assert late.status_code == 409 and f"job {done.id} is complete" in late.json()["detail"]
            assert http.get(f"/jobs/{done.id}/artifacts/results").status_code == 200  # the results with their files
        # The same run processed by a worker on the daemon's own disk gives the same light model.
        remote_model = json.loads(Path(done.artifacts["light_model"]).read_text())
        local_job = rig_a.create_job(run.id, steps="hdr,sources", options={"layout": LAYOUT})
        with Catalog(url) as lab:
            local = JobWorker(lab, worker_id="w-local").run_once()
        assert local.id == local_job.id and local.state == "complete"
        local_model = json.loads(Path(local.artifacts["light_model"]).read_text())
        # The same to rounding: two processes may sum in another order (their BLAS threads).
        assert light_model_difference(remote_model["sources"], local_model["sources"]) < SAME_RESULTS_RTOL


def test_a_cut_fetch_resumes_and_a_wrong_one_is_caught(captured, tmp_path, postgres_server, daemon_factory):
    from acquisition.daemon.transfer import DaemonUnreachableError, RunFetcher
    from drivers.contracts.runfile import file_sha256

    _, _, source = captured
    url = postgres_server.create_database("lab_fetch")
    daemon, data_dir = _lab_daemon(daemon_factory, tmp_path, url, "rig-a")
    with Catalog(url, rig="rig-a") as rig_a:
        run = _finished_run(rig_a, data_dir, source)
        fetcher = RunFetcher(rig_a.daemon_url, tmp_path / "worker", TOKEN, fetch_patience_s=2)
        local = fetcher.run_folder(run) / Path(run.path).name
        part, tag = local.with_name(local.name + ".part"), local.with_name(local.name + ".etag")
        with daemon.client() as http, http.stream("GET", f"/runs/{run.id}/file") as answer:
            etag = answer.headers["etag"]
        whole = Path(run.path).read_bytes()
        local.parent.mkdir(parents=True)
        # Cut after a third: the rest is asked for with Range, and the whole checks out.
        part.write_bytes(whole[: len(whole) // 3])
        tag.write_text(etag)
        assert file_sha256(fetcher.fetch(run)) == file_sha256(run.path)
        # A copy whose first third went wrong: the daemon's SHA-256 catches it, and it starts over.
        local.unlink()
        part.write_bytes(b"\0" * (len(whole) // 3))
        tag.write_text(etag)
        with pytest.raises(DaemonUnreachableError, match="its SHA-256 differs"):
            fetcher.fetch(run)
        assert not part.exists()
        assert file_sha256(fetcher.fetch(run)) == file_sha256(run.path)
        # Without the token, the daemon gives nothing.
        with pytest.raises(Exception, match="401"):
            RunFetcher(rig_a.daemon_url, tmp_path / "other", None).fetch(run)
        # A daemon that does not answer: the job waits (its copy so far is kept for the next try).
        daemon.stop()
        with pytest.raises(DaemonUnreachableError, match=f"fetching run {run.id} from {daemon.url}"):
            RunFetcher(rig_a.daemon_url, tmp_path / "third", TOKEN, fetch_patience_s=0.5).fetch(run)


def test_partial_processing_without_the_daemons_disk_is_refused_with_its_reason(tmp_path, postgres_server):
    from acquisition.daemon.transfer import RunFetcher

    url = postgres_server.create_database("lab_partial")
    with Catalog(url, rig="rig-a") as rig_a, Catalog(url) as lab:
        rig_a.register_daemon("http://rig-a.lab:8000")
        run = rig_a.create_run(
            preset="light-sweep", path_for=lambda rid: f"/srv/rig-a/runs/{rid}.h5", n_positions=66, request={}
        )
        rig_a.transition_run(run.id, "running")
        job = rig_a.create_job(run.id, options={"partial": True})
        fetcher = RunFetcher(lab.daemon_url, tmp_path / "worker")
        done = JobWorker(lab, worker_id="w-remote", fetcher=fetcher).run_once()
        assert done.id == job.id and done.state == "failed"
        assert done.error.startswith("partial processing needs the run file on the worker's disk: ")
        assert f"still being acquired on rig rig-a, and /srv/rig-a/runs/{run.id}.h5 is not here" in done.error
        # A whole-run job on it waits for the run's end as everywhere.
        waiting = rig_a.create_job(run.id)
        again = JobWorker(lab, worker_id="w-remote", fetcher=fetcher).run_once()
        assert again.id == waiting.id and again.state == "queued" and "still being acquired" in again.message


def test_a_results_archive_cannot_write_outside_its_folder_or_over_the_run(tmp_path):
    import tarfile

    from acquisition.daemon.transfer import TransferError, pack_results, unpack_results

    folder = tmp_path / "runs"
    folder.mkdir()
    (folder / "run-1.h5").write_bytes(b"the run")
    made = tmp_path / "made"
    (made / "run-1.report").mkdir(parents=True)
    (made / "run-1.report" / "index.html").write_text("report")
    (made / "run-1.ies").write_text("ies")
    (made / "run-1.h5").write_text("the worker's copy of the run")
    archive = tmp_path / "ok.tar"
    archive.write_bytes(b"".join(pack_results(made, exclude={"run-1.h5"})))
    files = unpack_results(archive, folder, {"run-1.h5"})
    assert files == {
        "run-1.ies": str(folder / "run-1.ies"),
        "run-1.report/index.html": str(folder / "run-1.report" / "index.html"),
    }
    assert (folder / "run-1.h5").read_bytes() == b"the run" and (folder / "run-1.ies").read_text() == "ies"

    def archive_of(name, member):
        path = tmp_path / name
        with tarfile.open(path, "w") as tar:
            tar.addfile(member, io.BytesIO(b"x") if member.isfile() else None)
        return path

    outside = tarfile.TarInfo("../escaped")
    outside.size = 1
    link = tarfile.TarInfo("run-1.link")
    link.type, link.linkname = tarfile.SYMTYPE, "/etc/passwd"
    over = tarfile.TarInfo("run-1.h5")
    over.size = 1
    for name, member in (("outside.tar", outside), ("link.tar", link), ("over.tar", over)):
        with pytest.raises(TransferError, match="results archive: "):
            unpack_results(archive_of(name, member), folder, {"run-1.h5"})
    assert not (tmp_path / "escaped").exists() and not (folder / "run-1.link").exists()
    assert (folder / "run-1.h5").read_bytes() == b"the run"


def test_each_daemon_lists_the_labs_runs_and_changes_only_its_own(captured, tmp_path, postgres_server, daemon_factory):
    _, _, source = captured
    url = postgres_server.create_database("lab_listing")
    daemon_a, data_a = _lab_daemon(daemon_factory, tmp_path, url, "rig-a")
    daemon_b, _ = _lab_daemon(daemon_factory, tmp_path, url, "rig-b")
    with Catalog(url, rig="rig-a") as rig_a:
        run = _finished_run(rig_a, data_a, source)
        job = rig_a.create_job(run.id)
    with daemon_b.client() as b, daemon_a.client() as a:
        assert b.get("/health").json()["rig"] == "rig-b"
        assert b.get("/runs").json() == []  # its own rig's runs
        lab = b.get("/runs", params={"rig": "all"}).json()
        assert [(r["id"], r["rig"], r["read_only"]) for r in lab] == [(run.id, "rig-a", True)]
        assert [r["id"] for r in b.get("/runs", params={"rig": "rig-a"}).json()] == [run.id]
        assert a.get("/runs").json()[0]["read_only"] is False
        assert b.get(f"/runs/{run.id}").json()["state"] == "complete"
        assert [j["id"] for j in b.get("/jobs", params={"rig": "all"}).json()] == [job.id]
        assert b.get("/jobs").json() == []
        refused = b.post(f"/runs/{run.id}/process", json={})
        assert refused.status_code == 403
        assert refused.json()["detail"] == (
            f"cannot queue a job for it: run {run.id} belongs to rig 'rig-a'; rig 'rig-b' can only read it"
        )
        for control in ("pause", "resume", "abort"):  # the run engine's controls refuse it the same way
            answer = b.post(f"/runs/{run.id}/{control}")
            assert answer.status_code == 403 and f"cannot {control} it: run {run.id} belongs to rig" in answer.text
        assert a.get(f"/runs/{run.id}").json()["state"] == "complete"
        file = b.get(f"/runs/{run.id}/file")
        assert file.status_code == 404 and daemon_a.url in file.json()["detail"]
        served = a.get(f"/runs/{run.id}/file")
        assert served.status_code == 200 and served.headers["repr-digest"].startswith("sha-256=:")
        bad = b.get("/runs", params={"rig": "Rig A"})
        assert bad.status_code == 400 and "not a rig's name" in bad.json()["detail"]


def test_a_daemon_that_answers_it_cannot_now_is_tried_again_and_a_refusal_is_not(captured, tmp_path):
    """A 503 (the daemon's catalog or disk away) is passing: the fetch tries again; a 404 is an answer."""
    import http.server
    import threading as th

    from acquisition.daemon.catalog import RunRecord
    from acquisition.daemon.transfer import RunFetcher, TransferError, repr_digest
    from drivers.contracts.runfile import file_sha256

    _, _, source = captured
    body, answers = Path(source).read_bytes(), ["503", "200", "bare"]

    class Daemon(http.server.BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802 - the http.server protocol
            code = answers.pop(0) if answers else "404"
            self.send_response(200 if code == "bare" else int(code))
            if code in ("200", "bare"):
                if code == "200":  # "bare": a file without its SHA-256, which cannot be checked
                    self.send_header("Repr-Digest", repr_digest(file_sha256(source)))
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)
            else:
                self.send_header("Content-Type", "application/json")
                self.end_headers()
                self.wfile.write(json.dumps({"detail": f"said {code}"}).encode())

        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Daemon)
    th.Thread(target=server.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{server.server_address[1]}"
        now = datetime.now(UTC)
        run = RunRecord(
            id="run-x",
            rig="rig-a",
            created_utc=now,
            updated_utc=now,
            state="complete",
            preset=None,
            path="/elsewhere/run-x.h5",
            n_positions=66,
            positions_done=3,
            current_position=None,
            exposures_per_position=4,
            started_utc=now,
            finished_utc=now,
            last_error=None,
            request={},
            seconds_per_position=None,
        )
        fetcher = RunFetcher(lambda rig: url, tmp_path / "w", fetch_patience_s=10)
        assert file_sha256(fetcher.fetch(run)) == file_sha256(source)  # after one 503
        fetcher.forget(run)
        with pytest.raises(TransferError, match="the daemon sent no SHA-256"):
            fetcher.fetch(run)
        with pytest.raises(TransferError, match="404 said 404") as refused:
            fetcher.fetch(run)
        assert type(refused.value) is TransferError  # not "unreachable": the job fails, it does not wait
    finally:
        server.shutdown()
