"""The daemon as a lab uses it: a real process, driven over HTTP only, with the simulated
devices over Modbus TCP on loopback. Run files are checked through the run-file module."""

from __future__ import annotations

import math
import random
import time

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient

from acquisition.runfile import RunFile
from conftest import free_port, wait_for, write_config

EXPOSURES = [0.0002, 0.001, 0.005]


def test_full_default_sweep_over_http(tmp_path, daemon_factory):
    daemon = daemon_factory(write_config(tmp_path / "daemon.toml", tmp_path / "data"))
    with daemon.client() as http:
        assert http.get("/health").json()["status"] == "ok"
        started = http.post("/runs", json={"preset": "light-sweep", "operator": "test",
                                           "bracket": {"mode": "fixed", "exposures_s": EXPOSURES}})  # fmt: skip
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
    daemon = daemon_factory(write_config(tmp_path / "daemon.toml", tmp_path / "data"), token="s3cret")
    import httpx

    with httpx.Client(base_url=daemon.url) as anonymous:
        assert anonymous.get("/health").status_code == 200  # reading needs no token
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
    result = subprocess.run([str(exe), "serve", "--config", str(config), "--host", "0.0.0.0"],
                            capture_output=True, text=True, timeout=60, env=env)  # fmt: skip
    assert result.returncode == 2
    assert result.stderr.strip() == ("error: host: refusing to listen on 0.0.0.0 without a token "
                                     "(set token in the configuration or MG_TOKEN)")  # fmt: skip
