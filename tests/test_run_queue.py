"""The queue of runs through the daemon's API, in process: a run asked for while another is in
progress waits (202, its place in the queue), may be moved or removed, and starts by itself
once the run ahead completes; a run that fails or is aborted holds the queue until the
operator resumes it or starts the queue; a queued run that no longer fits in the free space
holds it with the reason; a restart keeps the queue, held.

The rig is tiny (250 x 164 pixels), the arm instant, each run a few one-frame positions: the
daemon's run thread, run files and catalog are the real ones; the shared daemon's tests run
with the catalog on SQLite and on PostgreSQL.
"""

from __future__ import annotations

import os
import re
import time

import pytest
from fastapi.testclient import TestClient
from test_disk_full import TINY_RIG, daemon, fill, small_fs  # noqa: F401 - fixtures

from acquisition.daemon.app import create_app
from acquisition.daemon.catalog import Catalog
from acquisition.daemon.engine import REMOVED
from acquisition.daemon.models import RunRequest
from acquisition.daemon.settings import load_settings
from drivers.contracts.runfile import RunFile

FINAL = ("complete", "aborted", "failed", "interrupted")
#: A run of two positions of one frame, without calibration frames: a few tens of ms.
TINY = {"count": 2, "bracket": {"mode": "fixed", "exposures_s": [0.001]}, "calibration": {"before": False}}
#: The run the others queue behind (paused at once).
LONGER = {**TINY, "count": 4}


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def shared(request, tmp_path_factory):
    """One daemon for the tests that need no particular data directory (its simulated camera
    costs a second or two on its first frames), on each of the catalog's databases."""
    folder = tmp_path_factory.mktemp("queue")
    (folder / "tiny.toml").write_text(TINY_RIG)
    catalog = None
    if request.param == "postgresql":
        catalog = request.getfixturevalue("postgres_server").create_database(f"queue_{os.getpid()}")
    settings = load_settings(None, data_dir=folder / "data", rig=folder / "tiny.toml", catalog=catalog)
    settings.arm.simulated.speed_m_s = settings.arm.simulated.accel_m_s2 = float("inf")
    app = create_app(settings)
    with TestClient(app, base_url="http://127.0.0.1", headers={"Content-Type": "application/json"}) as http:
        yield http, app.state.engine


def state_of(http, run_id: str) -> dict:
    answer = http.get(f"/runs/{run_id}")
    assert answer.status_code == 200, answer.text
    return answer.json()


def wait_state(http, run_id: str, states, timeout: float = 20.0) -> dict:
    deadline = time.monotonic() + timeout
    while (status := state_of(http, run_id))["state"] not in states and time.monotonic() < deadline:
        time.sleep(0.01)
    assert status["state"] in states, status
    return status


def queued_ids(http) -> list[str]:
    queue = http.get("/queue").json()
    assert [run["queue_position"] for run in queue["runs"]] == list(range(1, len(queue["runs"]) + 1))
    return [run["id"] for run in queue["runs"]]


def paused_run(http, body=None) -> str:
    """A run started and paused at once: the rig stays taken while the test queues behind it."""
    answer = http.post("/runs", json=body or LONGER)
    assert answer.status_code == 201 and answer.json()["state"] == "running", answer.text
    paused = http.post(f"/runs/{answer.json()['id']}/pause")
    assert paused.status_code == 200 and paused.json()["state"] == "paused", paused.text
    return answer.json()["id"]


def test_runs_queue_behind_the_active_one_move_and_leave_it_and_start_in_turn(shared):
    http, engine = shared
    active = paused_run(http)
    queued = []
    for k in range(3):
        answer = http.post("/runs", json={**TINY, "notes": f"queued {k}"})
        assert answer.status_code == 202, answer.text
        assert answer.json()["state"] == "queued" and answer.json()["queue_position"] == k + 1
        assert answer.json()["step"] is None and answer.json()["started_utc"] is None
        queued.append(answer.json()["id"])
    first, second, third = queued
    assert queued_ids(http) == queued
    health = http.get("/health").json()
    assert (health["active_run"], health["queued_runs"], health["queue_held"]) == (active, 3, None)

    # Reorder: the runs named first, the others after them in their order.
    answer = http.put("/queue", json={"run_ids": [third, first]})
    assert answer.status_code == 200, answer.text
    assert [run["id"] for run in answer.json()["runs"]] == [third, first, second]
    assert state_of(http, second)["queue_position"] == 3
    # A run that is not queued is a 409 naming it; an unknown one a 404; a repeated one a 422.
    refused = http.put("/queue", json={"run_ids": [first, active]})
    assert refused.status_code == 409
    assert refused.json()["detail"] == f"cannot reorder the queue: run {active} is paused, not queued"
    assert http.put("/queue", json={"run_ids": ["run-nope"]}).status_code == 404
    twice = http.put("/queue", json={"run_ids": [first, first]})
    assert twice.status_code == 422 and f"named more than once: {first}" in twice.text
    assert queued_ids(http) == [third, first, second]  # unchanged by the refusals

    # Remove: the run ends aborted, never started, without a file; a second removal is a 409.
    removed = http.delete(f"/queue/{first}")
    assert removed.status_code == 200, removed.text
    assert removed.json()["state"] == "aborted" and removed.json()["last_error"] == REMOVED
    assert removed.json()["queue_position"] is None and removed.json()["started_utc"] is None
    again = http.delete(f"/queue/{first}")
    assert again.status_code == 409
    assert again.json()["detail"] == f"cannot remove it from the queue: run {first} is aborted, not queued"
    assert http.delete(f"/queue/{active}").status_code == 409  # the paused run is not the queue's
    assert queued_ids(http) == [third, second]

    # The active run completes: the queue runs on by itself, in its order.
    assert http.post(f"/runs/{active}/resume").status_code == 200
    ends = {run_id: wait_state(http, run_id, FINAL) for run_id in (active, third, second)}
    assert {run_id: end["state"] for run_id, end in ends.items()} == dict.fromkeys(ends, "complete")
    assert ends[active]["finished_utc"] <= ends[third]["started_utc"]
    assert ends[third]["finished_utc"] <= ends[second]["started_utc"]
    engine.wait(10)
    for run_id in (third, second):
        with RunFile.open(engine.catalog.get_run(run_id).path) as run_file:
            assert run_file.complete.all() and run_file.header.metadata["notes"] == f"queued {queued.index(run_id)}"
    assert queued_ids(http) == [] and http.get("/queue").json()["held"] is None
    assert state_of(http, first)["state"] == "aborted"
    # The rig free and the queue empty, a run starts at once.
    started = http.post("/runs", json=TINY)
    assert started.status_code == 201, started.text
    wait_state(http, started.json()["id"], FINAL)


def test_a_failed_or_aborted_run_holds_the_queue_until_resumed_or_started(shared):
    http, engine = shared
    # Aborted: the queue waits, says why, and goes on when started again.
    active = paused_run(http)
    waiting = http.post("/runs", json=TINY).json()["id"]
    assert http.post(f"/runs/{active}/abort").json()["state"] == "aborted"
    engine.wait(10)
    time.sleep(0.1)
    assert state_of(http, waiting)["state"] == "queued"
    queue = http.get("/queue").json()
    assert queue["held"] == f"run {active} was aborted" and queue["held_utc"] is not None
    assert http.get("/health").json()["queue_held"] == f"run {active} was aborted"
    started = http.post("/queue/start")
    assert started.status_code == 200 and started.json()["held"] is None, started.text
    assert wait_state(http, waiting, FINAL)["state"] == "complete"

    # Failed: an alarm on the run's second move holds the queue with the device's message; a
    # resume of the failed run (the fault cleared) releases it, and the queue goes on after it.
    stage = engine.devices.simulated["stage"]
    stage.inject_alarm_on_move(stage.move_count + 2)
    broken = http.post("/runs", json=LONGER).json()["id"]
    behind = http.post("/runs", json=TINY)
    assert behind.status_code == 202, behind.text
    failed = wait_state(http, broken, FINAL)
    assert failed["state"] == "failed" and "alarm" in failed["last_error"]
    engine.wait(10)
    held = http.get("/queue").json()["held"]
    assert held == f"run {broken} failed: {failed['last_error']}"
    assert state_of(http, behind.json()["id"])["state"] == "queued"
    assert http.post(f"/runs/{broken}/resume").status_code == 200
    assert http.get("/queue").json()["held"] is None
    assert wait_state(http, broken, FINAL)["state"] == "complete"
    assert wait_state(http, behind.json()["id"], FINAL)["state"] == "complete"
    # A queued run aborted through /runs/{id}/abort leaves the queue as DELETE /queue/{id} does.
    active = paused_run(http)
    queued = http.post("/runs", json=TINY).json()["id"]
    assert http.post(f"/runs/{queued}/abort").json()["last_error"] == REMOVED
    assert http.post(f"/runs/{active}/abort").json()["state"] == "aborted"
    assert http.get("/queue").json() == {"held": None, "held_utc": None, "runs": []}  # nothing left to hold


def test_a_queued_run_that_no_longer_fits_holds_the_queue_with_the_reason(small_fs, tmp_path, daemon):  # noqa: F811
    disk = small_fs(tmp_path / "disk", 8 * 1024)
    (tmp_path / "spool").mkdir()
    (disk / "data").mkdir()
    (disk / "data" / "spool").symlink_to(tmp_path / "spool")  # the camera's DNGs on another disk
    http, engine = daemon(disk / "data")
    active = paused_run(http, TINY)
    waiting = http.post("/runs", json={**TINY, "count": 8})
    assert waiting.status_code == 202, waiting.text  # it fits now (checked when queued, too)
    filler = fill(disk / "filler", leave=600_000)  # the disk fills meanwhile: the small run no longer fits
    assert http.post(f"/runs/{active}/resume").status_code == 200
    assert wait_state(http, active, FINAL)["state"] == "complete"
    engine.wait(10)
    assert state_of(http, waiting.json()["id"])["state"] == "queued"
    reason = http.get("/queue").json()["held"]
    assert re.fullmatch(
        rf"run {waiting.json()['id']} cannot start: the run \(8 positions, 8 frames of 250 x 164\) needs about "
        r'1\.5 MB, 0\.\d MB free in \S+/runs: free some space, or send "force": true to start anyway',
        reason,
    ), reason
    # Started by hand, it is refused with the same reason (507), and the queue stays held.
    refused = http.post("/queue/start")
    assert refused.status_code == 507 and reason.endswith(refused.json()["detail"]), refused.text
    assert http.get("/queue").json()["held"] == reason
    filler.unlink()  # space freed: the queue starts
    assert http.post("/queue/start").json()["held"] is None
    assert wait_state(http, waiting.json()["id"], FINAL)["state"] == "complete"


def test_a_restart_keeps_the_queue_held_until_the_interrupted_run_is_resumed(tmp_path, daemon):  # noqa: F811
    """The daemon died during a run with two runs queued (its catalog as it left it): after the
    restart the run is interrupted, the queued runs wait in their order and the queue is held;
    resuming the interrupted run releases it, and the queue runs on once that run completes."""
    data = tmp_path / "data"
    (data / "runs").mkdir(parents=True)
    with Catalog(data / "catalog.sqlite") as catalog:
        request = RunRequest.model_validate(TINY).model_dump(mode="json")
        runs = [
            catalog.create_run(
                preset="light-sweep",
                path_for=lambda run_id: data / "runs" / f"{run_id}.h5",
                n_positions=2,
                request=request,
            )
            for _ in range(3)
        ]
        died, *queued = (run.id for run in runs)
        catalog.transition_run(died, "running")
    http, engine = daemon(data)
    assert state_of(http, died)["state"] == "interrupted"
    queue = http.get("/queue").json()
    assert [run["id"] for run in queue["runs"]] == queued
    assert queue["held"] == f"the daemon restarted (run {died} interrupted): start the queue once the rig is ready"
    time.sleep(0.1)
    assert all(state_of(http, run_id)["state"] == "queued" for run_id in queued)  # nothing started by itself
    assert http.post(f"/runs/{died}/resume").status_code == 200
    for run_id in (died, *queued):
        assert wait_state(http, run_id, FINAL)["state"] == "complete"
