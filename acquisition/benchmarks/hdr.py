"""``mirrorgonio bench hdr``: this project's raw HDR merge next to its peers, on the same brackets.

The scene
    The simulated rig's mirrored ball (the rig's truth light, rendered by
    :class:`sim_devices.optics.MirrorBallRenderer` at a few distinct schedule positions and
    cycled over the benchmark's positions) plus a smooth background of log-uniform
    brightness: a horizontal gradient from 1e2 to 1e7 e⁻/s, the same in every channel, so
    that the whole dynamic range of the bracket is exercised (the ball image alone is
    mostly dark with a few very bright sources). Each position's bracket is exposed by
    :class:`sim_devices.sensor.SensorModel` (photon and read noise, full-well clipping) with
    fresh seeded noise, outside the timed sections; only one bracket is held at a time.

The methods
    :mod:`acquisition.benchmarks.hdr_methods`: this project's merge (both weightings), HDRutils,
    colour-hdri and OpenCV's Debevec merge, given the same frames.

The error
    Every output is converted to DN/s above black on the mosaic (each photosite's own
    channel for the peers that return RGB; the scales are exact, nothing is fitted) and
    compared with the truth on the same pixel set for every method: photosites whose true
    signal in the shortest exposure stays 3 σ below the clipping level and that reach at
    least 10 DN in the longest.
"""

from __future__ import annotations

import math
import os
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path

import numba
import numpy as np

from acquisition.benchmarks.hdr_methods import (
    UNRESOLVED_MERGE_ONLY,
    MergeContext,
    MergeMethod,
    Sensor,
    colour_hdri_method,
    hdrutils_method,
    merge_only_s,
    opencv_method,
    ours_method,
    significant,
)
from drivers.contracts.rig import Rig, load_rig, rig_from_dict, rig_to_toml_dict
from sim_devices.lights import load_truth
from sim_devices.optics import MirrorBallRenderer
from sim_devices.sensor import SensorModel, mosaic_of

BACKGROUND_E_PER_S = (1e2, 1e7)
SHORTEST_S, LONGEST_S = 1e-3, 0.5
MIN_DN_LONGEST = 10.0
CLIP_MARGIN_SIGMA = 3.0
DISTINCT_SCENES = 6
TARGET_SPEEDUP = 3.0
OURS = ("mirrorgonio_optimal", "mirrorgonio_poisson")
PEERS = ("hdrutils", "colour_hdri", "opencv_debevec", "opencv_debevec_12bit")


class BenchmarkError(ValueError):
    """Parameters the benchmark cannot run with (one line naming the field)."""


# --- the scene -----------------------------------------------------------------------------------
@dataclass
class _Scene:
    position: int
    rate_e: np.ndarray  # (H, W) e⁻/s on the mosaic
    mask: np.ndarray  # the pixel set
    truth: np.ndarray  # true DN/s above black on the pixel set
    floor_rel_var_sum: float  # Σ over the set of the ideal merge's variance / truth²


def exposure_times(count: int) -> np.ndarray:
    """``count`` exposures, geometric from SHORTEST_S to LONGEST_S."""
    if count == 1:
        return np.array([SHORTEST_S])
    return SHORTEST_S * (LONGEST_S / SHORTEST_S) ** (np.arange(count) / (count - 1))


def rig_at_size(rig: Rig, width: int, height: int) -> Rig:
    """The rig with its sensor resampled to ``width`` x ``height``, the same field of view across.

    Parameters
    ----------
    rig : drivers.contracts.rig.Rig
        The rig as described.
    width, height : int
        The sensor's size in photosites.

    Returns
    -------
    drivers.contracts.rig.Rig
        ``rig`` itself at its own size; else a copy whose pixel pitch (and principal point)
        are scaled so that the sensor spans the same field of view.
    """
    cam = rig.camera
    if (cam.width, cam.height) == (width, height):
        return rig
    scale = cam.width / width
    data = rig_to_toml_dict(rig)
    data["camera"].update(width=width, height=height, pixel_pitch_m=cam.pixel_pitch_m * scale)
    if cam.principal_point_px is not None:
        cx, cy = cam.principal_point_px
        data["camera"]["principal_point_px"] = [(cx + 0.5) / scale - 0.5, (cy + 0.5) / scale - 0.5]
    return rig_from_dict(data, f"rig {rig.name!r} at {width}x{height}")


def _background(height: int, width: int) -> np.ndarray:
    lo, hi = BACKGROUND_E_PER_S
    return np.broadcast_to(np.logspace(math.log10(lo), math.log10(hi), width), (height, width))


def _pixel_set(truth_dn: np.ndarray, sensor: Sensor, exposures: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The compared photosites, and the variance of the ideal merge of each."""
    clip = sensor.range_dn
    short = truth_dn * exposures.min()
    unsaturated = short + CLIP_MARGIN_SIGMA * np.sqrt(sensor.variance_dn(short)) < clip
    mask = unsaturated & (truth_dn * exposures.max() >= MIN_DN_LONGEST)
    # Off the frame's outer row and column: HDRutils' bilinear demosaic (edge-repeating
    # convolution) changes the sampled channel's value there, which is not its merge's doing.
    mask[0, :] = mask[-1, :] = mask[:, 0] = mask[:, -1] = False
    x = truth_dn[mask]
    info = np.zeros_like(x)
    for t in exposures:
        mu = x * t
        var = sensor.variance_dn(mu)
        usable = mu + CLIP_MARGIN_SIGMA * np.sqrt(var) < clip
        info += np.where(usable, t * t / var, 0.0)
    return mask, x, float(np.sum(1.0 / (info * x * x)))


def _scenes(rig: Rig, sensor: Sensor, exposures: np.ndarray, distinct: int, seed: int) -> list[_Scene]:
    """The ball rendered at ``distinct`` positions spread over the schedule, the background
    added; each scene's pixel set and truth."""
    renderer = MirrorBallRenderer(
        rig, load_truth(rig.simulation.truth), diffraction=rig.simulation.diffraction, seed=seed
    )
    poses = rig.light_poses()
    picks = sorted({int(i) for i in np.linspace(0, len(poses) - 1, distinct).round()})
    background = _background(rig.camera.height, rig.camera.width)
    scenes = []
    for i in picks:
        rate = mosaic_of(renderer.render(poses[i]).rate, sensor.cfa_pattern) + background
        mask, truth, floor = _pixel_set(rate / sensor.gain, sensor, exposures)
        scenes.append(_Scene(i, rate, mask, truth, floor))
    return scenes


def _bracket(sensor: Sensor, scene: _Scene, exposures: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    assert sensor.model is not None  # _sensor_of's
    rgb = np.broadcast_to(scene.rate_e, (3, *scene.rate_e.shape))  # every channel: the site's own rate
    return np.stack([sensor.model.expose(rgb, float(t), rng) for t in exposures])


# --- errors against the truth ---------------------------------------------------------------------
@dataclass
class _Errors:
    n: int = 0
    abs_sum: float = 0.0
    sq_sum: float = 0.0
    signed_sum: float = 0.0
    nonfinite: int = 0

    def add(self, estimate: np.ndarray, truth: np.ndarray) -> None:
        rel = estimate.astype(np.float64) / truth - 1.0
        finite = np.isfinite(rel)
        self.nonfinite += int(rel.size - np.count_nonzero(finite))
        rel = rel[finite]
        self.n += rel.size
        self.abs_sum += float(np.abs(rel).sum())
        self.sq_sum += float(np.square(rel).sum())
        self.signed_sum += float(rel.sum())

    def report(self) -> dict:
        if self.n == 0:
            return {"mean_abs_rel_error_pct": None, "rms_rel_error_pct": None, "bias_pct": None}
        return {
            "mean_abs_rel_error_pct": round(100.0 * self.abs_sum / self.n, 4),
            "rms_rel_error_pct": round(100.0 * math.sqrt(self.sq_sum / self.n), 4),
            "bias_pct": round(100.0 * self.signed_sum / self.n, 4),
        }


@dataclass
class _State:
    method: MergeMethod
    times: list[float]
    excluded_times: list[float]
    errors: _Errors = field(default_factory=_Errors)
    first_call_s: float = 0.0
    failed: str | None = None


# --- the benchmark --------------------------------------------------------------------------------
def bench_hdr(
    positions: int = 66,
    exposures: int = 5,
    width: int = 2000,
    height: int = 1312,
    repeat: int = 1,
    seed: int = 0,
    *,
    rig_path: str | Path | None = None,
    peers: bool = True,
    distinct_scenes: int = DISTINCT_SCENES,
) -> dict:
    """Merge ``positions`` brackets of ``exposures`` frames with every method; time and error of each.

    ``repeat`` > 1 times every merge that many times per position (the median of the
    per-repeat totals is reported). ``peers=False`` runs this project's merges only.
    """
    t_start = time.perf_counter()
    _check_parameters(positions, exposures, width, height, repeat)
    rig = rig_at_size(load_rig(rig_path), width, height)
    sensor = _sensor_of(rig)
    times_s = exposure_times(exposures)
    ctx = MergeContext(sensor, times_s, height, width)

    t0 = time.perf_counter()
    scenes = _scenes(rig, sensor, times_s, distinct_scenes, seed)
    render_s = time.perf_counter() - t0

    methods = _methods(ctx, peers)
    states = {
        name: _State(m, [0.0] * repeat, [0.0] * repeat) for name, m in methods.items() if isinstance(m, MergeMethod)
    }
    generate_s = 0.0
    for p in range(positions):
        scene = scenes[p % len(scenes)]
        t0 = time.perf_counter()
        frames = _bracket(sensor, scene, times_s, np.random.default_rng([seed, p]))
        generate_s += time.perf_counter() - t0
        for name, state in states.items():
            if not state.failed:
                _merge_timed(name, state, frames, scene, p, repeat)
        del frames

    return _report(
        rig=rig,
        sensor=sensor,
        scenes=scenes,
        times_s=times_s,
        methods=methods,
        states=states,
        positions=positions,
        repeat=repeat,
        seed=seed,
        width=width,
        height=height,
        render_s=render_s,
        generate_s=generate_s,
        wall_s=time.perf_counter() - t_start,
    )


def _check_parameters(positions: int, exposures: int, width: int, height: int, repeat: int) -> None:
    """Raise :class:`BenchmarkError` naming the first parameter the benchmark cannot run with."""
    if positions < 1:
        raise BenchmarkError(f"positions: must be at least 1, got {positions}")
    if not 2 <= exposures <= 16:
        raise BenchmarkError(f"exposures: must be between 2 and 16, got {exposures}")
    for name, value in (("width", width), ("height", height)):
        if value < 4 or value % 2:
            raise BenchmarkError(f"{name}: must be an even number of pixels, at least 4 (a Bayer mosaic), got {value}")
    if repeat < 1:
        raise BenchmarkError(f"repeat: must be at least 1, got {repeat}")


def _sensor_of(rig: Rig) -> Sensor:
    """The rig's simulated sensor (with noise), and its constants in DN."""
    model = SensorModel.from_rig(rig.camera, noise=True)
    return Sensor(
        model.cfa_pattern,
        int(model.black_level_dn),
        int(model.white_level_dn),
        model.gain_e_per_dn,
        model.read_noise_e / model.gain_e_per_dn,
        model,
    )


def _methods(ctx: MergeContext, peers: bool) -> dict[str, MergeMethod | str]:
    """Every method by name: ours, then the peers (a string saying why where one does not run)."""
    methods: dict[str, MergeMethod | str] = {name: ours_method(ctx, name.split("_", 1)[1]) for name in OURS}
    if peers:
        methods["hdrutils"] = hdrutils_method(ctx)
        methods["colour_hdri"] = colour_hdri_method(ctx)
        methods["opencv_debevec"] = opencv_method(ctx, full_range=True)
        methods["opencv_debevec_12bit"] = opencv_method(ctx, full_range=False)
    else:
        methods.update({name: "skipped (peers=False)" for name in PEERS})
    return methods


def _merge_timed(name: str, state: _State, frames: np.ndarray, scene: _Scene, position: int, repeat: int) -> None:
    """One method on one bracket: its first call and its steady state timed, its error added up.
    A peer that fails is marked failed (a result); this project's merge failing raises."""
    m = state.method
    try:
        if position == 0:  # warm-up, untimed: numba's JIT, the peers' lazy imports
            m.run(m.prepare(frames))
            if m.excluded:
                m.excluded(None)
        # The first call on a fresh bracket, right after the previous method's work: timed
        # apart. It is often slower (caches, the allocator's state, the kernel's page
        # handling), by an amount that depends on what ran before, not only on the method.
        prepared = m.prepare(frames)
        t0 = time.perf_counter()
        m.run(prepared)
        state.first_call_s += time.perf_counter() - t0
        del prepared
        # Steady state: the method after its own previous call, as in a run of many brackets.
        out = None
        for r in range(repeat):
            prepared = m.prepare(frames)
            t0 = time.perf_counter()
            out = m.run(prepared)
            state.times[r] += time.perf_counter() - t0
            if m.excluded:
                t0 = time.perf_counter()
                m.excluded(prepared)
                state.excluded_times[r] += time.perf_counter() - t0
            del prepared
        state.errors.add(m.to_dn_per_s(out)[scene.mask], scene.truth)
        del out
    except Exception as exc:  # noqa: BLE001 - a peer failing is a result; ours is not
        if name in OURS:
            raise
        state.failed = (
            f"failed at position {position}: {type(exc).__name__}: "
            f"{str(exc).strip().splitlines()[0] if str(exc).strip() else ''}"
        )


# --- the report -----------------------------------------------------------------------------------
TIMING = (
    "time.perf_counter around each method's call, per position, summed over the positions; "
    "time_s is the steady state (the method called on the bracket just after an untimed call of "
    "its own on it; the median over repeats), time_s_first_call the call right after the previous "
    "method's work (reported, not used for the speed-ups); preparing a peer's input is not timed; "
    "one untimed call on the first bracket warms numba's JIT and the peers' imports"
)
ERROR_DEFINITION = (
    "relative error (estimate / truth - 1) per photosite, both in DN/s above black; "
    "mean |.|, RMS and mean (bias), in percent"
)


def _report(
    *,
    rig: Rig,
    sensor: Sensor,
    scenes: list[_Scene],
    times_s: np.ndarray,
    methods: dict,
    states: dict,
    positions: int,
    repeat: int,
    seed: int,
    width: int,
    height: int,
    render_s: float,
    generate_s: float,
    wall_s: float,
) -> dict:
    """The benchmark's JSON: the set-up, every method's time and error, the speed-ups and the target."""
    model = sensor.model
    assert model is not None  # _sensor_of's
    used = [scenes[p % len(scenes)] for p in range(positions)]
    out_methods = {name: _method_entry(m, states.get(name), positions) for name, m in methods.items()}
    result: dict = {
        "benchmark": "hdr",
        "width": width,
        "height": height,
        "positions": positions,
        "exposures_per_position": len(times_s),
        "exposures_s": [float(f"{t:.6g}") for t in times_s],
        "repeat": repeat,
        "seed": seed,
        "scene": {
            "description": (
                "the rig's mirrored ball lit by the truth light, rendered at a few schedule positions "
                "(cycled over the benchmark's positions, fresh seeded sensor noise per position), plus a "
                "smooth background: a horizontal log-uniform gradient from 1e2 to 1e7 e-/s in every channel"
            ),
            "truth_light": rig.simulation.truth,
            "rendered_schedule_positions": [s.position for s in scenes],
            "background_e_per_s": list(BACKGROUND_E_PER_S),
            "diffraction": rig.simulation.diffraction,
        },
        "sensor": {
            "cfa_pattern": sensor.cfa_pattern,
            "black_level_dn": sensor.black,
            "white_level_dn": sensor.white,
            "full_well_e": model.full_well_e,
            "read_noise_e": model.read_noise_e,
            "gain_e_per_dn": round(sensor.gain, 5),
        },
        "pixel_set": _pixel_set_report(used, positions * width * height),
        "timing": TIMING,
        "error_definition": ERROR_DEFINITION,
        "methods": out_methods,
    }
    result.update(_speedups_and_target(out_methods))
    result["machine"] = _machine()
    result["render_s"] = round(render_s, 2)
    result["frame_generation_s"] = round(generate_s, 2)
    result["wall_s"] = round(wall_s, 1)
    return result


def _method_entry(m: MergeMethod | str, state: _State | None, positions: int) -> dict:
    """One method's entry in the report: why it did not run, why it failed, or its time and error."""
    unmeasured = {
        "time_s": None,
        "ms_per_position": None,
        "mean_abs_rel_error_pct": None,
        "rms_rel_error_pct": None,
        "bias_pct": None,
    }
    if not isinstance(m, MergeMethod):
        return {"status": m, **unmeasured, "notes": m}
    assert state is not None  # every method that ran has its state
    if state.failed:
        return {"status": state.failed, **unmeasured, "notes": m.notes, "version": m.version}
    total = statistics.median(state.times)
    entry = {
        "status": "ok",
        "time_s": significant(total, 4),
        "ms_per_position": round(1000.0 * total / positions, 3),
        **state.errors.report(),
        "pixels_compared": state.errors.n,
        "nonfinite_pixels": state.errors.nonfinite,
        "time_s_all": [round(t, 4) for t in state.times],
        "time_s_first_call": significant(state.first_call_s, 4),
        "input": m.input,
        "scale": m.scale,
        "notes": m.notes,
        "version": m.version,
    }
    if m.excluded:
        excluded = statistics.median(state.excluded_times)
        entry["excluded_part_s"] = round(excluded, 4)
        entry["excluded_part"] = m.excluded_what
        own = merge_only_s(total, excluded)
        if own is not None:
            entry["time_s_merge_only_est"] = significant(own, 4)
        else:
            entry["merge_only"] = UNRESOLVED_MERGE_ONLY
    return entry


def _pixel_set_report(used: list[_Scene], photosites: int) -> dict:
    """The compared pixel set over the scenes ``used`` (one per position): its rule, size,
    signal range and the ideal merge's noise floor."""
    n_set = sum(int(s.mask.sum()) for s in used)
    floor = math.sqrt(sum(s.floor_rel_var_sum for s in used) / n_set) if n_set else None
    return {
        "rule": (
            f"true signal in the shortest exposure + {CLIP_MARGIN_SIGMA:g} sigma below the clipping level, "
            f"and >= {MIN_DN_LONGEST:g} DN above black in the longest; not on the frame's outermost rows "
            "and columns "
            "(HDRutils' bilinear demosaic alters the sampled value there); the same photosites for every method"
        ),
        "pixels_compared": n_set,
        "fraction_of_photosites": round(n_set / photosites, 4),
        "true_signal_dn_per_s_range": [
            round(float(min(s.truth.min() for s in used if s.truth.size)), 2) if n_set else None,
            round(float(max(s.truth.max() for s in used if s.truth.size)), 1) if n_set else None,
        ],
        "noise_floor_rms_rel_error_pct": round(100.0 * floor, 4) if floor is not None else None,
        "noise_floor": "RMS relative error of the ideal unbiased merge: weights t^2/sigma^2 from the true "
        "signal, over the frames 3 sigma below clipping (photon, read and quantisation noise)",
    }


def _speedups_and_target(out_methods: dict) -> dict:
    """Our speed-up over each peer measured, and the target (:data:`TARGET_SPEEDUP`, the error
    no higher) judged per peer and over all of them."""
    ours = out_methods["mirrorgonio_optimal"]
    result: dict = {}
    target_rows = {}
    for peer in PEERS:
        entry = out_methods.get(peer, {})
        peer_time = entry.get("time_s_merge_only_est", entry.get("time_s"))
        if entry.get("status") != "ok" or not ours.get("time_s") or peer_time is None:
            result[f"speedup_vs_{peer}"] = None
            continue
        speedup = peer_time / ours["time_s"]
        result[f"speedup_vs_{peer}"] = significant(speedup)
        if "time_s_merge_only_est" in entry:
            result[f"speedup_vs_{peer}_full_call"] = significant(entry["time_s"] / ours["time_s"])

        first_call = entry["time_s_first_call"]
        first_call = merge_only_s(first_call, entry.get("excluded_part_s", 0.0)) or first_call

        def not_worse(key, entry=entry):
            return ours[key] is not None and entry[key] is not None and ours[key] <= entry[key] * 1.001 + 1e-3

        target_rows[peer] = {
            "speedup": significant(speedup),
            "speedup_first_call": significant(first_call / ours["time_s_first_call"]),
            "at_least_3x_faster": speedup >= TARGET_SPEEDUP,
            "error_not_higher": not_worse("mean_abs_rel_error_pct") and not_worse("rms_rel_error_pct"),
        }
    result["target"] = (
        f"mirrorgonio_optimal at least {TARGET_SPEEDUP:g}x faster than every peer, with a mean |relative "
        "error| and an RMS relative error no higher than the peer's"
    )
    result["target_per_peer"] = target_rows
    result["meets_target"] = (
        all(r["at_least_3x_faster"] and r["error_not_higher"] for r in target_rows.values()) if target_rows else None
    )
    result["peers_measured"] = sorted(target_rows)
    return result


def _machine() -> dict:
    info = {
        "cpu_count": os.cpu_count(),
        "numba_threads": numba.get_num_threads(),
        "numpy": np.__version__,
        "numba": numba.__version__,
    }
    try:
        import cv2  # noqa: PLC0415 - heavy

        info["opencv_threads"] = cv2.getNumThreads()
    except ImportError:  # pragma: no cover - OpenCV is a dependency
        pass
    return info
