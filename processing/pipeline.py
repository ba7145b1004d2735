"""The offline processing of one run file, step by step, position by position.

Steps (``--steps``, :mod:`processing.steps`): ``hdr`` — merge each position's bracket
(``processing.hdr``) into the results file, an OpenEXR and a PNG per position; ``sources``
— per position, the chief rays, the sources' templates and their unmixing (or cell sums);
then per run the fits, the light model, the IES / LDT / TM-25 files and the report.

Positions stream through a :class:`~processing.parallel.Compute` (a Dask cluster, or this
process): every task opens the run file itself, by path, reads one position and returns
only that position's result; this process writes each result into the results file as it
arrives. A run is never loaded whole, and the memory in use is a few positions' worth
whatever the run's length. When the sources' layout is given, one task per position does
both steps (the merged radiance goes straight into the unmixing); when it is to be found
in the data, the merge comes first, the layout is found at three positions, and a second
pass over the results file unmixes.

A run still being written is processed as far as it goes: the positions complete when it
is opened (``ProcessReport.partial`` says so).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numba
import numpy as np

from drivers.contracts.runfile import RunFile, RunFileError
from processing.hdr import HDRError, NoiseModel, estimate_noise, merge_raw, superpixels
from processing.parallel import Compute, in_dask_worker, tune_malloc
from processing.results import (
    HDRInfo,
    Results,
    ResultsError,
    ResultsWriter,
    encode_hdr,
    position_file_for,
    results_path_for,
    stored_variance,
    write_position_file,
)
from processing.steps import STEPS, StepsError, resolve_steps

log = logging.getLogger("mirrorgonio.processing")
ESTIMATORS = ("auto", "templates", "cell-sums")
__all__ = ["ESTIMATORS", "STEPS", "ProcessReport", "ProcessingError", "process_run"]


class ProcessingError(ValueError):
    """A run that cannot be processed (one line naming the file and the cause)."""


@dataclass
class ProcessReport:
    """What :func:`process_run` did and wrote.

    ``outputs`` maps a kind (``exr``, ``png``, ``ies``, ``ldt``, ``tm25``, ``report``) to
    its files; ``timings`` the stages (``noise``, ``layout``, ``positions``, ``fit``,
    ``exports``, ``report``, ``total``) to seconds of wall time; ``task_stages`` the
    seconds the position tasks spent in each of their stages (``read``, ``merge``,
    ``encode``, ``write`` (the position file), ``images``, ``masks``, ``sources``), summed
    over the tasks, wherever they ran.
    """

    run_file: Path
    results_file: Path
    positions: int
    noise: NoiseModel
    outputs: dict[str, list[Path]] = field(default_factory=dict)
    samples: object = None
    model: object = None
    saturated_pixels: int = 0
    light_model: Path | None = None
    estimator: str = ""
    estimator_reason: str = ""
    layout_search: str = ""  # how the sources were found in the data (empty when a layout was given)
    aperture_fit: dict = field(default_factory=dict)  # the aperture fitted to the data (fit_aperture), or why it failed
    sensor_distance_fit: dict = field(
        default_factory=dict
    )  # the sensor distance fitted to the data (fit_sensor_distance)
    spatial_resolution_m: float = float("nan")
    n_positions: int = 0
    partial: bool = False
    compute: str = ""
    timings: dict[str, float] = field(default_factory=dict)
    task_stages: dict[str, float] = field(default_factory=dict)

    def add_task(self, result: PositionResult) -> None:
        for stage, seconds in result.stages.items():
            self.task_stages[stage] = self.task_stages.get(stage, 0.0) + seconds
        self.task_stages["tasks"] = self.task_stages.get("tasks", 0.0) + result.seconds


def rig_noise(run: RunFile) -> NoiseModel:
    cam = run.header.rig.camera
    return NoiseModel(cam.gain_e_per_dn, cam.read_noise_e / cam.gain_e_per_dn, source="rig")


def radiometric_gain(run: RunFile) -> float:
    """e⁻ per DN for turning merged DN/s into e⁻/s: the rig's calibrated gain, always.

    The camera's sensitivity (e⁻/s per unit radiance) that the templates and cell sums
    divide by was calibrated with this gain, and the reflectance step converts with it too
    (``processing.reflectance``). A gain estimated from the brackets only weights the merge
    (the noise model): converting with it instead would scale the light's intensities,
    and so every albedo measured under it, by estimated/rig (+2.1 % on the bench's run).
    """
    return float(run.header.rig.camera.gain_e_per_dn)


#: How far an estimated gain may lie from the rig's before it is worth a warning: the
#: estimate from the brackets came out 2.1 % above the simulated camera's true gain on the
#: bench's run, and it only weights the merge; beyond this, the rig's figure is suspect.
GAIN_MISMATCH_WARNING = 0.05


def gain_mismatch(noise: NoiseModel, rig_gain: float) -> tuple[int, str] | None:
    """How far the noise model's gain lies from the rig's calibrated gain, as a logging level
    and one line: None within 1 %, a warning beyond :data:`GAIN_MISMATCH_WARNING`, else
    information. The light and the reflectance steps both say it so."""
    off = noise.gain_e_per_dn / rig_gain - 1.0
    if abs(off) <= 0.01:
        return None
    warn = abs(off) > GAIN_MISMATCH_WARNING
    advice = "; check the camera's calibration" if warn else ""
    return (
        logging.WARNING if warn else logging.INFO,
        f"the noise model's gain ({noise.source}, {noise.gain_e_per_dn:.4g} e-/DN) differs from the rig's calibrated "
        f"gain ({rig_gain:.4g} e-/DN) by {100 * off:+.1f} %: the merge is weighted with it, intensities use the "
        f"rig's{advice}",
    )


def _report_gain_mismatch(run: RunFile, noise: NoiseModel) -> None:
    said = gain_mismatch(noise, radiometric_gain(run))
    if said is not None:
        log.log(said[0], "%s: %s", run.path, said[1])


def _prepare_task() -> None:
    """What every task does first: keep freed arrays in the heap (``tune_malloc``) and, in a
    Dask worker, run the numerical kernels on the task's thread alone.

    The workers are the parallelism: numba's parallel kernels would start a thread per core
    in every worker, and on 2 cores the noise estimates then took 50-200 ms each instead of
    40-50. ``numba.set_num_threads`` holds for the calling thread only, so each task sets it
    on the thread it runs on. Without Dask, the kernels keep every core.
    """
    tune_malloc()
    if in_dask_worker():
        numba.set_num_threads(1)


def _noise_estimate_at(index: int, run_path: str) -> NoiseModel | None:
    """One position's noise estimate (a task: opens the run itself); None if its bracket allows none."""
    _prepare_task()
    with _open_run(run_path) as run:
        if len(run.exposures(index)) < 2:
            return None
        try:
            return estimate_noise(
                run.frames(index),
                run.exposures(index),
                run.black_level(index)[0],
                white_level=int(run.white_level(index)[0]),
            )
        except HDRError as exc:
            log.info("position %d: %s", index, exc)
            return None


def choose_noise(run: RunFile, positions: np.ndarray, mode: str, compute: Compute | None = None) -> NoiseModel:
    """The noise model: the rig's figures, or estimated from the brackets (median over a
    few positions), falling back to the rig's with the reason logged."""
    from_rig = rig_noise(run)
    if mode == "rig":
        return from_rig
    sample = positions[np.linspace(0, len(positions) - 1, min(5, len(positions))).astype(int)]
    found: dict[int, NoiseModel | None] = {}
    (compute or Compute()).map_unordered(
        _noise_estimate_at, [int(i) for i in sample], str(run.path), on_result=found.__setitem__
    )
    estimates = [found[int(i)] for i in sample if found.get(int(i)) is not None]
    if not estimates:
        if mode == "estimated":
            raise ProcessingError(f"{run.path}: the noise model cannot be estimated from these brackets")
        log.warning("%s: noise model from the rig: the brackets did not allow an estimate", run.path)
        return from_rig
    gain = float(np.median([e.gain_e_per_dn for e in estimates]))
    read = float(np.median([e.read_noise_dn for e in estimates]))
    return NoiseModel(gain, read, source="estimated")


def _open_run(path) -> RunFile:
    try:
        return RunFile.open(path)
    except RunFileError as exc:
        raise ProcessingError(str(exc)) from None


# --- the work of one position (runs in a Dask worker, or here) ------------------------------------
def warm_up_worker() -> None:
    """Ready a worker process for position tasks: import the processing modules and load
    the compiled kernels from numba's cache, on tiny inputs.

    A fresh worker otherwise pays this (about a second, and matplotlib's import and fonts
    for the report's sections) in the first tasks of its first run;
    :func:`processing.parallel.open_compute` runs it on every worker it starts, as a part of
    starting the cluster.
    """
    from processing.images import tonemap
    from processing.report import warm_up_drawing
    from processing.sources import _convex_coverage, specular_points

    _prepare_task()
    rng = np.random.default_rng(0)
    frames = rng.integers(64, 4000, (2, 8, 8)).astype(np.uint16)
    merged = merge_raw(frames, [1e-3, 4e-3], 64, 4095, NoiseModel(5.0, 0.6))
    _position_masks(merged.radiance, stored_variance(merged.variance), merged.count, merged.saturated)
    tonemap(superpixels(merged.radiance, "RGGB"))
    encode_hdr(merged)
    try:
        estimate_noise(frames, [1e-3, 4e-3], 64, white_level=4095)
    except HDRError:
        pass  # too few pixels for an estimate: the kernels ran all the same
    specular_points(np.array([[0.0, 0.05, 0.1]]), np.array([[0.0, 0.0, 0.2]]), np.zeros(3), 0.0254)
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    _convex_coverage(square, np.linspace(-0.5, 1.5, 5), np.linspace(-0.5, 1.5, 5), 0.5)
    warm_up_drawing()  # the workers draw report sections at the end of a run


@dataclass(frozen=True)
class _HDRWork:
    method: str
    noise: NoiseModel
    cfa: str
    images_dir: str | None


@dataclass(frozen=True)
class CameraFit:
    """The camera's numbers fitted to the data (``--fit-aperture``, ``--fit-sensor-distance``);
    each None where the rig's description stands."""

    aperture_m: float | None = None
    sensor_distance_m: float | None = None


@dataclass(frozen=True)
class _SourcesPlan:
    """What every position's source estimate needs, decided once per run."""

    layout: tuple
    ball_centre: tuple | None
    estimator: str  # chosen: "templates" or "cell-sums"
    reason: str
    footprint: float
    cell_radius: float
    camera: CameraFit | None = None  # fitted to the data; None: as the rig describes it


@dataclass(frozen=True)
class _PositionWork:
    run_path: str
    results_path: str
    hdr: _HDRWork | None  # None: read the merged position from the results file
    sources: _SourcesPlan | None


@dataclass
class _SourceRow:
    theta: np.ndarray
    phi: np.ndarray
    intensity_rgb: np.ndarray  # (n_sources, 3)
    sigma_rgb: np.ndarray
    cell_sum: np.ndarray  # (n_sources,)


@dataclass
class PositionResult:
    """What one position task returns: when it merged, the saturation level of the merge it
    wrote to its position file (the data stay there: only this process's caller commits
    them), and its source samples."""

    index: int
    saturation_level: np.ndarray | None = None
    images: dict[str, Path] = field(default_factory=dict)
    saturated: int = 0
    all_saturated: bool = False
    sources: _SourceRow | None = None
    seconds: float = 0.0
    stages: dict[str, float] = field(default_factory=dict)  # seconds per stage of this task


class _StageClock:
    """Seconds spent in each stage of one task (``read``, ``merge``, ``encode``, ...)."""

    def __init__(self, into: dict[str, float]):
        self.into, self.last = into, time.perf_counter()

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        self.into[stage] = self.into.get(stage, 0.0) + now - self.last
        self.last = now


def process_position(index: int, work: _PositionWork) -> PositionResult:
    """Merge and/or estimate one position; opens the run (and results) file by path.

    A module-level function so that Dask workers import it. Domain errors come back as
    :class:`ProcessingError` naming the file and the position.
    """
    started = time.perf_counter()
    _prepare_task()
    out = PositionResult(index)
    clock = _StageClock(out.stages)
    with _open_run(work.run_path) as run:
        try:
            if work.hdr is not None:
                h = work.hdr
                frames, exposures = run.frames(index), run.exposures(index)
                black, white = run.black_level(index)[0], int(run.white_level(index)[0])
                clock.lap("read")
                merged = merge_raw(frames, exposures, black, white, h.noise, method=h.method)
                # As the results file stores it, so that both paths give the same numbers
                # (in place: the merge's array is this task's own).
                stored_variance(merged.variance, out=merged.variance)
                del frames
                clock.lap("merge")
                encoded = encode_hdr(merged, variance_stored=True)  # compressed and written here, in parallel
                clock.lap("encode")
                write_position_file(position_file_for(work.results_path, index), encoded)
                out.saturation_level = encoded.saturation_level
                del encoded
                clock.lap("write")
                if h.images_dir is not None:
                    out.images = _write_images(Path(h.images_dir), index, merged.radiance, h.cfa)
                    clock.lap("images")
                radiance, variance, count, saturated = merged.radiance, merged.variance, merged.count, merged.saturated
                cfa = h.cfa
            else:
                with Results.open(work.results_path) as results:
                    radiance, variance = results.radiance(index), results.variance(index)
                    count, saturated = results.count(index), results.saturated(index)
                    cfa = results.cfa_pattern
                clock.lap("read")
            gain = radiometric_gain(run)
        except HDRError as exc:
            raise ProcessingError(f"{run.path}: position {index}: {exc}") from None
        except RunFileError as exc:
            raise ProcessingError(str(exc)) from None
        except ResultsError as exc:
            raise ProcessingError(str(exc)) from None
        usable, lit, n_saturated = _position_masks(radiance, variance, count, np.asarray(saturated, bool))
        out.saturated = n_saturated
        out.all_saturated = n_saturated == saturated.size
        if work.sources is not None:
            # The estimates read windows and a few hundred pixels: convert only those to e⁻/s.
            rate, var = ElectronRates(radiance, gain), ElectronRates(variance, gain, gain)
            clock.lap("masks")
            out.sources = _estimate_at(run, work.sources, index, rate, var, usable, lit, cfa)
            clock.lap("sources")
    out.seconds = time.perf_counter() - started
    return out


class ElectronRates:
    """A merged mosaic in DN/s (or DN²/s²) read as e⁻/s (or (e⁻/s)²): converted to float64
    and multiplied by each factor in turn only where it is indexed.

    The source estimates read a window around the templates and a few hundred pixels of
    the cells, out of 2.6 M; converting whole frames cost more (21 ms a position) than the
    estimates themselves. Any index gives the numbers ``array.astype(float64) * f1 * f2``
    would hold there.
    """

    __slots__ = ("dn", "factors", "shape")

    def __init__(self, dn: np.ndarray, *factors: float):
        self.dn, self.factors, self.shape = dn, factors, dn.shape

    def __getitem__(self, key) -> np.ndarray:
        out = np.asarray(self.dn[key], dtype=np.float64)
        for factor in self.factors:
            out = out * factor
        return out


@numba.njit(cache=True)
def _position_masks(radiance, variance, count, saturated):
    """One pass over a merged position: the usable pixels (a finite estimate from at least
    one unsaturated sample), the lit ones among them (3 σ above zero, in float32 as the
    arrays hold it) and the number saturated in every frame."""
    usable = np.empty(radiance.shape, np.bool_)
    lit = np.empty(radiance.shape, np.bool_)
    n_saturated = 0
    three = np.float32(3.0)
    largest = np.float32(3.4028234663852886e38)  # |x| <= largest: finite (nan compares false)
    r, v, c, s = radiance.ravel(), variance.ravel(), count.ravel(), saturated.ravel()
    u, li = usable.ravel(), lit.ravel()
    # Without branches (& rather than `and`): 1.3 ms a 1312x2000 position instead of 1.8.
    for i in range(r.size):
        n_saturated += np.int64(s[i])
        x = r[i]
        ok = (not s[i]) & (c[i] > 0) & (abs(x) <= largest)
        u[i] = ok
        li[i] = ok & (x > three * np.sqrt(v[i]))
    return usable, lit, n_saturated


def _rates(radiance, variance, count, saturated, gain: float):
    """Electron rates, their variance and the usable pixels of one merged position."""
    usable, _, _ = _position_masks(radiance, variance, count, np.asarray(saturated, bool))
    return ElectronRates(radiance, gain)[...], ElectronRates(variance, gain, gain)[...], usable


def _write_images(folder: Path, index: int, radiance: np.ndarray, cfa: str) -> dict[str, Path]:
    from processing.images import write_exr, write_png

    rgb = superpixels(radiance, cfa, nonfinite=0.0)
    return {
        "exr": write_exr(folder / f"position-{index:03d}.exr", rgb),
        "png": write_png(folder / f"position-{index:03d}.png", rgb),
    }


_GEOMETRIES: dict[tuple, tuple] = {}


def _geometry(run: RunFile, ball_centre, camera: CameraFit | None = None):
    """The rig's geometry and template builder (ball at ``ball_centre``, or where the rig says;
    the camera's aperture and sensor distance as ``camera`` has them, or as the rig says).

    Kept per process for the rig object the run file's header shares (``drivers.contracts.runfile``
    validates a rig once per text): every position task of a run asks for the same one, and
    making them cost 1 ms a task. The rig itself is held with them, so its ``id`` stays its own.
    """
    from processing.sources import TemplateBuilder
    from processing.trace import RigGeometry

    rig = run.header.rig
    camera = camera or CameraFit()
    key = (id(rig), None if ball_centre is None else tuple(float(x) for x in ball_centre), camera)
    held = _GEOMETRIES.get(key)
    if held is None or held[0] is not rig:
        geometry = RigGeometry.from_rig(rig, ball_centre=ball_centre)
        if camera.aperture_m is not None:
            geometry = replace(geometry, aperture_radius=0.5 * float(camera.aperture_m))
        if camera.sensor_distance_m is not None:
            geometry = geometry.with_sensor_distance(float(camera.sensor_distance_m))
        if len(_GEOMETRIES) >= 8:
            _GEOMETRIES.pop(next(iter(_GEOMETRIES)))
        held = _GEOMETRIES[key] = (rig, geometry, TemplateBuilder(geometry, rig.camera.sensitivity_e_per_s))
    return held[1], held[2]


def _estimate_at(run: RunFile, plan: _SourcesPlan, index: int, rate, variance, usable, lit, cfa: str) -> _SourceRow:
    """Every source's intensity at one position: templates unmixed, and the cell sums over
    the ``lit`` pixels."""
    from processing.sources import cell_sums, unmix_position

    geometry, builder = _geometry(run, plan.ball_centre, plan.camera)
    layout = list(plan.layout)
    pose = _light_pose(run, geometry, index)
    estimate = unmix_position(index, rate, variance, usable, cfa, builder, layout, pose)
    sums = cell_sums(
        rate, lit, geometry, run.header.rig.camera.sensitivity_e_per_s, layout, pose, plan.cell_radius, cfa
    ).mean(axis=1)
    return _SourceRow(estimate.theta, estimate.phi, estimate.intensity, estimate.sigma, sums)


# --- one run ---------------------------------------------------------------------------------------
class _Progress:
    def __init__(self, callback, total: int):
        self.callback, self.total, self.done = callback, total, 0

    def step(self) -> None:
        self.done += 1
        if self.callback:
            self.callback(self.done, self.total)


def process_run(
    run_path,
    out_dir=None,
    *,
    steps=("hdr",),
    method: str = "optimal",
    noise: str = "auto",
    progress: Callable[[int, int], None] | None = None,
    layout=None,
    estimator: str = "auto",
    fit_method: str = "gaussian",
    units: str = "relative",
    truth=None,
    ball_centre=None,
    compute: Compute | None = None,
    images: bool = True,
    fit_aperture: bool | None = None,
    fit_sensor_distance: bool = False,
) -> ProcessReport:
    """Process one run file; results go beside it, or into ``out_dir``.

    Parameters
    ----------
    run_path : path-like
        The run file; a run still being written is processed up to its last complete
        position.
    out_dir : path-like, optional
        Folder for the results (default: the run's folder).
    steps : str or sequence of str
        ``hdr``, ``sources`` (:func:`processing.steps.resolve_steps`).
    compute : Compute, optional
        Where the position tasks run (:func:`processing.parallel.open_compute`); default:
        in this process, one after the other.
    progress : callable, optional
        ``progress(done, total)`` after every position task.
    images : bool
        Write an OpenEXR and a PNG preview per position (the ``hdr`` step).
    fit_aperture : bool, optional
        Fit the camera's aperture diameter (the pinhole's) to the data before the sources are
        estimated, and estimate them with it (:func:`processing.sources.fit_aperture`;
        ``report.aperture_fit``, the light model's provenance). With ``layout`` given, the
        merge and the estimate then take two passes over the positions; without, the search
        for the sources and the aperture's fit alternate (:func:`_layout_and_camera`).
        None (the default): fitted when the sources are searched for in the data (no
        ``layout``), where it mended a pinhole described 1-10 % off and cost 0.3-0.5 % of peak
        with the description exactly right (``docs/light-model.md``); a fit that fails
        there is said and the last aperture kept. True: fitted with a layout too, and a failed
        fit fails the processing.
    fit_sensor_distance : bool
        Fit the sensor distance (pinhole to sensor) to the data as well, before the aperture
        (:func:`processing.sources.fit_sensor_distance`; ``report.sensor_distance_fit``, the
        light model's provenance): at a given layout's sources, held; without a layout, with
        the sources refitted at each trial distance, in the alternation with the search
        (:func:`_layout_and_camera`). About a minute more on the demo rig.
    truth : callable, optional
        Simulated runs only, given by the caller: ``truth(source, theta) -> intensity``,
        drawn beside the fits in the report (:mod:`processing.report`).

    Raises
    ------
    ProcessingError
        One line naming the file: unreadable, truncated or corrupt, nothing complete,
        bad options, a run the estimate cannot work with.
    """
    started = time.perf_counter()
    try:
        steps = resolve_steps(steps)
    except StepsError as exc:
        raise ProcessingError(f"--steps: {exc}") from None
    if "sources" in steps and estimator not in ESTIMATORS:
        raise ProcessingError(f"--estimator: {estimator!r} is not one of {', '.join(ESTIMATORS)}")
    compute = compute or Compute()
    run_path = Path(run_path)
    timings: dict[str, float] = {}
    sources = None
    if "sources" in steps and layout is not None:
        from processing.sources import SourcesError, load_layout

        try:
            sources = load_layout(layout)
        except SourcesError as exc:
            raise ProcessingError(str(exc)) from None
    with _open_run(run_path) as run:
        try:
            positions = run.completed_positions()
        except RunFileError as exc:
            raise ProcessingError(str(exc)) from None
        if positions.size == 0:
            raise ProcessingError(f"{run_path}: the run has no complete position (no frames to process)")
        out = Path(out_dir) if out_dir is not None else run_path.parent
        out.mkdir(parents=True, exist_ok=True)
        results_file = results_path_for(run_path, out)
        if "hdr" in steps:
            clock = time.perf_counter()
            model = choose_noise(run, positions, noise, compute)
            timings["noise"] = time.perf_counter() - clock
            report = ProcessReport(run_path, results_file, int(positions.size), model, {"exr": [], "png": []})
        else:
            try:
                with Results.open(results_file) as existing:
                    done = existing.hdr_done & run.complete
                    report = ProcessReport(run_path, results_file, int(done.sum()), existing.noise, {})
            except ResultsError:
                raise ProcessingError(f"{results_file}: no HDR results to build on (run --steps hdr first)") from None
            positions = np.flatnonzero(done)
            if positions.size == 0:
                raise ProcessingError(f"{run.path}: no position has both frames and an HDR result")
        if "sources" in steps:
            _report_gain_mismatch(run, report.noise)
        report.n_positions = run.n_positions
        report.partial = positions.size < run.n_positions
        report.compute = compute.description
        # With the layout known, each position is merged and unmixed by one task.
        plan = _plan_sources(run, sources, estimator, ball_centre, positions) if sources is not None else None
        aperture_optional = fit_aperture is None  # the default: fitted where the sources are searched for
        fit_aperture = (sources is None) if fit_aperture is None else fit_aperture
        fused = "hdr" in steps and plan is not None and not fit_aperture and not fit_sensor_distance
        passes = int("hdr" in steps) + int("sources" in steps and not fused)
        tracker = _Progress(progress, passes * int(positions.size))
        rows: dict[int, _SourceRow] = {}
        saturated_all: dict[int, bool] = {}
        if "hdr" in steps:
            clock = time.perf_counter()
            _hdr_pass(
                run,
                run_path,
                out,
                results_file,
                positions,
                method,
                report,
                plan,
                compute,
                tracker,
                rows,
                saturated_all,
                images,
            )
            timings["positions"] = time.perf_counter() - clock
    if "sources" in steps:
        if not fused:
            if plan is None:
                with _open_run(run_path) as run:
                    clock = time.perf_counter()
                    found, report.aperture_fit, report.sensor_distance_fit = _layout_and_camera(
                        run,
                        results_file,
                        positions,
                        ball_centre,
                        compute,
                        fit_aperture,
                        fit_sensor_distance,
                        optional=aperture_optional,
                    )
                    timings["layout"] = time.perf_counter() - clock
                    sources = found.sources
                    report.layout_search = (
                        "candidate grid (NNLS), then positions and radius fitted: "
                        if found.refined
                        else "candidate grid (NNLS) only: "
                    ) + found.message
                    plan = _plan_sources(
                        run,
                        sources,
                        estimator,
                        ball_centre,
                        positions,
                        _fitted_camera(report.aperture_fit, report.sensor_distance_fit),
                    )
            elif fit_aperture or fit_sensor_distance:
                with _open_run(run_path) as run:
                    clock = time.perf_counter()
                    if fit_sensor_distance:  # the sources' places known: held at each trial
                        report.sensor_distance_fit = sensor_distance_from_data(
                            run, results_file, positions, sources, ball_centre, compute, refit=False
                        )
                    if fit_aperture:
                        report.aperture_fit = aperture_from_data(
                            run,
                            results_file,
                            positions,
                            sources,
                            ball_centre,
                            compute,
                            sensor_distance=report.sensor_distance_fit.get("fitted_m"),
                        )
                        _warn_if_unexplained(run, report.aperture_fit)
                    timings["camera"] = time.perf_counter() - clock
                    plan = _plan_sources(
                        run,
                        sources,
                        estimator,
                        ball_centre,
                        positions,
                        _fitted_camera(report.aperture_fit, report.sensor_distance_fit),
                    )
            clock = time.perf_counter()
            work = _PositionWork(str(run_path), str(results_file), None, plan)

            def collect(index, result: PositionResult):
                report.add_task(result)
                rows[index] = result.sources
                saturated_all[index] = result.all_saturated
                tracker.step()

            compute.map_unordered(process_position, [int(i) for i in positions], work, on_result=collect)
            timings["sources"] = time.perf_counter() - clock
        if all(saturated_all.get(int(i), False) for i in positions):
            raise ProcessingError(
                f"{run_path}: every pixel is saturated even in the shortest exposure: take shorter exposures"
            )
        _finish_sources(
            run_path,
            out,
            report,
            plan,
            positions,
            rows,
            fit_method=fit_method,
            units=units,
            truth=truth,
            layout_path=layout,
            timings=timings,
            compute=compute,
        )
    timings["total"] = time.perf_counter() - started
    report.timings = {k: round(v, 3) for k, v in timings.items()}
    report.task_stages = {k: round(v, 3) for k, v in report.task_stages.items()}
    return report


def _hdr_pass(
    run: RunFile,
    run_path: Path,
    out: Path,
    results_file: Path,
    positions,
    method,
    report: ProcessReport,
    plan,
    compute: Compute,
    tracker: _Progress,
    rows: dict,
    saturated_all: dict,
    images: bool,
) -> None:
    """Merge every position (and unmix it, with a plan) on ``compute``; write the results as they come."""
    from drivers.contracts.version import __version__

    folder = out / f"{run_path.stem}.hdr"  # the position files, and the images beside them
    folder.mkdir(exist_ok=True)
    try:
        cfa = run.cfa_pattern(int(positions[0]))[0]
    except RunFileError as exc:
        raise ProcessingError(str(exc)) from None
    hdr = _HDRWork(method, report.noise, cfa, str(folder) if images else None)
    work = _PositionWork(str(run_path), str(results_file), hdr, plan)
    found_images: dict[int, dict[str, Path]] = {}
    with ResultsWriter.create(
        results_file,
        run_id=run.header.run_id,
        run_file=str(run_path),
        n_positions=run.n_positions,
        frame_shape=run.frame_shape,
        software_version=__version__,
        hdr=HDRInfo(method, report.noise, rig_noise(run), cfa),
    ) as writer:

        def write(index: int, result: PositionResult) -> None:
            report.add_task(result)
            writer.commit_position(index, result.saturation_level)
            report.saturated_pixels += result.saturated
            saturated_all[index] = result.all_saturated
            found_images[index] = result.images
            if result.sources is not None:
                rows[index] = result.sources
            tracker.step()

        compute.map_unordered(process_position, [int(i) for i in positions], work, on_result=write)
    for index in sorted(found_images):
        for kind, path in found_images[index].items():
            report.outputs.setdefault(kind, []).append(path)
    if report.saturated_pixels:
        log.warning(
            "%s: %d pixel samples saturated even in the shortest exposure (flagged in the results)",
            run_path,
            report.saturated_pixels,
        )


def _plan_sources(
    run: RunFile, layout, estimator: str, ball_centre, positions, camera: CameraFit | None = None
) -> _SourcesPlan:
    """Check the view and choose the estimator: geometry only, before any position is read."""
    geometry, builder = _geometry(run, ball_centre, camera)
    _check_view(run, geometry, builder, layout, positions)
    middle = int(positions[len(positions) // 2])
    chosen, reason, footprint = choose_estimator(
        geometry, builder, layout, _light_pose(run, geometry, middle), estimator
    )
    log.info("%s: %s", run.path, reason)
    spacing = min((math.dist(a.centre, b.centre) for a in layout for b in layout if a is not b), default=math.inf)
    cell_radius = min(0.5 * spacing, 3.0 * footprint) if math.isfinite(footprint) else 0.5 * spacing
    return _SourcesPlan(
        tuple(layout),
        tuple(ball_centre) if ball_centre is not None else None,
        chosen,
        reason,
        footprint,
        cell_radius,
        camera,
    )


def _finish_sources(
    run_path: Path,
    out: Path,
    report: ProcessReport,
    plan: _SourcesPlan,
    positions,
    rows: dict,
    *,
    fit_method,
    units,
    truth,
    layout_path,
    timings: dict,
    compute: Compute | None = None,
) -> None:
    """Assemble the samples, fit, and write the light model, the light files and the report."""
    from processing.exports import write_ies, write_ldt, write_tm25
    from processing.report import write_report

    samples = _assemble(positions, rows, plan)
    clock = time.perf_counter()
    with _open_run(run_path) as run:
        model = fit_light_model(
            run,
            list(plan.layout),
            samples,
            method=fit_method,
            units=units,
            estimator=plan.estimator,
            footprint=plan.footprint,
        )
    timings["fit"] = time.perf_counter() - clock
    ball_centre = plan.ball_centre
    model.provenance["ball_centre_m"] = list(ball_centre) if ball_centre is not None else "as described by the rig"
    model.provenance["layout"] = (
        str(layout_path) if layout_path is not None else f"found in the data: {report.layout_search}"
    )
    model.provenance["aperture_m"] = _fit_provenance(report.aperture_fit, "--fit-aperture")
    model.provenance["sensor_distance_m"] = _fit_provenance(report.sensor_distance_fit, "--fit-sensor-distance")
    report.light_model = model.save(out / f"{run_path.stem}.light.json")
    stem = out / run_path.stem
    luminaire = f"mirrorgonio run {run_path.stem}"

    def light_files() -> dict[str, list[Path]]:
        started = time.perf_counter()
        files = {
            "ies": [write_ies(model, stem.with_suffix(".ies"), luminaire=luminaire)],
            "ldt": [write_ldt(model, stem.with_suffix(".ldt"), luminaire=luminaire)],
            "tm25": [write_tm25(model, stem.with_suffix(".tm25ray"), n_rays=100_000, seed=0)],
        }
        timings["exports"] = time.perf_counter() - started
        return files

    report.estimator, report.estimator_reason, report.spatial_resolution_m = (
        plan.estimator,
        plan.reason,
        2.0 * plan.footprint,
    )
    report.samples = samples
    report.model = model
    # The light files are written on a thread while the report is drawn (both only read the
    # model): with a cluster this process mostly waits for the workers' sections meanwhile.
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="mirrorgonio-exports") as pool:
        exports = pool.submit(light_files)
        clock = time.perf_counter()
        with _open_run(run_path) as run:  # the report draws the rig's chief rays at the middle position
            drawn = write_report(
                stem.with_suffix(".report.html"),
                model,
                run=run,
                samples=samples,
                report=report,
                truth=truth,
                compute=compute,
            )
        timings["report"] = time.perf_counter() - clock
        report.outputs.update(exports.result())
    report.outputs["report"] = [drawn]


#: Where along the sweep the layout's refinement and the aperture's fit take their positions. The
#: refinement fits every source's centre to five: with three, noise-free data came out 1.4-5.6 µm
#: off and the fits 0.06-0.26 % off the truth; with five, 1.1-3.8 µm and 0.02-0.10 % (the true
#: layout: 0.02-0.17 %), for 5.4 s instead of 3.6.
_FIT_FRACTIONS = (1 / 6, 2 / 6, 3 / 6, 4 / 6, 5 / 6)


def layout_from_data(
    run: RunFile,
    results_file,
    positions=None,
    ball_centre=None,
    compute: Compute | None = None,
    camera: CameraFit | None = None,
):
    """The sources found in the data (``docs/light-model.md``): the candidate grid at three
    positions spread over the sweep (:func:`~processing.sources.lit_box`,
    :func:`~processing.sources.candidate_grid`, :func:`~processing.sources.candidate_strength`,
    each position a task on ``compute``), its local maxima as the first guess, then
    :func:`~processing.sources.refine_layout` at five positions (one task: it needs the
    positions together). A :class:`processing.sources.LayoutFit`."""
    from processing.sources import SourcesError, candidate_grid, seeds_from_strength, sources_from_strength

    if positions is None:
        with Results.open(results_file) as results:
            positions = np.flatnonzero(results.hdr_done & run.complete)
    positions = np.asarray(positions)
    if positions.size == 0:
        raise ProcessingError(f"{run.path}: no position has both frames and an HDR result")
    picks = _spread_over(positions, (0.25, 0.5, 0.75))
    compute = compute or Compute()
    args = (str(run.path), str(results_file), ball_centre, camera)
    boxes: dict[int, tuple | None] = {}
    compute.map_unordered(_layout_box_at, picks, *args, on_result=boxes.__setitem__)
    try:
        candidates, us, vs = candidate_grid([boxes[i] for i in picks])
        strengths: dict[int, np.ndarray] = {}
        compute.map_unordered(_candidate_strength_at, picks, *args, tuple(candidates), on_result=strengths.__setitem__)
        strength = sum(strengths[i] for i in picks)
        first = sources_from_strength(strength, us, vs)
    except SourcesError as exc:
        raise ProcessingError(f"{run.path}: the sources could not be found in the data: {exc}") from None
    spread = _spread_over(positions, _FIT_FRACTIONS)
    refine = (_refined_layout, *args, tuple(spread), first, seeds_from_strength(strength, us, vs))
    fit = compute.submit(*refine).result() if compute.dask else _refined_layout(*refine[1:])
    if not fit.refined:
        log.warning("%s: the layout found in the data is the candidate grid's (%s)", run.path, fit.message)
    log.info("%s: %d sources found in the data at positions %s (%s)", run.path, len(fit.sources), picks, fit.message)
    return fit


#: χ²/pixel of the templates above which the aperture's fit warns. With the description right it
#: was 1.06 on the demo rig (the templates' small model error); with it fitted after the ball was
#: described 0.2 mm off along z, 1.35, and after the other errors of ``bench tolerance``, 1.5-22.
_CHI2_PER_PIXEL_WARNING = 1.2


def aperture_from_data(
    run: RunFile,
    results_file,
    positions,
    layout,
    ball_centre=None,
    compute: Compute | None = None,
    sensor_distance: float | None = None,
) -> dict:
    """The camera's aperture diameter fitted to five merged positions spread over the sweep,
    at the sources of ``layout`` (:func:`processing.sources.fit_aperture`, one task on
    ``compute``; the sensor ``sensor_distance`` behind it, or as the rig says): a dict for
    ``ProcessReport.aperture_fit`` and the light model's provenance."""
    picks = _spread_over(np.asarray(positions), _FIT_FRACTIONS)
    camera = CameraFit(sensor_distance_m=sensor_distance)
    fit = _fit_from_data(
        run, "--fit-aperture", _fitted_aperture, results_file, ball_centre, picks, layout, camera, compute
    )
    log.info(
        "%s: aperture %.4g mm fitted to the data (the rig says %.4g mm; χ²/pixel %.4f, %.4f there)",
        run.path,
        1e3 * fit.diameter_m,
        1e3 * fit.described_m,
        fit.chi2 / fit.pixels,
        fit.chi2_described / fit.pixels,
    )
    return _fit_record(fit, fit.diameter_m, fit.described_m, picks)


def sensor_distance_from_data(
    run: RunFile,
    results_file,
    positions,
    layout,
    ball_centre=None,
    compute: Compute | None = None,
    *,
    aperture: float | None = None,
    refit: bool = True,
) -> dict:
    """The sensor distance fitted to five merged positions spread over the sweep, at the sources
    of ``layout``, refitted at each trial distance with ``refit`` (sources found in the data;
    :func:`processing.sources.fit_sensor_distance`, one task on ``compute``; the aperture
    ``aperture`` across, or as the rig says): a dict for ``ProcessReport.sensor_distance_fit``
    and the light model's provenance."""
    picks = _spread_over(np.asarray(positions), _FIT_FRACTIONS)
    camera = CameraFit(aperture_m=aperture)
    fit = _fit_from_data(
        run,
        "--fit-sensor-distance",
        _fitted_sensor_distance,
        results_file,
        ball_centre,
        picks,
        layout,
        camera,
        compute,
        refit,
    )
    log.info(
        "%s: sensor distance %.3f mm fitted to the data (the rig says %.3f mm; χ²/pixel %.4f, %.4f there)",
        run.path,
        1e3 * fit.sensor_distance_m,
        1e3 * fit.described_m,
        fit.chi2 / fit.pixels,
        fit.chi2_described / fit.pixels,
    )
    return _fit_record(fit, fit.sensor_distance_m, fit.described_m, picks) | {"sources_refitted": fit.sources_refitted}


def _fit_from_data(run: RunFile, option: str, task, results_file, ball_centre, picks, layout, camera, compute, *extra):
    """One of the camera's fits as a task on ``compute``; its failure as one line naming ``option``."""
    from processing.sources import SourcesError

    args = (str(run.path), str(results_file), ball_centre, tuple(picks), tuple(layout), camera, *extra)
    compute = compute or Compute()
    try:
        return compute.submit(task, *args).result() if compute.dask else task(*args)
    except SourcesError as exc:
        raise ProcessingError(f"{run.path}: {option}: {exc}") from None


def _fit_record(fit, fitted_m: float, described_m: float, picks) -> dict:
    return {
        "fitted_m": fitted_m,
        "described_m": described_m,
        "chi2_per_pixel": round(fit.chi2 / fit.pixels, 5),
        "chi2_per_pixel_described": round(fit.chi2_described / fit.pixels, 5),
        "pixels": fit.pixels,
        "positions": [int(i) for i in picks],
        "evaluations": fit.evaluations,
    }


def _warn_if_unexplained(run: RunFile, fitted: dict) -> None:
    """Say so when the templates, with the aperture fitted, still leave the data unexplained."""
    if fitted.get("chi2_per_pixel", 0.0) > _CHI2_PER_PIXEL_WARNING:
        log.warning(
            "%s: with the aperture fitted the templates still explain the data only to χ²/pixel %.3g: other "
            "numbers of the rig description (the ball's place and radius, the sensor distance) may be off "
            "(docs/light-model.md; --fit-sensor-distance fits the last)",
            run.path,
            fitted["chi2_per_pixel"],
        )


def _fitted_aperture(run_path: str, results_file: str, ball_centre, picks, layout, camera: CameraFit):
    """:func:`processing.sources.fit_aperture` on the merged positions ``picks`` (a task)."""
    _prepare_task()
    from processing.sources import fit_aperture

    with _open_run(run_path) as run:
        data, builder, cfa = _layout_data(run, results_file, ball_centre, picks, camera)
        return fit_aperture(data, builder, cfa, list(layout))


def _fitted_sensor_distance(
    run_path: str, results_file: str, ball_centre, picks, layout, camera: CameraFit, refit: bool
):
    """:func:`processing.sources.fit_sensor_distance` on the merged positions ``picks`` (a task)."""
    _prepare_task()
    from processing.sources import fit_sensor_distance

    with _open_run(run_path) as run:
        data, builder, cfa = _layout_data(run, results_file, ball_centre, picks, camera)
        return fit_sensor_distance(data, builder, cfa, list(layout), refit=refit)


def _layout_data(run: RunFile, results_file: str, ball_centre, picks, camera: CameraFit | None = None):
    """The merged positions ``picks`` as the layout fits take them: (data, builder, cfa pattern)."""
    from processing.sources import LayoutData

    geometry, builder = _geometry(run, ball_centre, camera)
    data, cfa = [], "RGGB"
    for index in picks:
        rate, var, usable, cfa = _merged_rates(run, results_file, index)
        data.append(LayoutData(rate, var, usable, _light_pose(run, geometry, index)))
    return data, builder, cfa


def _layout_and_camera(
    run: RunFile,
    results_file,
    positions,
    ball_centre,
    compute: Compute,
    fit_aperture: bool,
    fit_sensor_distance: bool = False,
    *,
    optional: bool = False,
    max_searches: int = 3,
    settle: float = 0.01,
    settle_distance: float = 5e-4,
):
    """The sources found in the data (:func:`layout_from_data`) and the camera's numbers fitted
    at them: the sensor distance with ``fit_sensor_distance`` (:func:`sensor_distance_from_data`,
    the sources refitted at each trial), then the aperture with ``fit_aperture``
    (:func:`aperture_from_data`). Returns (layout fit, aperture record, sensor distance record):
    the records are ``{}`` when not fitted, and give the camera to estimate with
    (:func:`_fitted_camera`).

    A search made with a wrong aperture explains the templates' wrong width with sources that
    are not there (the pinhole described 10 % wide: six sources on the demo rig, 150-730 µm
    off), and the aperture fitted at those is off too (2 %); a wrong sensor distance (0.5 %)
    adds sources as well. So the search is made again with what was fitted, and the fits made
    again at what it finds, until the aperture moves by less than ``settle`` and the distance
    by less than ``settle_distance`` (at most ``max_searches`` searches). From ±10 % on the
    demo rig: the second search found the five sources 21-73 µm off and the aperture 0.4-0.7 %
    off; the third, 27-28 µm and 0.1-0.4 % (fits 0.49-1.12 % of peak; with the description
    right, one search: 20 µm, 0.2 %, 0.61 %).

    ``optional``: an aperture fit that fails (its best at a bound of the search) is logged and
    the last search's sources kept, with the camera they were found with (the aperture's
    record then says ``failed``); otherwise it raises :class:`ProcessingError`.
    """
    camera, aperture_fit, distance_fit = CameraFit(), {}, {}
    for search in range(1, max_searches + 1):
        found = layout_from_data(run, results_file, positions, ball_centre, compute, camera=camera)
        if not (fit_aperture or fit_sensor_distance):
            return found, {}, {}
        new, new_distance_fit = camera, distance_fit
        if fit_sensor_distance:
            new_distance_fit = sensor_distance_from_data(
                run, results_file, positions, found.sources, ball_centre, compute, aperture=camera.aperture_m
            ) | {"searches": search}
            new = replace(new, sensor_distance_m=new_distance_fit["fitted_m"])
        if fit_aperture:
            try:
                attempt = aperture_from_data(
                    run,
                    results_file,
                    positions,
                    found.sources,
                    ball_centre,
                    compute,
                    sensor_distance=new.sensor_distance_m,
                )
            except ProcessingError as exc:
                if not optional:
                    raise
                kept = (
                    "the rig's aperture"
                    if camera.aperture_m is None
                    else f"the aperture fitted before, {1e3 * camera.aperture_m:.4g} mm"
                )
                log.warning("%s (the sources are estimated with %s)", exc, kept)
                return found, dict(aperture_fit, failed=str(exc)), distance_fit
            aperture_fit = attempt | {"searches": search}
            new = replace(new, aperture_m=attempt["fitted_m"])
        distance_fit = new_distance_fit
        moved_aperture = _moved(camera.aperture_m, new.aperture_m, aperture_fit.get("described_m"))
        moved_distance = _moved(camera.sensor_distance_m, new.sensor_distance_m, distance_fit.get("described_m"))
        camera = new
        if moved_aperture < settle and moved_distance < settle_distance:
            break
    else:
        log.warning(
            "%s: the camera's numbers fitted to the data had not settled after %d searches for the sources "
            "(the aperture moved %.2g %%, the sensor distance %.2g %% at the last)",
            run.path,
            max_searches,
            100 * moved_aperture,
            100 * moved_distance,
        )
    if aperture_fit:
        _warn_if_unexplained(run, aperture_fit)  # the last fit's: the searches before it may have left spurious sources
    return found, aperture_fit, distance_fit


def _moved(before: float | None, after: float | None, described: float | None) -> float:
    """How far a fitted number moved, relative (0 when it was not fitted)."""
    if after is None:
        return 0.0
    return abs(after / (before if before is not None else described) - 1.0)


def _fitted_camera(aperture_fit: dict, distance_fit: dict) -> CameraFit:
    """The camera the sources are estimated with: each number its fit's, where it was fitted."""
    return CameraFit(aperture_fit.get("fitted_m"), distance_fit.get("fitted_m"))


def _fit_provenance(fitted: dict, option: str):
    """The light model's ``aperture_m`` or ``sensor_distance_m``: the fit's record, or how the
    rig's number came to be used."""
    if fitted.get("fitted_m") is not None:
        return dict(fitted, how=f"fitted to the data ({option})")
    if fitted.get("failed"):
        return f"as described by the rig (the fit to the data failed: {fitted['failed']})"
    return "as described by the rig"


def _spread_over(positions: np.ndarray, fractions) -> list[int]:
    """The positions at these fractions of the way through ``positions`` (each once, in order)."""
    return sorted({int(positions[int(q * (len(positions) - 1))]) for q in fractions})


def _refined_layout(run_path: str, results_file: str, ball_centre, camera, picks, first, seeds):
    """:func:`processing.sources.refine_layout` on the merged positions ``picks`` (a task)."""
    _prepare_task()
    from processing.sources import refine_layout

    with _open_run(run_path) as run:
        data, builder, cfa = _layout_data(run, results_file, ball_centre, picks, camera)
        return refine_layout(data, builder, cfa, first, seeds)


def _merged_rates(run: RunFile, results_file: str, index: int):
    with Results.open(results_file) as results:
        rate, var, usable = _rates(
            results.radiance(index),
            results.variance(index),
            results.count(index),
            results.saturated(index),
            radiometric_gain(run),
        )
        return rate, var, usable, results.cfa_pattern


def _layout_box_at(index: int, run_path: str, results_file: str, ball_centre, camera):
    """The lit box of one merged position (a task)."""
    _prepare_task()
    from processing.sources import lit_box

    with _open_run(run_path) as run:
        geometry, _ = _geometry(run, ball_centre, camera)
        rate, _, usable, _ = _merged_rates(run, results_file, index)
        return lit_box(rate, usable, _light_pose(run, geometry, index), geometry)


def _candidate_strength_at(index: int, run_path: str, results_file: str, ball_centre, camera, candidates):
    """The candidates' strengths at one merged position (a task)."""
    _prepare_task()
    from processing.sources import candidate_strength

    with _open_run(run_path) as run:
        geometry, builder = _geometry(run, ball_centre, camera)
        rate, var, usable, cfa = _merged_rates(run, results_file, index)
        return candidate_strength(rate, var, usable, _light_pose(run, geometry, index), builder, list(candidates), cfa)


# --- sources and fits (measurement.md steps 2-5) ---------------------------------------------
@dataclass
class SourceSamples:
    """Every source's samples over the run: one row per position."""

    positions: np.ndarray
    theta: np.ndarray  # (n_positions, n_sources)
    phi: np.ndarray
    intensity: np.ndarray  # channel mean
    sigma: np.ndarray
    intensity_rgb: np.ndarray  # (n_positions, n_sources, 3)
    cell_sum: np.ndarray  # (n_positions, n_sources), the fast path on the same data


def _assemble(positions, rows: dict[int, _SourceRow], plan: _SourcesPlan) -> SourceSamples:
    """The per-position rows, in position order, as the samples of every source."""
    n, m = len(positions), len(plan.layout)
    out = SourceSamples(
        positions, *(np.full((n, m), np.nan) for _ in range(4)), np.full((n, m, 3), np.nan), np.full((n, m), np.nan)
    )
    for row, index in enumerate(positions):
        found = rows[int(index)]
        out.theta[row], out.phi[row] = found.theta, found.phi
        out.cell_sum[row] = found.cell_sum
        if plan.estimator == "cell-sums":
            out.intensity[row] = found.cell_sum
            out.sigma[row] = np.nan
        else:
            out.intensity_rgb[row] = found.intensity_rgb
            out.intensity[row] = np.nanmean(found.intensity_rgb, axis=1)
            out.sigma[row] = np.sqrt(np.nansum(found.sigma_rgb**2, axis=1)) / 3.0
    return out


def _light_pose(run: RunFile, geometry, index: int):
    from processing.trace import light_pose_at

    measured = run.measured_pose(index)
    return light_pose_at(geometry, measured if measured is not None else run.header.tool_poses[index])


def choose_estimator(geometry, builder, layout, light_pose, requested: str) -> tuple[str, str, float]:
    """Templates, or cell sums where the blur's footprint on the light plane is smaller
    than the sources' spacing; returns (estimator, reason, footprint radius in metres)."""
    from processing.trace import trace_pixels

    footprint = float("nan")
    for source in layout:
        template = builder.build(source, light_pose)
        if template is None:
            continue
        col, row = template.image_centre
        rays = trace_pixels(geometry, light_pose, np.array([col, col + 1.0, col]), np.array([row, row, row + 1.0]))
        per_pixel = max(
            math.hypot(rays.u[1] - rays.u[0], rays.v[1] - rays.v[0]),
            math.hypot(rays.u[2] - rays.u[0], rays.v[2] - rays.v[0]),
        )
        footprint = per_pixel * template.blur_radius_px
        break
    spacing = min((math.dist(a.centre, b.centre) for a in layout for b in layout if a is not b), default=math.inf)
    if requested != "auto":
        return requested, f"{requested} as requested", footprint
    if not math.isfinite(footprint):
        return "templates", "no source in view to size the footprint", footprint
    size = 2.0 * min(source.radius for source in layout)
    if 2.0 * footprint < spacing and 2.0 * footprint <= 2.0 * size:
        return (
            "cell-sums",
            (
                f"the footprint ({2e3 * footprint:.2f} mm across) is smaller than the sources' spacing "
                f"({1e3 * spacing:.2f} mm) and comparable to their size: flux sums are exact enough"
            ),
            footprint,
        )
    # Measured: even a lone 2 mm LED under a 13 mm footprint is 3 % off with flux sums
    # (each pixel's chief ray misstates the direction its light left in), so a footprint
    # much larger than the emitters also calls for templates.
    return (
        "templates",
        (
            f"the footprint ({2e3 * footprint:.2f} mm across) exceeds the sources' spacing "
            f"({1e3 * spacing:.2f} mm) or size ({1e3 * size:.2f} mm): unmixing with templates"
        ),
        footprint,
    )


def _check_view(run: RunFile, geometry, builder, layout, positions) -> None:
    """Refuse, in one line, a run the estimate cannot work with (from the geometry alone;
    a run saturated everywhere is refused once its positions are merged)."""
    from processing.trace import ball_pixel_box

    if ball_pixel_box(geometry) is None:
        raise ProcessingError(f"{run.path}: the ball is not in the camera's view (check camera.pose and ball.centre_m)")
    seen = any(
        builder.build(source, _light_pose(run, geometry, int(i))) is not None
        for i in positions[:: max(1, len(positions) // 8)]
        for source in layout
    )
    if not seen:
        raise ProcessingError(
            f"{run.path}: the light never reflects into the camera at any position (is it facing the ball?)"
        )


def source_colour(intensity_rgb: np.ndarray) -> tuple[float, float, float]:
    """A source's ``(R, G, B)`` (mean 1) from its per-channel intensities at every position
    (n, 3): each channel's sum over the positions where all three are measured, over the
    channel means' sum, so that the strong samples count most. Grey (1, 1, 1) where the
    channels were not measured apart (cell sums) or sum to nothing.

    The colour is taken as one for all directions: an LED's spectrum shifts little with
    angle next to the intensity's own change, and the samples are too few per direction to
    fit a colour each.
    """
    rgb = np.asarray(intensity_rgb, dtype=float).reshape(-1, 3)
    both = np.all(np.isfinite(rgb), axis=1)
    sums = rgb[both].sum(axis=0)
    if not both.any() or not np.all(sums > 0):
        return (1.0, 1.0, 1.0)
    return tuple(float(c) for c in sums / sums.mean())


def fit_light_model(
    run: RunFile,
    layout,
    samples: SourceSamples,
    *,
    method: str = "gaussian",
    units: str = "relative",
    estimator: str = "",
    footprint: float = float("nan"),
):
    """Fit every source's samples and assemble the light model."""
    from drivers.contracts.version import __version__
    from processing.fit import FitError, Samples, fit_intensity
    from processing.lightmodel import LightModel, SourceModel, samples_table

    sources = []
    for k, source in enumerate(layout):
        ok = np.isfinite(samples.intensity[:, k]) & np.isfinite(samples.theta[:, k])
        sigma = samples.sigma[:, k][ok]
        if not np.all(np.isfinite(sigma) & (sigma > 0)):
            # Cell sums carry no uncertainty: weight by a constant fraction of the peak.
            sigma = np.full(ok.sum(), 0.01 * max(np.nanmax(samples.intensity[:, k]), 1e-30))
        data = Samples(samples.theta[:, k][ok], samples.phi[:, k][ok], samples.intensity[:, k][ok], sigma)
        try:
            fit = fit_intensity(data, method=method)
        except FitError as exc:
            raise ProcessingError(f"{run.path}: source {source.name}: {exc}") from None
        table = samples_table(data, samples.positions[ok], samples.cell_sum[:, k][ok])
        sources.append(
            SourceModel(
                source.name, source.centre, source.radius, fit, table, source_colour(samples.intensity_rgb[:, k])
            )
        )
    provenance = {
        "run_id": run.header.run_id,
        "run_file": str(run.path),
        "rig": run.header.rig.name,
        "software_version": __version__,
        "method": estimator,
        "fit": method,
        "spatial_resolution_m": 2.0 * footprint,
        "gain_e_per_dn": radiometric_gain(run),
        "gain_source": "rig",  # DN/s -> e-/s, as the reflectance step
        # the whole rig, so an object run can check it is lit in the same light frame
        "rig_description": run.header.rig.model_dump(mode="json", exclude_none=True),
    }
    return LightModel(sources, units=units, provenance=provenance)
