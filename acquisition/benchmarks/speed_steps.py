"""``bench speed``'s measurements of single steps: the chief rays, the HDR merge next to its
peers, and what the daemon adds to each frame it acquires.

``trace``
    ``processing.trace.trace_pixels``: the chief ray of every photosite of the frame to the
    light plane, at the middle position; rays per second.
``hdr``
    ``processing.hdr.brackets.merge_raw`` (the rig's noise model, as ``process`` runs it: one process,
    numba's threads) on the run's own brackets, next to HDRutils' merge and colour-hdri's
    ``image_stack_to_HDRI`` on the same brackets (:mod:`acquisition.benchmarks.hdr_methods`
    prepares their inputs: not timed); a few positions spread over the sweep.
``acquire``
    The daemon's run engine taking a full run with zero-latency devices (the simulated arm
    with infinite speed, a camera that hands back the run's own frames): the time per frame,
    next to the camera's capture calls alone and to a plain h5py write of the same frames
    with the same chunks and filter. The difference with the camera alone is the daemon's
    overhead per frame.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numba
import numpy as np

from acquisition.benchmarks.acquire import plain_h5py_write, run_file_of, timed_engine_run, zero_latency_arm
from acquisition.benchmarks.hdr_methods import (
    UNRESOLVED_MERGE_ONLY,
    MergeContext,
    MergeMethod,
    Sensor,
    colour_hdri_method,
    hdrutils_method,
    merge_only_s,
    ours_method,
    significant,
)
from acquisition.benchmarks.speed_runs import SpeedBenchError
from acquisition.daemon.devices import Devices
from acquisition.daemon.models import FixedBracket, RunRequest
from acquisition.daemon.settings import load_settings
from drivers.camera import Camera, RawFrame
from drivers.contracts.runfile import RunFile
from processing.trace import RigGeometry, light_pose_at, trace_pixels
from sim_devices.replay_camera import ReplayCamera

#: How ``measure_hdr`` measures, as its JSON says.
HDR_HOW = (
    "the run's own brackets read from the run file (untimed); per method one untimed call on the first "
    "bracket, then every bracket merged `repeat` times; ms_per_position is the median over repeats of "
    "the total over the positions, divided by their number. mirrorgonio: processing.hdr.brackets.merge_raw "
    "(method optimal, the rig's noise model; numba, this process's threads). HDRutils: its merge only "
    "(the bilinear demosaic its call always runs is timed apart and subtracted, in its favour); "
    "colour-hdri: image_stack_to_HDRI. The peers' inputs are prepared untimed as in `bench hdr` "
    "(acquisition/benchmarks/hdr.py); errors against the truth are `bench hdr`'s subject, not this one's"
)


# --- chief rays -----------------------------------------------------------------------------------
def measure_trace(run_path: Path, repeat: int, block_pixels: int = 1 << 20) -> dict:
    """The chief ray of every photosite of the frame traced to the light plane at the middle
    position, in blocks of about ``block_pixels`` rays; rays per second (median over ``repeat``)."""
    with RunFile.open(run_path) as run:
        rig = run.header.rig
        middle = run.n_positions // 2
        measured = run.measured_pose(middle) if run.complete[middle] else None
        tool = measured if measured is not None else run.header.tool_poses[middle]
    geometry = RigGeometry.from_rig(rig)
    light = light_pose_at(geometry, tool)
    width, height = rig.camera.width, rig.camera.height
    rows_per_block = max(1, block_pixels // width)
    col_row = np.arange(width, dtype=float)
    first = min(height, rows_per_block)  # untimed: imports, the first touch of a block's memory
    trace_pixels(
        geometry,
        light,
        np.broadcast_to(col_row, (first, width)),
        np.broadcast_to(np.arange(first, dtype=float)[:, None], (first, width)),
    )
    times, hits, valid = [], 0, 0
    for _ in range(repeat):
        hits = valid = 0
        t0 = time.perf_counter()
        for r0 in range(0, height, rows_per_block):
            rows = np.arange(r0, min(height, r0 + rows_per_block), dtype=float)
            cols = np.broadcast_to(col_row, (rows.size, width))
            rays = trace_pixels(geometry, light, cols, np.broadcast_to(rows[:, None], (rows.size, width)))
            hits += int(np.count_nonzero(rays.hits_ball))
            valid += int(np.count_nonzero(rays.valid))
        times.append(time.perf_counter() - t0)
    trace_s = statistics.median(times)
    n = width * height
    return {
        "rays": n,
        "trace_s": round(trace_s, 4),
        "trace_s_all": [round(t, 4) for t in times],
        "rays_per_s": round(n / trace_s),
        "rays_hitting_ball": hits,
        "rays_reaching_light_plane": valid,
        "position": middle,
        "how": f"processing.trace.trace_pixels: the chief ray of every photosite of the frame (ball or not) to the "
        f"light plane at the middle position, in blocks of {rows_per_block} rows (~{rows_per_block * width} "
        "rays, memory bounded), one process (numpy); one untimed block first; median over repeats",
    }


# --- HDR merge next to its peers, on the run's own brackets ----------------------------------------
def measure_hdr(run_path: Path, positions: int, repeat: int, peers: bool = True) -> dict:
    """This project's HDR merge on ``positions`` of the run's own brackets (spread over the
    sweep), next to HDRutils' and colour-hdri's merges (``peers``); per position, the median
    over ``repeat`` of the total."""
    with RunFile.open(run_path) as run:
        picks, exposures, ctx = _brackets_to_merge(run, run_path, positions)
        methods: dict[str, MergeMethod | str] = {"mirrorgonio": ours_method(ctx, "optimal")}
        if peers:
            methods["hdrutils"] = hdrutils_method(ctx)
            methods["colour_hdri"] = colour_hdri_method(ctx)
        else:
            methods.update(hdrutils="skipped (--no-peers)", colour_hdri="skipped (--no-peers)")
        usable = {name: m for name, m in methods.items() if isinstance(m, MergeMethod)}
        times, excluded, failed = _time_merges(run, run_path, picks, exposures, usable, repeat)
    out_methods = _hdr_entries(methods, times, excluded, failed, len(picks))
    ours = out_methods["mirrorgonio"]["ms_per_position"]
    speedups = {
        name: (significant(e["ms_per_position"] / ours) if e.get("ms_per_position") is not None else None)
        for name, e in out_methods.items()
        if name != "mirrorgonio"
    }
    return {
        "positions_merged": picks,
        "exposures_s": [float(f"{t:.6g}") for t in exposures],
        "methods": out_methods,
        "speedup_vs": speedups,
        "numba_threads": numba.get_num_threads(),
        "how": HDR_HOW,
    }


def _brackets_to_merge(run: RunFile, run_path: Path, positions: int) -> tuple[list[int], np.ndarray, MergeContext]:
    """The positions to merge (spread over the run's complete ones), their exposures, and the
    context the merges are built for (the rig's sensor, the run's levels)."""
    cam = run.header.rig.camera
    done = run.completed_positions()
    picks = sorted({int(done[int(k)]) for k in np.linspace(0, done.size - 1, min(positions, done.size)).round()})
    first = picks[0]
    exposures = np.asarray(run.exposures(first), float)
    black = run.black_level(first)[0]
    white = int(run.white_level(first)[0])
    cfa = run.cfa_pattern(first)[0]
    height, width = run.frame_shape
    if not np.allclose(black, black.flat[0]):
        raise SpeedBenchError(f"{run_path}: the peers take one black level, this run has one per CFA site")
    sensor = Sensor(cfa, int(black.flat[0]), white, cam.gain_e_per_dn, cam.read_noise_e / cam.gain_e_per_dn, None)
    return picks, exposures, MergeContext(sensor, exposures, height, width)


def _time_merges(
    run: RunFile, run_path: Path, picks: list[int], exposures: np.ndarray, usable: dict[str, MergeMethod], repeat: int
) -> tuple[dict[str, list[float]], dict[str, list[float]], dict[str, str]]:
    """Every method on every picked bracket, ``repeat`` times: per method the summed seconds
    per repeat, those of its part timed apart, and why it failed (a peer's failure is a result)."""
    times = {name: [0.0] * repeat for name in usable}
    excluded = {name: [0.0] * repeat for name in usable}
    failed: dict[str, str] = {}
    for p, index in enumerate(picks):
        frames = run.frames(index)
        if not np.allclose(run.exposures(index), exposures):
            raise SpeedBenchError(f"{run_path}: position {index} has other exposures than position {picks[0]}")
        for name, m in usable.items():
            if name in failed:
                continue
            try:
                if p == 0:  # untimed: numba's JIT, the peers' lazy imports
                    m.run(m.prepare(frames))
                    if m.excluded:
                        m.excluded(None)
                for r in range(repeat):
                    prepared = m.prepare(frames)
                    t0 = time.perf_counter()
                    m.run(prepared)
                    times[name][r] += time.perf_counter() - t0
                    if m.excluded:
                        t0 = time.perf_counter()
                        m.excluded(prepared)
                        excluded[name][r] += time.perf_counter() - t0
                    del prepared
            except Exception as exc:  # noqa: BLE001 - a peer failing is a result; ours is not
                if name == "mirrorgonio":
                    raise
                failed[name] = f"failed at position {index}: {type(exc).__name__}: {exc}"
        del frames
    return times, excluded, failed


def _hdr_entries(methods: dict, times: dict, excluded: dict, failed: dict, n: int) -> dict[str, dict]:
    """Each method's entry: why it did not run or failed, or its milliseconds per position."""
    out_methods: dict[str, dict] = {}
    for name, m in methods.items():
        if isinstance(m, str):
            out_methods[name] = {"status": m, "ms_per_position": None}
            continue
        if name in failed:
            out_methods[name] = {"status": failed[name], "ms_per_position": None, "version": m.version}
            continue
        # Per repeat: the method's own time (HDRutils: its call minus the demosaic timed apart);
        # the whole call where that difference is not positive (a busy host), and the entry says so.
        own = [merge_only_s(t, x) for t, x in zip(times[name], excluded[name], strict=True)]
        resolved = all(t is not None for t in own)
        own_s = [t for t in own if t is not None] if resolved else times[name]
        entry = {
            "status": "ok",
            "ms_per_position": significant(1000 * statistics.median(own_s) / n, 4),
            "ms_per_position_all": [significant(1000 * t / n, 4) for t in own_s],
            "version": m.version,
            "notes": m.notes,
        }
        if not resolved:
            entry["merge_only"] = UNRESOLVED_MERGE_ONLY
        if m.excluded:
            entry["ms_per_position_full_call"] = round(1000 * statistics.median(times[name]) / n, 2)
            entry["excluded_part"] = m.excluded_what
            entry["excluded_ms_per_position"] = round(1000 * statistics.median(excluded[name]) / n, 2)
        out_methods[name] = entry
    return out_methods


# --- acquisition overhead -------------------------------------------------------------------------
class _TimedCamera(Camera):
    """Wraps a camera and adds up the time its capture calls take (all else is the camera's)."""

    def __init__(self, camera: Camera) -> None:
        self.camera = camera
        self.name = camera.name
        self.capture_s = 0.0
        self.calls = 0

    def capture(self, exposure_s: float) -> RawFrame:
        """The wrapped camera's capture, timed."""
        t0 = time.perf_counter()
        try:
            return self.camera.capture(exposure_s)
        finally:
            self.capture_s += time.perf_counter() - t0
            self.calls += 1

    @property
    def identity(self) -> str:
        return self.camera.identity

    def problem(self) -> str | None:
        return self.camera.problem()

    def connect(self) -> None:
        self.camera.connect()

    def close(self) -> None:
        self.camera.close()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.camera, name)


def measure_acquire(run_path: Path, repeat: int, distinct_positions: int = 4) -> dict:
    """The daemon's run engine taking the whole run with zero-latency devices (the camera hands
    back ``distinct_positions`` positions' frames of the run in turn), next to the camera's
    capture calls alone and a plain h5py write of the same frames (medians over ``repeat``)."""
    with RunFile.open(run_path) as run:
        rig = run.header.rig
        done = run.completed_positions()
        exposures = [float(t) for t in run.exposures(int(done[0]))]
        picks = sorted(
            {int(done[int(k)]) for k in np.linspace(0, done.size - 1, min(distinct_positions, done.size)).round()}
        )
        frames = [run.frame(i, k) for i in picks for k in range(len(exposures))]
        positions = int(done.size)
    total = positions * len(exposures)
    frame_bytes = frames[0].mosaic.nbytes
    engine_times, capture_times, plain_times, file_bytes = [], [], [], 0
    request = RunRequest(count=positions, bracket=FixedBracket(exposures_s=exposures))
    with tempfile.TemporaryDirectory(prefix="mirrorgonio-speed-acquire-") as tmp_dir, zero_latency_arm(rig) as arm:
        tmp = Path(tmp_dir)
        for r in range(repeat):
            settings = load_settings(None, data_dir=tmp / f"engine-{r}")
            camera = _TimedCamera(ReplayCamera(frames))
            seconds, state = timed_engine_run(settings, rig, Devices(arm=arm, camera=camera), request)
            engine_times.append(seconds)
            capture_times.append(camera.capture_s)
            run_file = run_file_of(state)
            file_bytes = run_file.stat().st_size
            run_file.unlink()
            plain = tmp / f"plain-{r}.h5"
            plain_times.append(plain_h5py_write(plain, frames, positions, len(exposures)))
            plain.unlink()
    engine_s, plain_s, capture_s = (statistics.median(t) for t in (engine_times, plain_times, capture_times))
    megabytes = total * frame_bytes / 1e6
    return {
        "positions": positions,
        "exposures_per_position": len(exposures),
        "frames": total,
        "engine_s": round(engine_s, 3),
        "engine_s_all": [round(t, 3) for t in engine_times],
        "engine_ms_per_frame": round(1000 * engine_s / total, 2),
        "camera_capture_ms_per_frame": round(1000 * capture_s / total, 4),
        "overhead_ms_per_frame": round(1000 * (engine_s - capture_s) / total, 2),
        "engine_mb_per_s": round(megabytes / engine_s, 1),
        "plain_h5py_ms_per_frame": round(1000 * plain_s / total, 2),
        "plain_h5py_mb_per_s": round(megabytes / plain_s, 1),
        "engine_over_plain_throughput": round(plain_s / engine_s, 3),
        "run_file_bytes": file_bytes,
        "how": "the daemon's run engine (acquisition.daemon.engine.RunEngine: catalog, run file, writer thread) "
        "takes a full run with the simulated arm at infinite speed over Modbus on loopback and a zero-latency "
        f"camera that hands back {len(frames)} frames of the cached run in turn (acquisition/benchmarks/acquire.py's "
        "set-up); camera_capture_ms_per_frame is the camera's capture calls alone, timed inside the run; "
        "overhead_ms_per_frame = (run time - capture time) / frames: what the daemon adds per frame (moves, "
        "checks, LZ4 compression and the HDF5 write, catalog updates). plain_h5py: the same frames written "
        "into one dataset with the same chunks and filter, as a floor",
    }
