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
    result = runner.invoke(
        app, ["simulate", "capture", "--rig", str(small_rig), "--position", "33", "--exposure", "0.003", "-o", str(out)]
    )
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


def test_every_subcommand_has_help():
    for args in (
        ["--help"],
        ["simulate", "--help"],
        ["simulate", "arm", "--help"],
        ["simulate", "capture", "--help"],
        ["bench", "render", "--help"],
        ["demo", "--help"],
        ["import", "--help"],
        ["process", "--help"],
        ["reflectance", "--help"],
        ["worker", "--help"],
        ["bench", "reflectance", "--help"],
        ["bench", "speed", "--help"],
    ):
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
    proc = subprocess.Popen(
        [str(exe), "simulate", "arm", "--port", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
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


# --- process: several runs in one call ---------------------------------------------------------
def _small_run(path: Path, run_id: str, positions=(3, 4), seed: int = 0) -> Path:
    """A run file of a tiny synthetic sensor: a linear scene bracketed at three exposures."""
    import numpy as np

    from drivers.camera import RawFrame
    from drivers.contracts.rig import rig_from_dict
    from drivers.contracts.runfile import PositionTimes, RunFileWriter, RunHeader

    rig = rig_from_dict({"camera": {"width": 64, "height": 48}})
    exposures = [0.001, 0.004, 0.016]
    header = RunHeader(
        run_id=run_id,
        rig=rig,
        tool_poses=rig.tool_poses(),
        light_poses=rig.light_poses(),
        max_exposures=len(exposures),
        frame_shape=(48, 64),
        bracket={"mode": "fixed", "exposures_s": exposures},
        metadata={},
        devices={},
        software_version="test",
        created_utc="2026-01-01T00:00:00+00:00",
    )
    rng = np.random.default_rng(seed)
    rate = np.outer(np.linspace(1e4, 2e5, 48), np.linspace(0.5, 1.5, 64))  # DN/s
    path.parent.mkdir(parents=True, exist_ok=True)
    with RunFileWriter.create(path, header) as writer:
        for index in positions:
            frames = [
                RawFrame(
                    mosaic=np.clip(64 + rng.poisson(rate * t), 0, 4095).astype(np.uint16),
                    black_level=np.full((2, 2), 64.0),
                    white_level=4095,
                    cfa_pattern="RGGB",
                    exposure_s=t,
                    timestamp=1.0e9,
                    camera_id="test",
                )
                for t in exposures
            ]
            writer.write_position(index, rig.tool_poses()[index], PositionTimes(1.0e9, 1.0e9, 1.0e9), frames)
        writer.set_status("complete")
    return path


def test_process_several_runs_with_the_same_name_and_one_broken(tmp_path):
    first = _small_run(tmp_path / "day1" / "run-0001.h5", "run-0001", seed=1)
    second = _small_run(tmp_path / "day2" / "run-0001.h5", "run-0001b", positions=(7,), seed=2)
    third = _small_run(tmp_path / "day2" / "other.h5", "other", seed=3)
    broken = tmp_path / "day2" / "broken.h5"
    broken.write_text("not a run file")
    out = tmp_path / "results"
    result = runner.invoke(
        app,
        [
            "process",
            str(first),
            str(broken),
            str(second),
            str(third),
            "--steps",
            "hdr",
            "--noise",
            "rig",
            "--method",
            "poisson",
            "--out",
            str(out),
        ],
    )
    assert result.exit_code == 2, result.output
    # the others still complete, each in its own place: same-named runs in a subfolder each
    from processing.results import Results

    for results_file, done in (
        (out / "day1" / "run-0001.results.h5", [3, 4]),
        (out / "day2" / "run-0001.results.h5", [7]),
        (out / "other.results.h5", [3, 4]),
    ):
        with Results.open(results_file) as results:
            assert results.hdr_done.nonzero()[0].tolist() == done
            assert results.noise.source == "rig"
    assert (out / "day1" / "run-0001.hdr" / "position-003.exr").exists()
    assert (out / "day2" / "run-0001.hdr" / "position-007.exr").exists()
    lines = result.output.strip().splitlines()
    assert "processed runs" in result.output and "3 of 4 runs processed, 1 failed" in result.output
    errors = [line for line in lines if line.startswith("error:")]
    assert len(errors) == 1 and str(broken) in errors[0] and "not an HDF5 file" in errors[0]
    assert lines[-1] == errors[0]  # the failure is the last thing said
    for name in ("run-0001.h5", "other.h5", "broken.h5"):
        assert name in result.output


def test_process_several_runs_all_good_exits_zero(tmp_path):
    runs = [_small_run(tmp_path / f"run-{k}.h5", f"run-{k}", positions=(k,), seed=k) for k in (1, 2)]
    again = tmp_path / "." / "run-1.h5"  # the same file twice: processed once
    result = runner.invoke(
        app, ["process", *map(str, runs), str(again), "--steps", "hdr", "--out", str(tmp_path / "out")]
    )
    assert result.exit_code == 0, result.output
    assert "processed once" in result.output
    assert "2 of 2 runs processed" in result.output and "failed" not in result.output
    assert (tmp_path / "out" / "run-1.results.h5").exists() and (tmp_path / "out" / "run-2.results.h5").exists()


def test_process_bad_option_fails_before_any_run(tmp_path):
    run = _small_run(tmp_path / "run.h5", "run")
    result = runner.invoke(
        app, ["process", str(run), str(run.with_name("x.h5")), "--steps", "hdr,dance", "--out", str(tmp_path / "out")]
    )
    assert result.exit_code == 2
    assert result.output.strip().splitlines() == [
        "error: --steps: unknown step 'dance' (known: hdr, sources; trace and fit are part of sources)"
    ]
    assert not (tmp_path / "out").exists()


def test_output_folders_for_same_named_runs(tmp_path):
    from acquisition.cli.process import _output_folders

    a, b, c = tmp_path / "a" / "x" / "run.h5", tmp_path / "b" / "x" / "run.h5", tmp_path / "c" / "other.h5"
    folders = _output_folders([a, b, c], tmp_path / "out")
    assert folders[c] == tmp_path / "out"
    assert folders[a] != folders[b]
    assert folders[a].parent == folders[b].parent == tmp_path / "out"
    assert folders[a].name.startswith("x-") and folders[b].name.startswith("x-")
    assert _output_folders([a, c], None) == {a: None, c: None}


def _command_line(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """The program as a user starts it (its console entry), in a fresh process."""
    wide = {**os.environ, "COLUMNS": "200"}  # the help's tables unwrapped
    return subprocess.run(
        [sys.executable, "-m", "acquisition.cli", *args], cwd=cwd, capture_output=True, text=True, timeout=60, env=wide
    )


def _console_entry(capsys, *args: str) -> tuple[int, str, str]:
    """:func:`acquisition.cli.main`, the console entry, run here: (exit status, stdout, stderr)."""
    from acquisition.cli import main

    with pytest.raises(SystemExit) as ended:
        main(list(args))
    out = capsys.readouterr()
    return ended.value.code, out.out, out.err


def test_process_refuses_a_bad_method_in_one_line_at_once(tmp_path):
    """``mirrorgonio process RUN.h5 --method bogus`` as a user runs it: exit status 2, one line
    on standard error naming the option, within seconds (no cluster started), nothing written."""
    run = _small_run(tmp_path / "run.h5", "run")
    before = sorted(tmp_path.iterdir())
    started = time.perf_counter()
    result = _command_line("process", str(run), "--method", "bogus", cwd=tmp_path)
    seconds = time.perf_counter() - started
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip().splitlines() == [
        "error: process: Invalid value for '--method': 'bogus' is not one of 'optimal', 'poisson'."
    ]
    assert result.stdout == "" and seconds < 5.0
    assert sorted(tmp_path.iterdir()) == before  # no results file, no .hdr folder


@pytest.mark.parametrize(
    ("option", "value", "said"),
    [
        ("--fit", "gauss", "Invalid value for '--fit': 'gauss' is not one of 'gaussian', 'polynomial',"),
        ("--noise", "guess", "Invalid value for '--noise': 'guess' is not one of 'auto', 'estimated', 'rig'."),
        ("--estimator", "sums", "Invalid value for '--estimator': 'sums' is not one of 'auto', 'templates',"),
        ("--steps", "hdr,dance", "--steps: unknown step 'dance'"),
        ("--ball-centre", "1,2", "--ball-centre: expected X,Y,Z in metres, got '1,2'"),
        ("--extrapolation", "zero", "Invalid value for '--extrapolation': 'zero' is not one of 'fitted', 'none'."),
        ("--scheduler", "my-cluster", "--scheduler: 'my-cluster' is not 'local', 'none', 'synchronous'"),
    ],
)
def test_process_refuses_a_bad_option_in_one_line_before_any_work(tmp_path, capsys, option, value, said):
    run = _small_run(tmp_path / "run.h5", "run")
    before = sorted(tmp_path.iterdir())
    code, out, err = _console_entry(capsys, "process", str(run), "--out", str(tmp_path / "out"), option, value)
    assert code == 2 and out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and said in lines[0], err
    assert sorted(tmp_path.iterdir()) == before


def test_the_program_says_its_version_and_takes_h_for_help(tmp_path, capsys, monkeypatch):
    from drivers.contracts.version import __version__

    monkeypatch.setenv("COLUMNS", "200")  # the help's tables unwrapped
    assert _console_entry(capsys, "--version") == (0, f"mirrorgonio {__version__}\n", "")
    for args in (["-h"], ["process", "-h"], ["bench", "speed", "-h"]):
        code, out, _ = _console_entry(capsys, *args)
        assert code == 0 and "Usage: mirrorgonio" in out, args
    assert "<optimal|poisson>" in _console_entry(capsys, "process", "-h")[1]
