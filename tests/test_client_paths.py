"""Files a client names in a request (a run's ``light_results``, a job's ``layout``): regular
files only, a size limit, read with a time limit off the event loop, and answers that tell a
client without the token nothing of the machine's filesystem (``acquisition.daemon.client_files``)."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import httpx
from conftest import REDUCED_RIG, write_config
from fastapi.testclient import TestClient
from test_worker import Data

from acquisition.daemon.app import create_app
from acquisition.daemon.settings import load_settings
from drivers.config_files import MAX_TEXT_BYTES

PUBLIC = "{field}: the {what} cannot be used (the daemon's or worker's log says why)"


def bad_files(folder: Path) -> dict[str, Path]:
    """The paths a hostile or mistaken client may name, each of another kind."""
    folder.mkdir()
    fifo = folder / "pipe.json"
    os.mkfifo(fifo)  # nothing writes: an ordinary open for reading waits for ever
    sparse = folder / "sparse.json"
    with open(sparse, "wb") as f:
        f.truncate(100 * MAX_TEXT_BYTES)  # 1.6 GB that take no disk, never to be read
    (folder / "dir.json").mkdir()
    return {
        "/dev/zero": Path("/dev/zero"),  # endless
        "fifo": fifo,
        "directory": folder / "dir.json",
        "sparse": sparse,
        "missing": folder / "missing.json",
    }


class HealthWatch:
    """``GET /health`` asked again and again from another thread; the slowest answer kept."""

    def __init__(self, url: str):
        self.url, self.slowest, self.answers = url, 0.0, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)

    def _watch(self) -> None:
        with httpx.Client(base_url=self.url, timeout=10.0) as http:
            while not self._stop.is_set():
                started = time.monotonic()
                http.get("/health")
                self.slowest = max(self.slowest, time.monotonic() - started)
                self.answers += 1
                self._stop.wait(0.05)

    def __enter__(self) -> HealthWatch:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(15)


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


def test_a_daemon_refuses_special_files_as_light_results_quickly_and_says_nothing_of_them(daemon_factory, tmp_path):
    """A real daemon without a token (any local program may ask): every bad path gets the same
    422 within a second, /health answers within a second all along, no run is created, the
    daemon does not grow, and its log says why each was refused."""
    daemon = daemon_factory(write_config(tmp_path / "daemon.toml", tmp_path / "data"))
    paths = bad_files(tmp_path / "client")
    public = PUBLIC.format(field="light_results", what="light model")
    rss_before = rss_mb(daemon.proc.pid)
    with daemon.client() as http, HealthWatch(daemon.url) as health:
        time.sleep(0.2)
        for name, path in paths.items():
            started = time.monotonic()
            answer = http.post("/runs", json={"light_results": str(path)})
            assert time.monotonic() - started < 1.0, name
            assert answer.status_code == 422 and answer.json() == {"detail": public}, (name, answer.text)
        runs = http.get("/runs").json()
    assert health.answers >= 3 and health.slowest < 1.0
    assert runs == []
    assert rss_mb(daemon.proc.pid) - rss_before < 100
    log = daemon.log_path.read_text()
    for words in ("a character device", "a FIFO (named pipe)", "a directory", "more than the 16 MiB", "not found"):
        assert "(a client's light model): light_results: " in log and words in log, words


def test_a_token_holder_is_told_why_the_file_cannot_be_used(tmp_path):
    token = "t" * 32
    settings = load_settings(None, data_dir=tmp_path / "data", rig=REDUCED_RIG, token=token)
    fifo = tmp_path / "pipe.json"
    os.mkfifo(fifo)
    with TestClient(
        create_app(settings), base_url="http://127.0.0.1", headers={"Authorization": f"Bearer {token}"}
    ) as http:
        answer = http.post("/runs", json={"light_results": str(fifo)})
    assert answer.status_code == 422
    reason = f"light_results: {fifo}: a FIFO (named pipe), not a light model (a regular file)"
    assert answer.json() == {"detail": reason}


def test_a_job_whose_layout_cannot_be_used_fails_at_once_and_its_error_says_nothing_of_it(tmp_path):
    """The worker reads the layout before it starts the job: /dev/zero, a FIFO, a directory, a
    huge file, a missing one, a file that is not a layout: each job ends ``failed`` (never
    left ``running`` with heartbeats) within a second, with the same error for all."""
    data = Data(tmp_path / "data")
    try:
        paths = bad_files(tmp_path / "client")
        (not_a_layout := tmp_path / "client" / "notes.toml").write_text("title = 'notes'\n")
        paths["not a layout"] = not_a_layout
        run = data.run(state="complete")
        public = PUBLIC.format(field="layout", what="layout file")
        worker = data.worker(heartbeat_s=0.1)
        for name, path in paths.items():
            job = data.catalog.create_job(run.id, steps="hdr,sources", options={"layout": str(path)})
            started = time.monotonic()
            done = worker.run_once()
            assert time.monotonic() - started < 1.0, name
            assert done.id == job.id and done.state == "failed" and done.error == public, (name, done)
        assert data.catalog.requeue_stale_jobs(0.0) == []  # none left running
    finally:
        data.catalog.close()
