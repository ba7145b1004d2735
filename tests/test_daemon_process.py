"""The daemon as a lab uses it: a real process, driven over HTTP only, with the simulated
devices over Modbus TCP on loopback. Run files are checked through the run-file module."""

from __future__ import annotations

import math
import random
import time

import numpy as np
from conftest import free_port, wait_for, write_config
from pymodbus.client import ModbusTcpClient

from drivers.contracts.runfile import RunFile

EXPOSURES = [0.0002, 0.001, 0.005]


def test_full_default_sweep_over_http(tmp_path, daemon_factory):
    daemon = daemon_factory(write_config(tmp_path / "daemon.toml", tmp_path / "data"))
    with daemon.client() as http:
        assert http.get("/health").json()["status"] == "ok"
        started = http.post(
            "/runs",
            json={"preset": "light-sweep", "operator": "test", "bracket": {"mode": "fixed", "exposures_s": EXPOSURES}},
        )
        assert started.status_code == 201, started.text
        run = started.json()
        assert run["n_positions"] == 66
        final = wait_for(http, run["id"], {"complete", "failed", "aborted"}, timeout=600)
        assert final["state"] == "complete", final
        assert final["percent_done"] == 100.0
        download = http.get(final["file_url"])
        assert download.status_code == 200
    path = tmp_path / "downloaded.h5"
    path.write_bytes(download.content)
    with RunFile.open(path) as run_file:
        assert run_file.n_positions == 66
        assert run_file.complete.all()
        assert run_file.status == "complete"
        for i in range(66):
            np.testing.assert_allclose(run_file.exposures(i), EXPOSURES, rtol=1e-9)
            assert run_file.frames(i).shape == (3, 328, 500)
            measured, commanded = run_file.measured_pose(i), run_file.header.tool_poses[i]
            distance, angle = measured.distance_to(commanded)
            # The simulated stage: 20 um in-position tolerance plus 5 um read-back noise.
            assert distance < 50e-6 and angle < 1e-3, (i, distance, angle)
        assert run_file.header.metadata["operator"] == "test"
        # The sources are in view: the brightest frames carry real signal.
        assert max(int(run_file.frames(i).max()) for i in (20, 33, 45)) > 1000


def test_sigkill_during_a_run_then_resume(tmp_path, daemon_factory):
    config = write_config(tmp_path / "daemon.toml", tmp_path / "data")
    port = free_port()
    first = daemon_factory(config, port=port)
    with first.client() as http:
        run = http.post("/runs", json={"count": 30, "bracket": {"mode": "fixed", "exposures_s": EXPOSURES}}).json()
        # Kill at a random moment once some positions are in (seeded, so a failure reproduces).
        wait_for(http, run["id"], set(), done_at_least=5, timeout=120)
        time.sleep(random.Random(7).uniform(0.0, 1.5))
    first.kill()
    with RunFile.open(tmp_path / "data" / "runs" / f"{run['id']}.h5") as crashed:
        before = crashed.completed_positions()
        kept = {int(i): crashed.frames(int(i)).copy() for i in before}
    assert len(before) >= 5

    second = daemon_factory(config, port=port)
    with second.client() as http:
        status = http.get(f"/runs/{run['id']}").json()
        assert status["state"] == "interrupted"
        resumed = http.post(f"/runs/{run['id']}/resume")
        assert resumed.status_code == 200, resumed.text
        final = wait_for(http, run["id"], {"complete", "failed"}, timeout=300)
        assert final["state"] == "complete", final
    with RunFile.open(tmp_path / "data" / "runs" / f"{run['id']}.h5") as done:
        assert done.complete.all()
        for i, frames in kept.items():  # what was taken before the kill is untouched
            np.testing.assert_array_equal(done.frames(i), frames)


def test_alarm_at_position_10_fails_the_run_keeps_the_data_and_resume_completes(tmp_path, daemon_factory):
    arm_port = free_port()
    daemon = daemon_factory(write_config(tmp_path / "daemon.toml", tmp_path / "data", arm_port=arm_port))
    # Inject the fault over Modbus, as another program would: the stage's 11th move fails.
    with ModbusTcpClient("127.0.0.1", port=arm_port) as modbus:
        assert not modbus.write_registers(900, [11, 0x0410], device_id=1).isError()
    with daemon.client() as http:
        run = http.post("/runs", json={"count": 16, "bracket": {"mode": "fixed", "exposures_s": EXPOSURES}}).json()
        failed = wait_for(http, run["id"], {"failed", "complete"}, timeout=120)
        assert failed["state"] == "failed"
        assert "alarm 0x0410" in failed["last_error"] and "overload" in failed["last_error"]
        assert http.get("/health").json()["status"] == "degraded"
        path = tmp_path / "data" / "runs" / f"{run['id']}.h5"
        with RunFile.open(path) as run_file:
            assert run_file.completed_positions().tolist() == list(range(10))
            assert run_file.status == "failed"
        resumed = http.post(f"/runs/{run['id']}/resume")
        assert resumed.status_code == 200, resumed.text
        final = wait_for(http, run["id"], {"complete", "failed"}, timeout=120)
        assert final["state"] == "complete", final["last_error"]
        assert http.get("/health").json()["status"] == "ok"
    with RunFile.open(path) as run_file:
        assert run_file.complete.all() and run_file.n_positions == 16


def test_token_is_required_off_loopback_and_checked(tmp_path, daemon_factory):
    daemon = daemon_factory(write_config(tmp_path / "daemon.toml", tmp_path / "data"), token="s3cret-token-0123456789")
    import httpx

    with httpx.Client(base_url=daemon.url, headers={"Content-Type": "application/json"}) as anonymous:
        assert anonymous.get("/health").status_code == 200  # the health needs no token
        missing = anonymous.post("/runs", json={"count": 1})
        assert missing.status_code == 401
        assert missing.headers["www-authenticate"] == "Bearer"
        wrong = anonymous.post("/runs", json={"count": 1}, headers={"Authorization": "Bearer nope"})
        assert wrong.status_code == 403
        assert anonymous.post("/arm/stop").status_code == 401
    with daemon.client() as http:
        assert http.post("/runs", json={"count": 1}).status_code == 201


def test_serve_refuses_a_public_address_without_a_token(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    config = write_config(tmp_path / "daemon.toml", tmp_path / "data")
    exe = Path(sys.executable).with_name("mirrorgonio")
    env = {k: v for k, v in __import__("os").environ.items() if k != "MG_TOKEN"}
    result = subprocess.run(
        [str(exe), "serve", "--config", str(config), "--host", "0.0.0.0"],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
    )
    assert result.returncode == 2
    assert result.stderr.strip() == (
        "error: host: refusing to listen on 0.0.0.0 without a token (set token in the configuration or MG_TOKEN)"
    )


# --- the simulated arm in its own process (as in docker-compose.yml) --------------------------
def _start_sim_arm(tmp_path, port: int):
    """``mirrorgonio simulate arm`` as its own process; returns it once it accepts connections."""
    import socket
    import subprocess
    import sys
    from pathlib import Path

    exe = Path(sys.executable).with_name("mirrorgonio")
    log = open(tmp_path / "sim-arm.log", "ab")
    proc = subprocess.Popen(
        [str(exe), "simulate", "arm", "--host", "127.0.0.1", "--port", str(port), "--speed", "0.5", "--accel", "5"],
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        assert proc.poll() is None, (tmp_path / "sim-arm.log").read_text()
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1.0).close()
            return proc, log
        except OSError:
            time.sleep(0.1)
    proc.kill()
    raise AssertionError("the simulated arm did not start listening")


def _sweep_positions(indices):
    """Light poses of the reduced rig's sweep at ``indices``, as a ``poses`` run request."""
    from conftest import REDUCED_RIG

    from drivers.contracts.rig import load_rig

    light = load_rig(REDUCED_RIG).light_poses()
    return [
        {
            "position_m": list(map(float, light[i].position)),
            "rotation_deg": [math.degrees(a) for a in (light[i].rx, light[i].ry, light[i].rz)],
        }
        for i in indices
    ]


def _run_frames(daemon, request) -> tuple[list[np.ndarray], dict]:
    with daemon.client() as http:
        devices = http.get("/devices").json()
        started = http.post("/runs", json=request)
        assert started.status_code == 201, started.text
        final = wait_for(http, started.json()["id"], {"complete", "failed", "aborted"}, timeout=180)
        assert final["state"] == "complete", final
    path = daemon.config.parent / "data" / "runs" / f"{final['id']}.h5"
    with RunFile.open(path) as run_file:
        for i in range(run_file.n_positions):
            distance, angle = run_file.measured_pose(i).distance_to(run_file.header.tool_poses[i])
            assert distance < 50e-6 and angle < 1e-3, (i, distance, angle)
        return [run_file.frames(i).astype(float) for i in range(run_file.n_positions)], devices


def test_simulated_camera_follows_a_simulated_arm_in_another_process(tmp_path, daemon_factory):
    """The compose deployment's link: the daemon drives `mirrorgonio simulate arm` (another
    process) with the real Modbus driver, and the simulated camera photographs the light
    where that arm's controller says it is. Same frames as with the arm in-process."""
    from conftest import REDUCED_RIG

    arm_port = free_port()
    sim_arm, sim_arm_log = _start_sim_arm(tmp_path, arm_port)
    try:
        remote_dir = tmp_path / "remote"
        remote_dir.mkdir()
        config = remote_dir / "daemon.toml"
        config.write_text(
            f'data_dir = "{remote_dir / "data"}"\nrig = "{REDUCED_RIG}"\n'
            f'[arm]\nkind = "modbus-tcp"\nprofile = "sim_stage"\nhost = "127.0.0.1"\nport = {arm_port}\n'
            '[camera]\nkind = "simulated"\n'
        )
        local_dir = tmp_path / "local"
        local_dir.mkdir()
        request = {
            "preset": "poses",
            "poses": _sweep_positions([20, 33, 45]),
            "bracket": {"mode": "fixed", "exposures_s": [0.001, 0.005]},
        }

        remote = daemon_factory(config)
        remote_frames, devices = _run_frames(remote, request)
        assert devices["arm"]["identity"].endswith(f"@ tcp://127.0.0.1:{arm_port})"), devices
        remote.stop()
        local = daemon_factory(write_config(local_dir / "daemon.toml", local_dir / "data"))
        local_frames, _ = _run_frames(local, request)
    finally:
        sim_arm.terminate()
        sim_arm.wait(20)
        sim_arm_log.close()
    assert sim_arm.returncode == 0, (tmp_path / "sim-arm.log").read_text()  # SIGTERM ends it cleanly

    def similarity(a, b):
        return float(np.corrcoef(a.ravel(), b.ravel())[0, 1])

    n = len(remote_frames)
    assert n == 3
    for i in range(n):
        # The light is lit where the arm is: the longest exposure shows the sources.
        assert remote_frames[i][-1].max() > 1000
        # The same picture as with the simulated arm in the daemon's own process (the
        # pose differs only by the read-back noise, so the frames nearly coincide)...
        assert similarity(remote_frames[i][-1], local_frames[i][-1]) > 0.95, i
        # ...and a different one at every other position.
        for j in range(n):
            if j != i:
                assert similarity(remote_frames[i][-1], remote_frames[j][-1]) < 0.5, (i, j)
