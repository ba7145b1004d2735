"""Benchmarks of the acquisition software: what the daemon adds to the hardware's time."""

from __future__ import annotations

import contextlib
import math
import statistics
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import h5py
import hdf5plugin

from acquisition.daemon.catalog import Catalog, RunRecord
from acquisition.daemon.devices import Devices
from acquisition.daemon.engine import RunEngine
from acquisition.daemon.models import FixedBracket, RunRequest
from acquisition.daemon.settings import DaemonSettings, load_settings
from drivers.camera import RawFrame
from drivers.contracts.rig import Rig, load_rig
from drivers.modbus_arm import ModbusArm
from drivers.modbus_profile import SIM_STAGE_PROFILE
from sim_devices.camera import SimulatedCamera
from sim_devices.modbus_server import SimulatedModbusArm
from sim_devices.replay_camera import ReplayCamera
from sim_devices.stage import SimulatedStage, StageConfig
from sim_devices.world import SimWorld


def _frames(rig: Rig, count: int, seed: int = 0) -> list[RawFrame]:
    """Realistic raw frames: rendered mirror-ball images with sensor noise."""
    poses = rig.tool_poses()
    state = {"pose": poses[len(poses) // 2]}
    with tempfile.TemporaryDirectory() as spool:
        camera = SimulatedCamera(rig, SimWorld(lambda: state["pose"]), spool, seed=seed)
        frames = []
        for k in range(count):
            state["pose"] = poses[(len(poses) // 2 + 7 * k) % len(poses)]
            frames.append(camera.capture([0.0002, 0.001, 0.005][k % 3]))
    return frames


def plain_h5py_write(path: Path, frames: list[RawFrame], positions: int, exposures: int) -> float:
    """The same frames into one dataset with the same chunks and filter: the peer; its seconds.

    Parameters
    ----------
    path : Path
        The HDF5 file written (replaced).
    frames : list
        Frames (``.mosaic``, uint16) cycled over the ``positions`` x ``exposures`` slots.
    positions, exposures : int
        The dataset's first two dimensions, as a run file's.

    Returns
    -------
    float
        Seconds from opening the file to closing it.
    """
    h, w = frames[0].mosaic.shape
    start = time.perf_counter()
    with h5py.File(path, "w") as f:
        raw = f.create_dataset("raw", (positions, exposures, h, w), dtype="u2", chunks=(1, 1, h, w), **hdf5plugin.LZ4())
        k = 0
        for i in range(positions):
            for e in range(exposures):
                raw[i, e] = frames[k % len(frames)].mosaic
                k += 1
    return time.perf_counter() - start


def run_file_of(record: RunRecord) -> Path:
    """The run file of a run that completed (RuntimeError where the catalog has none)."""
    if record.path is None:
        raise RuntimeError(f"run {record.id} has no run file in the catalog")
    return Path(record.path)


@contextlib.contextmanager
def zero_latency_arm(rig: Rig) -> Iterator[ModbusArm]:
    """The simulated stage at infinite speed behind a real Modbus TCP server on loopback, and
    the Modbus driver connected to it: the arm whose own time is (nearly) nothing."""
    stage = SimulatedStage(
        StageConfig(
            speed_m_s=math.inf,
            accel_m_s2=math.inf,
            angular_speed_rad_s=math.inf,
            angular_accel_rad_s2=math.inf,
            readback_noise_m=0.0,
            readback_noise_rad=0.0,
        )
    )
    with SimulatedModbusArm(stage) as server:
        arm = ModbusArm(SIM_STAGE_PROFILE, port=server.port, limits=rig.soft_limits(), poll_interval_s=0.0)
        arm.connect()
        try:
            yield arm
        finally:
            arm.close()


def timed_engine_run(
    settings: DaemonSettings, rig: Rig, devices: Devices, request: RunRequest
) -> tuple[float, RunRecord]:
    """One run of ``request`` through the daemon's run engine in ``settings.data_dir``:
    (seconds from start to the run's end, the run's catalog record). RuntimeError when the
    run does not complete."""
    settings.data_dir.mkdir(parents=True)
    catalog = Catalog(settings.catalog_url, rig=settings.rig_name)
    try:
        engine = RunEngine(settings, rig, devices, catalog)
        start = time.perf_counter()
        record = engine.start_run(request)
        engine.wait()
        seconds = time.perf_counter() - start
        state = catalog.get_run(record.id)
    finally:
        catalog.close()
    if state.state != "complete":
        raise RuntimeError(f"benchmark run ended {state.state}: {state.last_error}")
    return seconds, state


def bench_acquire(
    rig_path: str | Path | None = None,
    positions: int = 20,
    exposures: int = 3,
    repeat: int = 3,
    distinct_frames: int = 6,
) -> dict:
    """Run the real engine on zero-latency devices and compare with a plain h5py write."""
    rig = load_rig(rig_path)
    frames = _frames(rig, distinct_frames)
    frame_bytes = frames[0].mosaic.nbytes
    total_frames = positions * exposures
    engine_times, plain_times = [], []
    request = RunRequest(count=positions, bracket=FixedBracket(exposures_s=[0.0002 * 4**k for k in range(exposures)]))
    with tempfile.TemporaryDirectory() as tmp_dir, zero_latency_arm(rig) as arm:
        tmp = Path(tmp_dir)
        for r in range(repeat):
            settings = load_settings(None, data_dir=tmp / f"engine-{r}", rig=rig_path or None)
            seconds, _ = timed_engine_run(settings, rig, Devices(arm=arm, camera=ReplayCamera(frames)), request)
            engine_times.append(seconds)
            plain_times.append(plain_h5py_write(tmp / f"plain-{r}.h5", frames, positions, exposures))
    engine_s, plain_s = statistics.median(engine_times), statistics.median(plain_times)
    megabytes = total_frames * frame_bytes / 1e6
    return {
        "benchmark": "acquire",
        "frame_shape": list(frames[0].mosaic.shape),
        "positions": positions,
        "exposures_per_position": exposures,
        "repeat": repeat,
        "engine_s_median": round(engine_s, 3),
        "engine_frames_per_s": round(total_frames / engine_s, 2),
        "engine_mb_per_s": round(megabytes / engine_s, 1),
        "plain_h5py_s_median": round(plain_s, 3),
        "plain_h5py_mb_per_s": round(megabytes / plain_s, 1),
        "engine_over_plain_throughput": round(plain_s / engine_s, 3),
        "target_ratio": 0.7,
        "meets_target": plain_s / engine_s >= 0.7,
        "engine_s_all": [round(t, 3) for t in engine_times],
        "plain_s_all": [round(t, 3) for t in plain_times],
    }
