"""``mirrorgonio bench speed``: how fast the whole chain is, at two sensor sizes, in one run.

The runs (:mod:`acquisition.benchmarks.speed_runs`)
    The simulated default rig (``rigs/default.toml``: five Gaussian sources, diffraction,
    photon and read noise) at 2000x1312 and at 4000x2624 photosites (the same field of
    view: 5.9 µm and 2.95 µm pixels), each a full light sweep of 66 positions x 5
    exposures taken by the daemon's run engine with the simulated devices: the arm over
    Modbus, the camera rendering each position once (it keeps the rendering of the pose it
    is at) and exposing, writing and decoding a DNG per frame. Each run is made once and
    cached, its creation time reported apart, from the cache's record.

The measurements (each at both sizes)
    ``read`` and ``process`` (:mod:`acquisition.benchmarks.speed_process`)
        The input-bound floor, every frame of the run read warm in one process; and
        ``processing.light_run.run.process_run`` of the whole run, as ``mirrorgonio process``
        does it by default (a local Dask cluster, one worker process per core; steps hdr
        and sources, an OpenEXR and a PNG per position, the light model, IES, LDT, TM-25
        and the report), the sources' layout given (the truth's, as ``bench accuracy``
        does), timed warm on a cluster that is up, with its peak memory
        (:mod:`acquisition.benchmarks.speed_resources`).
    ``trace``, ``hdr`` and ``acquire`` (:mod:`acquisition.benchmarks.speed_steps`)
        The chief rays per second; the HDR merge on the run's own brackets next to its
        peers; the daemon's overhead per frame with zero-latency devices.

Timings are medians over ``repeat`` where a repeat is cheap (acquire, hdr, trace, read);
the whole-run processing is timed ``process_repeat`` times (default 3) after its untimed
first. The machine's load (``os.getloadavg``) is recorded before and after each size. The
target and the markdown table: :mod:`acquisition.benchmarks.speed_report`.
"""

from __future__ import annotations

import os
import platform
import shutil
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import psutil

from acquisition.benchmarks.hdr import rig_at_size
from acquisition.benchmarks.speed_process import measure_process, measure_read
from acquisition.benchmarks.speed_report import judge_target, markdown_table
from acquisition.benchmarks.speed_runs import DEFAULT_CACHE, EXPOSURES_S, POSITIONS, SpeedBenchError, simulated_run
from acquisition.benchmarks.speed_steps import measure_acquire, measure_hdr, measure_trace
from drivers.contracts.rig import load_rig
from drivers.contracts.version import __version__

SIZES = ((2000, 1312), (4000, 2624))


def parse_size(text: str) -> tuple[int, int]:
    """``WIDTHxHEIGHT`` -> (width, height), both even and at least 16."""
    try:
        w, h = (int(v) for v in text.lower().replace("×", "x").split("x"))
    except ValueError:
        raise SpeedBenchError(f"--sizes: {text!r} is not WIDTHxHEIGHT (e.g. 2000x1312)") from None
    if w < 16 or h < 16 or w % 2 or h % 2:
        raise SpeedBenchError(f"--sizes: {text!r}: width and height must be even and at least 16 (a Bayer mosaic)")
    return w, h


def bench_speed(
    *,
    rig_path: str | Path | None = None,
    sizes: Sequence[tuple[int, int]] = SIZES,
    positions: int = POSITIONS,
    exposures: int = len(EXPOSURES_S),
    repeat: int = 3,
    process_repeat: int = 3,
    hdr_positions: int = 8,
    peers: bool = True,
    scheduler: str = "local",
    workers: int | None = None,
    cache: Path | None = DEFAULT_CACHE,
    log: Callable[[str], None] | None = None,
) -> dict:
    """Measure the chain at every size in ``sizes``; see the module's description."""
    _check_options(positions, exposures, repeat, process_repeat, hdr_positions)
    base = load_rig(rig_path)
    if positions > len(base.tool_poses()):
        raise SpeedBenchError(
            f"--positions: the rig's schedule has {len(base.tool_poses())} positions, not {positions}"
        )
    bracket = EXPOSURES_S[:exposures]
    started = time.perf_counter()
    say = log or (lambda _message: None)
    result: dict = {
        "benchmark": "speed",
        "rig": str(rig_path) if rig_path else "rigs/default.toml",
        "positions": positions,
        "exposures_s": list(bracket),
        "repeat": repeat,
        "process_repeat": process_repeat,
        "scheduler": scheduler,
        "cache": str(cache) if cache is not None else None,
        "load_avg_start": _load(),
        "machine": _machine(),
        "software_version": __version__,
        "sizes": {},
    }
    # The runs first (slow when not cached), then the measurements, size by size.
    runs = {}
    try:
        for width, height in sizes:
            rig = rig_at_size(base, width, height)
            runs[(width, height)] = (rig, simulated_run(rig, bracket, positions, cache, log=say))
        _measure(
            runs,
            result,
            repeat=repeat,
            process_repeat=process_repeat,
            hdr_positions=hdr_positions,
            peers=peers,
            scheduler=scheduler,
            workers=workers,
            say=say,
        )
    finally:
        for _rig, made in runs.values():
            if made.temporary is not None:
                shutil.rmtree(made.temporary, ignore_errors=True)
    result["load_avg_end"] = _load()
    result["target"] = judge_target(result)
    result["wall_s"] = round(time.perf_counter() - started, 1)
    result["markdown"] = markdown_table(result)
    return result


def _check_options(positions: int, exposures: int, repeat: int, process_repeat: int, hdr_positions: int) -> None:
    """Raise :class:`SpeedBenchError` naming the first option the benchmark cannot run with."""
    if not 1 <= exposures <= len(EXPOSURES_S):
        raise SpeedBenchError(f"--exposures: must be between 1 and {len(EXPOSURES_S)}, got {exposures}")
    if positions < 3:
        raise SpeedBenchError(f"--positions: must be at least 3 (the fits need samples), got {positions}")
    for name, value in (("repeat", repeat), ("process-repeat", process_repeat), ("hdr-positions", hdr_positions)):
        if value < 1:
            raise SpeedBenchError(f"--{name}: must be at least 1, got {value}")


def _measure(
    runs: dict,
    result: dict,
    *,
    repeat: int,
    process_repeat: int,
    hdr_positions: int,
    peers: bool,
    scheduler: str,
    workers: int | None,
    say: Callable[[str], None],
) -> None:
    """Every measurement at every size, into ``result["sizes"]``."""
    for (width, height), (rig, made) in runs.items():
        label = f"{width}x{height}"
        entry: dict = {
            "width": width,
            "height": height,
            "pixel_pitch_um": round(rig.camera.pixel_pitch_m * 1e6, 4),
            "load_avg_before": _load(),
            "run": {
                "file": str(made.path),
                "bytes": made.path.stat().st_size,
                "from_cache": made.from_cache,
                "created_s": round(made.created_s, 1),
                "cache_key": made.key,
                "created_utc": made.record.get("created_utc"),
                "load_avg_when_made": made.record.get("load_avg_at_end"),
                "how": made.record.get("how"),
            },
        }
        say(f"{label}: read floor")
        entry["read"] = measure_read(made.path, repeat)
        say(f"{label}: whole-run processing ({scheduler})")
        entry["process"] = measure_process(
            made.path,
            rig,
            process_repeat,
            scheduler,
            workers,
            entry["read"]["read_s"],
            log=say,
            parallel_read_repeat=repeat,
        )
        say(f"{label}: chief rays")
        entry["trace"] = measure_trace(made.path, repeat)
        say(f"{label}: HDR merge" + (" next to HDRutils and colour-hdri" if peers else ""))
        entry["hdr"] = measure_hdr(made.path, hdr_positions, repeat, peers)
        say(f"{label}: acquisition")
        entry["acquire"] = measure_acquire(made.path, repeat)
        entry["load_avg_after"] = _load()
        result["sizes"][label] = entry


def _load() -> list[float]:
    """The load averages (1, 5, 15 minutes), to two decimals."""
    return [round(v, 2) for v in os.getloadavg()]


def _machine() -> dict:
    return {
        "cpu_count": os.cpu_count(),
        "memory_gb": round(psutil.virtual_memory().total / 1e9, 1),
        "python": platform.python_version(),
        "numpy": np.__version__,
    }
