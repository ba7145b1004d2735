"""The command line: real invocations, their outputs and their one-line errors."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from acquisition.cli import app
from drivers.raw_decode import decode_raw

ROOT = Path(__file__).resolve().parent.parent
runner = CliRunner()

SMALL_RIG = """
[camera]
width = 320
height = 320
principal_point_px = [159.5, 255.5]
[simulation]
truth = "five-gaussians"
"""


@pytest.fixture()
def small_rig(tmp_path):
    path = tmp_path / "small.toml"
    path.write_text(SMALL_RIG)
    return path


def test_simulate_capture_writes_a_dng_that_decodes(tmp_path, small_rig):
    out = tmp_path / "frame.dng"
    result = runner.invoke(app, ["simulate", "capture", "--rig", str(small_rig), "--position", "33",
                                 "--exposure", "0.003", "-o", str(out)])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert f"wrote {out}" in result.output
    frame = decode_raw(out)
    assert frame.mosaic.shape == (320, 320)
    assert frame.exposure_s == pytest.approx(0.003)
    assert frame.mosaic.max() > 500  # the five sources are in view at position 33


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--position", "66"], "error: --position: 66 is outside the schedule (0..65)"),
        (["--exposure", "-1"], "error: --exposure: must be a positive number of seconds, got -1.0"),
        (["--truth", "nonesuch"], "error: nonesuch: no such truth light"),
    ],
)
def test_simulate_capture_bad_input_is_one_line(tmp_path, small_rig, args, message):
    result = runner.invoke(app, ["simulate", "capture", "--rig", str(small_rig), "-o", str(tmp_path / "x.dng"), *args])
    assert result.exit_code == 2
    assert result.output.strip().startswith(message), result.output
    assert len(result.output.strip().splitlines()) == 1
    assert not (tmp_path / "x.dng").exists()


def test_bad_rig_file_is_named(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[ball]\nradius_m = -0.01\n")
    result = runner.invoke(app, ["simulate", "capture", "--rig", str(bad), "-o", str(tmp_path / "x.dng")])
    assert result.exit_code == 2
    assert result.output.strip().splitlines() == [f"error: {bad}: ball.radius_m: must be > 0 (got -0.01)"]


def test_bench_render_prints_json(small_rig):
    result = runner.invoke(app, ["bench", "render", "--rig", str(small_rig), "--repeat", "1", "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.output)
    assert data["benchmark"] == "render"
    assert (data["width"], data["height"]) == (320, 320)
    assert data["render_s_median"] > 0
    assert data["rays_traced_per_frame"] > 100_000


def test_demo_renders_and_decodes(tmp_path, small_rig):
    result = runner.invoke(app, ["demo", "--out", str(tmp_path / "demo"), "--rig", str(small_rig)])
    assert result.exit_code == 0, result.output
    written = tmp_path / "demo" / "capture-position-33.dng"
    assert str(written.resolve()) in result.output
    assert decode_raw(written).exposure_s == pytest.approx(0.001)


def test_every_subcommand_has_help():
    for args in (["--help"], ["simulate", "--help"], ["simulate", "arm", "--help"],
                 ["simulate", "capture", "--help"], ["bench", "render", "--help"], ["demo", "--help"]):  # fmt: skip
        result = runner.invoke(app, args)
        assert result.exit_code == 0, args
        assert "Usage" in result.output


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_simulate_arm_serves_modbus_to_the_real_driver():
    from drivers.modbus_arm import ModbusArm
    from drivers.modbus_profile import SIM_STAGE_PROFILE
    from drivers.pose import Pose

    port = _free_port()
    exe = Path(sys.executable).with_name("mirrorgonio")
    proc = subprocess.Popen([str(exe), "simulate", "arm", "--port", str(port)], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})  # fmt: skip
    try:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
                break
            except OSError:
                time.sleep(0.1)
        with ModbusArm(SIM_STAGE_PROFILE, host="127.0.0.1", port=port) as arm:
            target = Pose(0.01, 0.04, 0.10, 2.76, 0.0, 0.0)
            reached = arm.move_to(target, timeout=30)
            assert reached.distance_to(target)[0] < 50e-6
    finally:
        proc.terminate()
        proc.wait(timeout=10)
