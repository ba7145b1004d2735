"""The daemon's run engine through its API, in process (the lifespan starts the simulated
rig over Modbus TCP on loopback): control, faults, auto bracketing, events and files."""

from __future__ import annotations

import json
import math
import threading
import time

import numpy as np
import pytest
from conftest import REDUCED_RIG
from fastapi.testclient import TestClient

from acquisition.daemon.app import create_app
from acquisition.daemon.settings import load_settings
from drivers.contracts.runfile import RunFile

EXPOSURES = [0.0002, 0.001, 0.005]
JSON = {"Content-Type": "application/json"}


@pytest.fixture()
def daemon(tmp_path):
    def start(speed=0.5, camera_latency_s=0.0, **overrides):
        overrides.setdefault("rig", REDUCED_RIG)
        settings = load_settings(None, data_dir=tmp_path / "data", **overrides)
        settings.camera.simulated.latency_s = camera_latency_s
        settings.arm.simulated.speed_m_s = speed
        settings.arm.simulated.accel_m_s2 = 10 * speed
        # A host the daemon answers to; the control endpoints take JSON only, body or none.
        client = TestClient(create_app(settings), base_url="http://127.0.0.1", headers=JSON)
        client.__enter__()
        started.append(client)
        return client, client.app.state.engine

    started: list[TestClient] = []
    yield start
    for client in started:
        client.__exit__(None, None, None)


def wait_state(http, run_id, states, timeout=120.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        status = http.get(f"/runs/{run_id}").json()
        if status["state"] in states:
            return status
        time.sleep(0.05)
    raise AssertionError(f"{run_id} never reached {states}: {status}")


def test_presets_devices_and_health(daemon):
    http, _ = daemon()
    presets = http.get("/presets").json()
    assert presets["presets"]["light-sweep"]["positions"] == 66
    # The ball rig has no object to photograph: the preset is listed, refused, and says why.
    assert presets["presets"]["object-arc"]["valid"] is False
    assert "[object]" in presets["presets"]["object-arc"]["error"]
    assert presets["default_bracket"]["exposures_s"] == EXPOSURES
    devices = http.get("/devices").json()
    assert devices["arm"]["connected"] and "ModbusArm" in devices["arm"]["identity"]
    assert "SIM-0001" in devices["camera"]["identity"]
    health = http.get("/health")
    assert health.status_code == 200 and health.json()["status"] == "ok"


def test_pause_takes_effect_between_frames_and_resume_completes(daemon):
    http, engine = daemon(speed=0.05)
    run = http.post("/runs", json={"count": 6, "bracket": {"mode": "fixed", "exposures_s": EXPOSURES}}).json()
    wait_state(http, run["id"], {"running"})
    while http.get(f"/runs/{run['id']}").json()["positions_done"] < 1:
        time.sleep(0.05)
    assert http.post(f"/runs/{run['id']}/pause").json()["state"] == "paused"
    time.sleep(0.8)  # any frame in flight finishes, then nothing more happens
    frozen = http.get(f"/runs/{run['id']}").json()["positions_done"]
    time.sleep(1.0)
    assert http.get(f"/runs/{run['id']}").json()["positions_done"] == frozen
    assert frozen < 6
    assert http.post(f"/runs/{run['id']}/resume").json()["state"] == "running"
    assert wait_state(http, run["id"], {"complete", "failed"})["state"] == "complete"


def test_abort_stops_the_arm_and_keeps_the_frames(daemon):
    http, engine = daemon(speed=0.05)
    run = http.post("/runs", json={"count": 20, "bracket": {"mode": "fixed", "exposures_s": EXPOSURES}}).json()
    while http.get(f"/runs/{run['id']}").json()["positions_done"] < 2:
        time.sleep(0.05)
    aborted = http.post(f"/runs/{run['id']}/abort").json()
    assert aborted["state"] == "aborted"
    assert not engine.devices.simulated["stage"].moving
    with RunFile.open(engine.catalog.get_run(run["id"]).path) as run_file:
        assert run_file.status == "aborted"
        done = run_file.completed_positions()
        assert len(done) >= 2 and run_file.frames(int(done[0])).shape[0] == 3
    # A second run may start now.
    assert http.post("/runs", json={"count": 1}).status_code == 201


def test_stop_arm_mid_move_pauses_the_run_and_resume_retakes_the_position(daemon):
    http, engine = daemon(speed=0.02)  # the first move (about 14 cm) takes seconds
    stage = engine.devices.simulated["stage"]
    run = http.post("/runs", json={"count": 2, "bracket": {"mode": "fixed", "exposures_s": [0.001]}}).json()
    deadline = time.monotonic() + 10
    while not stage.moving and time.monotonic() < deadline:
        time.sleep(0.02)
    assert stage.moving
    assert http.post("/arm/stop").status_code == 202
    deadline = time.monotonic() + 10  # the stage decelerates in its own thread
    while stage.moving and time.monotonic() < deadline:
        time.sleep(0.02)
    assert not stage.moving
    assert stage.true_pose().distance_to(stage.target)[0] > 0.01  # stopped well short
    paused = wait_state(http, run["id"], {"paused"})
    assert "stopped by the operator at position 0" in paused["last_error"]
    assert paused["positions_done"] == 0
    http.post(f"/runs/{run['id']}/resume")
    final = wait_state(http, run["id"], {"complete", "failed"}, timeout=60)
    assert final["state"] == "complete", final
    with RunFile.open(engine.catalog.get_run(run["id"]).path) as run_file:
        target = run_file.header.tool_poses[0]
        assert run_file.measured_pose(0).distance_to(target)[0] < 50e-6


def test_transient_device_errors_are_retried(daemon):
    http, engine = daemon()
    server = engine.devices.simulated["modbus_server"]
    run = http.post("/runs", json={"count": 6, "bracket": {"mode": "fixed", "exposures_s": [0.001]}}).json()
    while http.get(f"/runs/{run['id']}").json()["positions_done"] < 1:
        time.sleep(0.02)
    server.drop_connections()  # a cable pulled and put back
    while http.get(f"/runs/{run['id']}").json()["positions_done"] < 3:
        time.sleep(0.02)
    server.stop_answering(True)  # the controller misses replies for 0.6 s (under its watchdog)
    threading.Timer(0.6, server.stop_answering, args=(False,)).start()
    final = wait_state(http, run["id"], {"complete", "failed"}, timeout=90)
    assert final["state"] == "complete", final["last_error"]


def test_a_silence_longer_than_the_watchdog_fails_the_run_with_the_devices_message(daemon):
    http, engine = daemon()
    server = engine.devices.simulated["modbus_server"]
    run = http.post("/runs", json={"count": 6, "bracket": {"mode": "fixed", "exposures_s": [0.001]}}).json()
    while http.get(f"/runs/{run['id']}").json()["positions_done"] < 1:
        time.sleep(0.02)
    server.stop_answering(True)  # longer than the controller's 3 s watchdog
    threading.Timer(4.5, server.stop_answering, args=(False,)).start()
    final = wait_state(http, run["id"], {"complete", "failed"}, timeout=90)
    assert final["state"] == "failed"
    assert "alarm 0x0301: communication watchdog expired" in final["last_error"]
    with RunFile.open(engine.catalog.get_run(run["id"]).path) as run_file:
        assert run_file.complete.sum() >= 1 and run_file.status == "failed"


def test_auto_bracket_meters_and_stores_the_chosen_exposures(daemon):
    http, engine = daemon()
    run = http.post("/runs", json={"count": 34, "bracket": {"mode": "auto", "target_snr": 20}}).json()
    assert wait_state(http, run["id"], {"complete", "failed"}, timeout=180)["state"] == "complete"
    rig = engine.rig
    with RunFile.open(engine.catalog.get_run(run["id"]).path) as run_file:
        exposures = run_file.exposures(33)  # the sources face the camera at the middle position
        assert 2 <= len(exposures) <= 7
        assert np.all(np.diff(exposures) > 0)
        assert np.all(exposures[1:] / exposures[:-1] <= 4.0 + 1e-9)
        shortest = run_file.frames(33)[0].astype(float) - rig.camera.black_level_dn
        headroom = rig.camera.white_level - rig.camera.black_level_dn
        assert shortest.max() < headroom  # the brightest pixel is unsaturated in the shortest
        assert np.percentile(shortest, 99.99) > 0.4 * headroom  # ...and well exposed


def test_progress_events_stream_until_the_run_ends(daemon):
    http, _ = daemon()
    run = http.post("/runs", json={"count": 3, "bracket": {"mode": "fixed", "exposures_s": [0.001]}}).json()
    states, done = [], []
    with http.stream("GET", f"/runs/{run['id']}/events") as stream:
        for line in stream.iter_lines():
            if line.startswith("data: "):
                event = json.loads(line[6:])
                states.append(event["state"])
                done.append(event["positions_done"])
    assert states[-1] == "complete"
    assert done == sorted(done) and done[-1] == 3


def test_preview_download_and_processing_job(daemon):
    http, _ = daemon()
    assert http.get("/preview.png").status_code == 404  # nothing taken yet
    run = http.post("/runs", json={"count": 2, "bracket": {"mode": "fixed", "exposures_s": [0.001]}}).json()
    assert wait_state(http, run["id"], {"complete", "failed"})["state"] == "complete"
    png = http.get(f"/runs/{run['id']}/preview.png")
    assert png.status_code == 200 and png.content[:8] == b"\x89PNG\r\n\x1a\n"
    import cv2

    image = cv2.imdecode(np.frombuffer(png.content, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image.shape == (164, 250) and image.max() == 255  # half resolution superpixels
    file = http.get(run["file_url"])
    assert file.status_code == 200 and file.content[:8] == b"\x89HDF\r\n\x1a\n"
    job = http.post(f"/runs/{run['id']}/process", json={"steps": "hdr"})
    assert job.status_code == 201 and job.json()["state"] == "queued"
    assert http.get(f"/jobs/{job.json()['id']}").json()["run_id"] == run["id"]
    assert http.get("/runs/nonesuch").status_code == 404
    assert http.post("/runs/nonesuch/process").status_code == 404


def test_download_is_refused_while_the_run_is_written(daemon):
    http, _ = daemon(speed=0.02)
    run = http.post("/runs", json={"count": 3, "bracket": {"mode": "fixed", "exposures_s": [0.001]}}).json()
    answer = http.get(run["file_url"])
    assert answer.status_code == 409 and "still being written" in answer.json()["detail"]
    http.post(f"/runs/{run['id']}/abort")


def test_an_impossible_preset_schedule_is_a_422_naming_the_pose(daemon):
    http, _ = daemon()
    answer = http.post("/runs", json={"preset": "poses", "poses": [{"position_m": [0.0, 0.0, 0.01]}]})
    assert answer.status_code == 422
    assert "position 0: the light is inside the ball" in answer.json()["detail"]


def test_the_next_move_overlaps_the_writing_of_the_frames_just_taken(daemon, monkeypatch):
    from acquisition.daemon import run_thread as runner

    spans = {}
    original = runner.RunFileWriter.write_position

    def slow_write(self, index, measured, times, frames):
        start = time.time()
        time.sleep(0.3)  # a slow disk
        original(self, index, measured, times, frames)
        spans[index] = (start, time.time())

    monkeypatch.setattr(runner.RunFileWriter, "write_position", slow_write)
    http, engine = daemon()
    run = http.post("/runs", json={"count": 5, "bracket": {"mode": "fixed", "exposures_s": [0.001]}}).json()
    assert wait_state(http, run["id"], {"complete", "failed"})["state"] == "complete"
    with RunFile.open(engine.catalog.get_run(run["id"]).path) as run_file:
        for i in range(4):
            # Position i+1's move began while position i was still being written.
            assert run_file.times(i + 1).move_started < spans[i][1], i


def test_stop_arm_during_a_capture_also_pauses_the_run(daemon):
    http, engine = daemon(camera_latency_s=0.4)  # captures take far longer than moves
    stage = engine.devices.simulated["stage"]
    run = http.post("/runs", json={"count": 6, "bracket": {"mode": "fixed", "exposures_s": [0.001, 0.002]}}).json()
    while http.get(f"/runs/{run['id']}").json()["positions_done"] < 1:
        time.sleep(0.02)
    while stage.moving:
        time.sleep(0.01)
    assert http.post("/arm/stop").status_code == 202
    paused = wait_state(http, run["id"], {"paused", "complete"}, timeout=10)
    assert paused["state"] == "paused" and "stopped by the operator" in paused["last_error"]
    http.post(f"/runs/{run['id']}/resume")
    assert wait_state(http, run["id"], {"complete", "failed"}, timeout=60)["state"] == "complete"


def test_object_arc_run_records_its_object_and_light(daemon, tmp_path):
    """An object rig's daemon photographs the object on the arc and names its mesh and light."""
    from drivers.contracts.rig import DEFAULT_RIG_PATH, load_rig
    from drivers.contracts.runfile import file_sha256

    shipped = DEFAULT_RIG_PATH.parent / "object-vase.toml"
    text = shipped.read_text().replace("width = 2000", "width = 250").replace("height = 1312", "height = 164")
    text = text.replace("pixel_pitch_m = 5.9e-6", "pixel_pitch_m = 47.2e-6")
    text = text.replace('mesh = "objects/vase.obj"', f'mesh = "{shipped.parent / "objects" / "vase.obj"}"')
    rig_file = tmp_path / "vase.toml"
    rig_file.write_text(text)
    assert load_rig(rig_file).camera.width == 250
    light = tmp_path / "light.json"
    light.write_text(json.dumps({"format": "mirrorgonio-light-model", "provenance": {"run_id": "run-light"}}))
    http, engine = daemon(rig=rig_file)
    presets = http.get("/presets").json()["presets"]
    assert presets["object-arc"]["valid"] and presets["object-arc"]["positions"] == 5

    bad = http.post("/runs", json={"preset": "object-arc", "light_results": str(tmp_path / "missing.json")})
    assert bad.status_code == 422 and bad.json()["detail"].startswith("light_results: ")
    run = http.post(
        "/runs",
        json={
            "preset": "object-arc",
            "light_results": str(light),
            "bracket": {"mode": "fixed", "exposures_s": [1.0, 4.0]},
        },
    ).json()
    status = wait_state(http, run["id"], {"complete", "failed"})
    assert status["state"] == "complete", status
    with RunFile.open(engine.catalog.get_run(run["id"]).path) as f:
        refs = f.header.references
        assert f.header.preset == "object-arc" and f.complete.all()
    assert refs["light_model"] == {"path": str(light.resolve()), "sha256": file_sha256(light), "run_id": "run-light"}
    assert refs["object_mesh"]["sha256"] == file_sha256(load_rig(shipped).object.mesh)


def test_a_setting_that_is_not_a_finite_number_is_refused_naming_it(tmp_path, monkeypatch):
    """inf and nan are TOML literals (and strings an environment variable can hold): a capture
    timeout of inf was accepted before, and a capture that hangs then waited for ever."""
    from acquisition.daemon.settings import SettingsError

    config = tmp_path / "daemon.toml"
    config.write_text("[camera]\ncapture_timeout_s = inf\n")
    with pytest.raises(SettingsError) as caught:
        load_settings(config)
    assert str(caught.value) == f"{config}: camera.capture_timeout_s: Input should be a finite number (got inf)"
    monkeypatch.setenv("MG_CAMERA__SIMULATED__LATENCY_S", "nan")
    with pytest.raises(SettingsError, match=r"camera\.simulated\.latency_s: Input should be a finite number"):
        load_settings(None)
    monkeypatch.delenv("MG_CAMERA__SIMULATED__LATENCY_S")
    # Finite but beyond any wait a thread can make (threading refuses ~9e9 s).
    config.write_text("[camera]\ncapture_timeout_s = 1e300\n")
    with pytest.raises(SettingsError, match=r"camera\.capture_timeout_s: must be <= 86400 \(got 1e\+300\)$"):
        load_settings(config)
    # The one documented infinity: a simulated stage whose moves take no time.
    config.write_text("[arm.simulated]\nspeed_m_s = inf\naccel_m_s2 = inf\n")
    assert load_settings(config).arm.simulated.speed_m_s == math.inf
    config.write_text("[arm.simulated]\nspeed_m_s = nan\n")
    with pytest.raises(SettingsError, match=r"arm\.simulated\.speed_m_s: must be > 0 \(got nan\)$"):
        load_settings(config)
