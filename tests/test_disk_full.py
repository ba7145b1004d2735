"""Write failures on a small file system the test mounts (a tmpfs; skipped, with the reason,
where mounting is not allowed): a full disk and a read-only one, at the level each happens —
the run file's writer, the catalog, and the daemon's run engine through its API."""

from __future__ import annotations

import errno
import gc
import os
import re
import subprocess
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from fastapi.testclient import TestClient
from test_runfile import SEED, make_header, position_data

from acquisition.daemon.app import create_app
from acquisition.daemon.engine import RunEngine
from acquisition.daemon.settings import load_settings
from drivers.contracts.runfile import RunFile, RunFileWriteError, RunFileWriter, storage_errno

N_POSITIONS = 20


@pytest.fixture()
def small_fs(tmp_path):
    """``mount(path, size_kb)``: a tmpfs of that size at ``path``, unmounted at the end."""
    mounted: list[Path] = []

    def mount(path: Path, size_kb: int) -> Path:
        if os.geteuid() != 0:
            pytest.skip("mounting a small file system needs root")
        path.mkdir(parents=True, exist_ok=True)
        result = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={size_kb}k", "tmpfs", str(path)], capture_output=True, text=True
        )
        if result.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here: {result.stderr.strip()}")
        mounted.append(path)
        return path

    yield mount
    for path in reversed(mounted):
        subprocess.run(["umount", "-l", str(path)], check=False)


def fill(path: Path, leave: int = 0) -> Path:
    """A file taking all the free space of ``path``'s file system but ``leave`` bytes."""
    free = os.statvfs(path.parent).f_bavail * os.statvfs(path.parent).f_frsize
    block = b"\xa5" * 65536
    with open(path, "wb") as f:
        todo = max(free - leave, 0)
        try:
            while todo > 0:
                todo -= f.write(block[: min(todo, len(block))])
                f.flush()
        except OSError as exc:
            assert exc.errno == errno.ENOSPC
    return path


def noisy_position(i: int):
    """Position ``i`` of test_runfile's run, its frames noise (which does not compress)."""
    measured, times, frames = position_data(SEED, i)
    for k, frame in enumerate(frames):
        frame.mosaic[:] = np.random.default_rng([SEED, i, k]).integers(0, 4096, frame.mosaic.shape)
    return measured, times, frames


def hdf5_open_objects() -> int:
    gc.collect()
    return h5py.h5f.get_obj_count(h5py.h5f.OBJ_ALL, h5py.h5f.OBJ_ALL)


def assert_positions_intact(path: Path, positions) -> None:
    with RunFile.open(path) as f:
        assert list(np.flatnonzero(f.complete)) == list(positions)
        for i in positions:
            expected = [frame.mosaic for frame in noisy_position(i)[2]]
            np.testing.assert_array_equal(f.frames(i)[: len(expected)], expected)


def test_a_write_the_disk_refuses_is_one_line_and_every_committed_position_survives(small_fs, tmp_path):
    disk = small_fs(tmp_path / "disk", 1024)
    baseline = hdf5_open_objects()
    filler = fill(disk / "filler", leave=300_000)
    path = disk / "run.h5"
    writer = RunFileWriter.create(path, make_header(N_POSITIONS))
    written: list[int] = []
    with pytest.raises(RunFileWriteError) as failure:
        for i in range(N_POSITIONS):
            writer.write_position(i, *noisy_position(i))
            written.append(i)
    assert str(failure.value) == f"no space left on device writing {path} (position {len(written)})"
    assert failure.value.errno == errno.ENOSPC and 5 <= len(written) < N_POSITIONS
    # The writer writes nothing more, and closes: HDF5 keeps nothing of the file open (a file
    # it could not close crashed the process at its next flush or at exit).
    with pytest.raises(RunFileWriteError, match="stopped after a failed write: no space left on device"):
        writer.set_status("failed", str(failure.value))
    writer.close()
    assert hdf5_open_objects() == baseline
    assert_positions_intact(path, written)
    # Space again: the run goes on (the file is salvaged, as a killed writer's) to its end.
    filler.unlink()
    with RunFileWriter.reopen(path) as writer:
        assert writer.first_incomplete() == len(written)
        for i in range(len(written), N_POSITIONS):
            writer.write_position(i, *noisy_position(i))
        writer.set_status("complete")
    assert hdf5_open_objects() == baseline
    assert_positions_intact(path, range(N_POSITIONS))


# --- the daemon ------------------------------------------------------------------------------
# The default rig's field of view in 250 x 164 pixels (82 kB a frame, ~33 kB in the run file),
# one exposure per position and one calibration frame: a run fits in a few hundred kB.
TINY_RIG = "[camera]\nwidth = 250\nheight = 164\npixel_pitch_m = 47.2e-6\n"
SMALL_RUN = {
    "count": 8,
    "bracket": {"mode": "fixed", "exposures_s": [0.001]},
    "calibration": {"dark": False, "ambient_exposures_s": [0.01]},
}


@pytest.fixture()
def daemon(tmp_path):
    """``start(data_dir)``: the daemon in process on a tiny rig, its devices simulated, its run
    thread, run files and catalog real; ``/health`` wants 0.2 MB free."""
    clients: list[TestClient] = []
    rig = tmp_path / "tiny.toml"
    rig.write_text(TINY_RIG)

    def start(data_dir: Path) -> tuple[TestClient, RunEngine]:
        settings = load_settings(None, data_dir=data_dir, rig=rig, storage={"min_free_mb": 0.2})
        settings.arm.simulated.speed_m_s = settings.arm.simulated.accel_m_s2 = float("inf")
        client = TestClient(
            create_app(settings), base_url="http://127.0.0.1", headers={"Content-Type": "application/json"}
        )
        client.__enter__()
        clients.append(client)
        return client, client.app.state.engine

    yield start
    for client in clients:
        client.__exit__(None, None, None)


def wait_end(http: TestClient, run_id: str, timeout: float = 60.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        status = http.get(f"/runs/{run_id}").json()
        if status["state"] not in ("queued", "running"):
            return status
        time.sleep(0.05)
    raise AssertionError(f"run {run_id} did not end: {status}")


def test_a_disk_that_fills_mid_run_fails_it_cleanly_and_the_run_resumes_once_space_is_freed(small_fs, tmp_path, daemon):
    disk = small_fs(tmp_path / "disk", 4 * 1024)
    # The camera's spool on another disk: the simulated camera's DNGs (62 kB, each deleted once
    # decoded) would otherwise race the run file's writes for the last kilobytes.
    (tmp_path / "spool").mkdir()
    (disk / "data").mkdir()
    (disk / "data" / "spool").symlink_to(tmp_path / "spool")
    http, engine = daemon(disk / "data")
    assert http.get("/health").json()["status"] == "ok"
    filler = fill(disk / "filler", leave=250_000)
    # The estimate does not fit: refused before anything is written, with both figures.
    refused = http.post("/runs", json=SMALL_RUN)
    assert refused.status_code == 507, refused.text
    assert re.fullmatch(
        r"the run \(8 positions, 9 frames of 250 x 164\) needs about 1\.6 MB, 0\.2 MB free in \S+/runs: "
        r'free some space, or send "force": true to start anyway',
        refused.json()["detail"],
    )
    assert http.get("/runs").json() == []
    run = http.post("/runs", json={**SMALL_RUN, "force": True}).json()
    failed = wait_end(http, run["id"])
    path = engine.catalog.get_run(run["id"]).path
    assert failed["state"] == "failed" and engine.busy is False
    assert re.fullmatch(rf"no space left on device writing {re.escape(path)} \(position \d+\)", failed["last_error"])
    assert 2 <= failed["positions_done"] < 8
    done = failed["positions_done"]
    with RunFile.open(path) as f:  # readable, every completed position whole
        assert list(np.flatnonzero(f.complete)) == list(range(done))
        kept = [f.timestamps(i) for i in range(done)]
        assert f.calibration_sets() == [("ambient", "before")]
    assert engine.devices.arm.status().moving is False
    health = http.get("/health")
    assert health.status_code == 503 and health.json()["status"] == "degraded"
    assert any(reason.startswith(f"data directory {disk / 'data'}: ") for reason in health.json()["reasons"])
    # The catalog's disk is full too: its writes are a 507 with one line, never a 500.
    rest = fill(disk / "rest")
    for answer in (
        http.post(f"/runs/{run['id']}/process", json={}),
        http.post("/runs", json={**SMALL_RUN, "force": True}),
        http.post(f"/runs/{run['id']}/resume"),
    ):
        assert answer.status_code == 507, answer.text
        assert "\n" not in answer.json()["detail"]
    assert http.post(f"/runs/{run['id']}/process", json={}).json()["detail"] == (
        f"no space left on device writing the catalog {engine.catalog.path}"
    )
    # Space again: healthy, and the run resumes (its file salvaged) to its end, without a restart.
    filler.unlink()
    rest.unlink()
    assert http.get("/health").json() == {**health.json(), "status": "ok", "reasons": []}
    assert http.post(f"/runs/{run['id']}/resume").status_code == 200
    assert wait_end(http, run["id"])["state"] == "complete"
    with RunFile.open(path) as f:
        assert f.complete.all() and f.status == "complete"
        for i in range(done):
            np.testing.assert_array_equal(f.timestamps(i), kept[i])
    assert http.post(f"/runs/{run['id']}/process", json={}).status_code == 201


def remount(path: Path, mode: str) -> None:
    subprocess.run(["mount", "-o", f"remount,{mode}", str(path)], check=True, capture_output=True)


def test_a_read_only_data_directory_degrades_health_and_a_forced_run_fails_cleanly(small_fs, tmp_path, daemon):
    runs = small_fs(tmp_path / "data" / "runs", 2048)
    http, engine = daemon(tmp_path / "data")
    remount(runs, "ro")
    health = http.get("/health")
    assert health.status_code == 503 and f"data directory {runs}: read-only file system" in health.json()["reasons"]
    request = {**SMALL_RUN, "count": 2}
    refused = http.post("/runs", json=request)
    assert refused.status_code == 503
    assert refused.json()["detail"] == (
        f"the run (2 positions, 3 frames of 250 x 164): data directory {runs}: read-only file system"
    )
    run = http.post("/runs", json={**request, "force": True}).json()
    failed = wait_end(http, run["id"])
    assert failed["state"] == "failed" and not engine.busy
    assert failed["last_error"] == f"read-only file system writing {runs / (run['id'] + '.h5')}"
    remount(runs, "rw")
    assert http.get("/health").json()["status"] == "ok"
    assert http.post(f"/runs/{run['id']}/resume").status_code == 200
    assert wait_end(http, run["id"])["state"] == "complete"
    with RunFile.open(runs / f"{run['id']}.h5") as f:
        assert f.complete.all()


@pytest.mark.parametrize(
    ("error", "code"),
    [
        (RuntimeError("Unable to flush (file write failed: errno = 28, error message = 'No space left')"), 28),
        (OSError(errno.EROFS, "Read-only file system"), errno.EROFS),
        (ValueError("run.h5: cannot create run.h5.lock: Input/output error"), errno.EIO),
        (OSError("Unable to open (file signature not found)"), None),
    ],
)
def test_the_storage_refusal_behind_an_error_is_found_in_its_code_or_words(error, code):
    assert storage_errno(error) == code


def test_results_sent_to_a_full_disk_are_a_507_and_leave_the_run_as_it_was(small_fs, daemon, tmp_path):
    """A worker on another machine sends its results to a daemon whose runs' disk is full: 507
    in one line, the run file untouched, nothing half-unpacked beside it."""
    import io
    import tarfile

    data = tmp_path / "data"
    runs = small_fs(data / "runs", 512)
    http, engine = daemon(data)
    catalog = engine.catalog
    run = catalog.create_run(preset=None, path_for=lambda run_id: runs / f"{run_id}.h5", n_positions=2, request={})
    Path(run.path).write_bytes(b"the run file")
    catalog.transition_run(run.id, "aborted")
    job = catalog.create_job(run.id)
    assert catalog.claim_job("w-remote").id == job.id
    fill(runs / "filler", leave=16_384)
    archive = io.BytesIO()
    with tarfile.open(fileobj=archive, mode="w") as tar:
        member = tarfile.TarInfo(f"{run.id}.results.h5")
        member.size = 200_000
        tar.addfile(member, io.BytesIO(os.urandom(member.size)))
    answer = http.put(
        f"/jobs/{job.id}/results",
        params={"worker_id": "w-remote"},
        content=archive.getvalue(),
        headers={"Content-Type": "application/x-tar"},
    )
    assert answer.status_code == 507, answer.text
    assert re.fullmatch(r"no space left on device writing .*\.tar", answer.json()["detail"])
    assert Path(run.path).read_bytes() == b"the run file"
    assert sorted(p.name for p in runs.iterdir()) == sorted([Path(run.path).name, "filler"])
