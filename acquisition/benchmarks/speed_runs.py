"""The simulated runs ``bench speed`` measures, made once and kept in a cache.

Rendering is slow, so each run is made once and kept (``~/.cache/mirrorgonio/bench/``, one
run file per key: a hash of the rig, the exposures, the positions and the creation code's
version, :data:`CACHE_FORMAT`), with a record of how long it took to make. Also here: the
benchmark's reference bracket and sweep, and :class:`SpeedBenchError`, which every part of
the benchmark raises for parameters or runs it cannot measure.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from acquisition.benchmarks.accuracy import REFERENCE_EXPOSURES_S, take_run
from acquisition.daemon.models import FixedBracket, RunRequest
from acquisition.daemon.settings import load_settings
from drivers.contracts.rig import Rig, rig_to_toml_dict

#: The reference bracket (``bench accuracy``'s): 2e-5 s to 12.5 ms, steps of 5.
EXPOSURES_S = REFERENCE_EXPOSURES_S
POSITIONS = 66
#: Bump when the way the cached runs are made changes: older cache entries are then ignored.
CACHE_FORMAT = 1
DEFAULT_CACHE = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "mirrorgonio" / "bench"


class SpeedBenchError(ValueError):
    """Parameters the benchmark cannot run with (one line naming the option)."""


def cache_key(rig: Rig, exposures: Sequence[float], positions: int) -> str:
    """A short hash of everything that makes a cached run what it is."""
    data = {
        "rig": rig_to_toml_dict(rig),
        "exposures_s": [float(t) for t in exposures],
        "positions": int(positions),
        "format": CACHE_FORMAT,
    }
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()[:16]


@dataclass
class CachedRun:
    """A simulated run's file and where it came from."""

    path: Path
    key: str
    created_s: float  # wall time the run took to make (rendering included)
    from_cache: bool
    record: dict
    temporary: Path | None = None  # made without a cache: the folder to delete when done


def _take_run(rig: Rig, exposures: Sequence[float], positions: int, workdir: Path) -> Path:
    """One run of the simulated rig through the daemon's run engine (the camera renders each
    pose once and exposes the bracket from it); the run file's path."""
    settings = load_settings(None, data_dir=workdir / "data")
    settings.arm.simulated.speed_m_s = math.inf  # the motion is not what is measured here
    return take_run(
        settings,
        rig,
        RunRequest(
            count=positions,
            bracket=FixedBracket(exposures_s=list(exposures)),
            notes="bench speed: cached simulated run",
        ),
    )


def simulated_run(
    rig: Rig,
    exposures: Sequence[float] = EXPOSURES_S,
    positions: int = POSITIONS,
    cache: Path | None = DEFAULT_CACHE,
    log: Callable[[str], None] | None = None,
) -> CachedRun:
    """The run file of ``rig``'s sweep: from ``cache`` when it holds one, else made (and kept
    there). ``cache=None``: made in a temporary folder (``CachedRun.temporary``, the caller's
    to delete)."""
    key = cache_key(rig, exposures, positions)
    if cache is not None:
        cache = Path(cache)
        run_path, record_path = cache / f"speed-{key}.h5", cache / f"speed-{key}.json"
        if run_path.is_file() and record_path.is_file():
            try:
                record = json.loads(record_path.read_text())
                return CachedRun(run_path, key, float(record["created_s"]), True, record)
            except (ValueError, KeyError, OSError):
                pass  # a damaged record: make the run again
        cache.mkdir(parents=True, exist_ok=True)
        work = Path(tempfile.mkdtemp(prefix=f"speed-{key}-", dir=cache))
    else:
        work = Path(tempfile.mkdtemp(prefix=f"mirrorgonio-speed-{key}-"))
        run_path, record_path = work / f"speed-{key}.h5", None
    cam = rig.camera
    if log:
        log(
            f"making the simulated run {cam.width}x{cam.height}, {positions} positions x {len(exposures)} exposures "
            f"(rendering each position once; cached as {run_path})"
        )
    started = time.perf_counter()
    try:
        made = _take_run(rig, exposures, positions, work)
        created_s = time.perf_counter() - started
        os.replace(made, run_path)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    if cache is not None:
        shutil.rmtree(work, ignore_errors=True)
    record = {
        "key": key,
        "created_s": round(created_s, 1),
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "width": cam.width,
        "height": cam.height,
        "pixel_pitch_m": cam.pixel_pitch_m,
        "positions": positions,
        "exposures_s": [float(t) for t in exposures],
        "truth": rig.simulation.truth,
        "run_file_bytes": run_path.stat().st_size,
        "load_avg_at_end": [round(v, 2) for v in os.getloadavg()],
        "how": "the daemon's run engine with the simulated arm (infinite speed) and camera (one rendering per "
        "position, every exposure drawn from it, DNG written and decoded)",
    }
    if record_path is not None:
        tmp = record_path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(record, indent=2))
        os.replace(tmp, record_path)
    return CachedRun(run_path, key, created_s, False, record, None if cache is not None else work)
