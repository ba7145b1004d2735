"""The work of one position, in a Dask worker or in this process: merge, write, unmix."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numba
import numpy as np

from drivers.contracts.rig import PoseSpec
from drivers.contracts.runfile import RunFile, RunFileError
from drivers.contracts.version import __version__
from processing.hdr.brackets import merge_raw
from processing.hdr.model import HDRError, NoiseModel
from processing.hdr.mosaic import superpixels
from processing.hdr.noise import estimate_noise
from processing.images import tonemap, write_exr, write_png
from processing.light_run.errors import ProcessingError, open_run
from processing.light_run.geometry import CameraFit, geometry_and_builder
from processing.parallel import in_dask_worker, tune_malloc
from processing.radiometry import ElectronRates, position_masks, radiometric_gain
from processing.report.drawing import warm_up_drawing
from processing.results import (
    Results,
    ResultsError,
    encode_hdr,
    position_file_for,
    stored_variance,
    write_position_file,
)
from processing.trace import light_pose_at_position, specular_points
from processing.unmixing.cell_flux import cell_sums
from processing.unmixing.psf import convex_coverage
from processing.unmixing.sources import Source
from processing.unmixing.unmix import unmix_position

log = logging.getLogger("mirrorgonio.processing")


def prepare_task() -> None:
    """What every task does first: keep freed arrays in the heap (``tune_malloc``) and, in a
    Dask worker, run the numerical kernels on the task's thread alone.

    The workers are the parallelism: numba's parallel kernels would start a thread per core
    in every worker, oversubscribing the cores (on 2 of them the noise estimates take up to
    four times as long). ``numba.set_num_threads`` holds for the calling thread only, so each task sets it
    on the thread it runs on. Without Dask, the kernels keep every core.
    """
    tune_malloc()
    if in_dask_worker():
        numba.set_num_threads(1)


def warm_up_worker() -> None:
    """Ready a worker process for position tasks: import the processing modules and load
    the compiled kernels from numba's cache, on tiny inputs.

    A fresh worker otherwise pays this (about a second, and matplotlib's import and fonts
    for the report's sections) in the first tasks of its first run;
    :func:`processing.parallel.open_compute` runs it on every worker it starts, as a part of
    starting the cluster.
    """

    prepare_task()
    rng = np.random.default_rng(0)
    frames = rng.integers(64, 4000, (2, 8, 8)).astype(np.uint16)
    merged = merge_raw(frames, [1e-3, 4e-3], 64, 4095, NoiseModel(5.0, 0.6))
    position_masks(merged.radiance, stored_variance(merged.variance), merged.count, merged.saturated)
    tonemap(superpixels(merged.radiance, "RGGB"))
    encode_hdr(merged)
    try:
        estimate_noise(frames, [1e-3, 4e-3], 64, white_level=4095)
    except HDRError:
        pass  # too few pixels for an estimate: the kernels ran all the same
    specular_points(np.array([[0.0, 0.05, 0.1]]), np.array([[0.0, 0.0, 0.2]]), np.zeros(3), 0.0254)
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    convex_coverage(square, np.linspace(-0.5, 1.5, 5), np.linspace(-0.5, 1.5, 5), 0.5)
    warm_up_drawing()  # the workers draw report sections at the end of a run


@dataclass(frozen=True)
class HDRWork:
    method: str
    noise: NoiseModel
    cfa: str
    images_dir: str | None


@dataclass(frozen=True)
class SourcesPlan:
    """What every position's source estimate needs, decided once per run."""

    layout: tuple[Source, ...]
    ball_centre: tuple[float, ...] | None
    estimator: str  # chosen: "templates" or "cell-sums"
    reason: str
    footprint: float
    cell_radius: float
    camera: CameraFit | None = None  # fitted to the data; None: as the rig describes it


@dataclass(frozen=True)
class PositionWork:
    run_path: str
    results_path: str
    hdr: HDRWork | None  # None: read the merged position from the results file
    sources: SourcesPlan | None


@dataclass
class SourceRow:
    theta: np.ndarray
    phi: np.ndarray
    intensity_rgb: np.ndarray  # (n_sources, 3)
    sigma_rgb: np.ndarray
    cell_sum: np.ndarray  # (n_sources,)
    chi2: float = 0.0  # the templates' weighted χ² over the pixels fitted
    dof: float = 0.0  # those pixels less the sources, over the channels
    signal: float = 0.0  # Σ (template model / σ)² over those pixels: what a relative model error scales with


@dataclass
class PositionResult:
    """What one position task returns: when it merged, the saturation level of the merge it
    wrote to its position file (the data stay there: only this process's caller commits
    them), and its source samples."""

    index: int
    saturation_level: np.ndarray | None = None
    images: dict[str, Path] = field(default_factory=dict)
    saturated: int = 0
    saturated_share: float = 0.0  # of the position's pixels
    sources: SourceRow | None = None
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


def process_position(index: int, work: PositionWork) -> PositionResult:
    """Merge and/or estimate one position; opens the run (and results) file by path.

    A module-level function so that Dask workers import it. Domain errors come back as
    :class:`ProcessingError` naming the file and the position.
    """
    started = time.perf_counter()
    prepare_task()
    out = PositionResult(index)
    clock = _StageClock(out.stages)
    with open_run(work.run_path) as run:
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
                    header = exr_header(run, index, exposures, h)
                    out.images = _write_images(Path(h.images_dir), index, merged.radiance, h.cfa, header)
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
        usable, lit, n_saturated = position_masks(radiance, variance, count, np.asarray(saturated, bool))
        out.saturated = n_saturated
        out.saturated_share = n_saturated / max(saturated.size, 1)
        if work.sources is not None:
            # The estimates read windows and a few hundred pixels: convert only those to e⁻/s.
            rate, var = ElectronRates(radiance, gain), ElectronRates(variance, gain, gain)
            clock.lap("masks")
            out.sources = _estimate_at(run, work.sources, index, rate, var, usable, lit, cfa)
            clock.lap("sources")
    out.seconds = time.perf_counter() - started
    return out


#: What an EXR's pixels are (its ``units`` and ``colourSpace`` attributes).
EXR_UNITS = (
    "relative radiance: DN per second above black (raw sensor counts a second, linear in the light); "
    "x gainElectronsPerDN for electrons per second; 0 where no exposure gave a usable sample"
)
EXR_COLOUR_SPACE = (
    "camera RGB: the sensor's raw R, G, B (a 2x2 Bayer superpixel, the two greens averaged), not white-balanced. "
    "Its primaries are not known, so the file has no chromaticities attribute: a reader that assumes Rec. 709 "
    "primaries without one shows camera RGB as if it were Rec. 709"
)


def exr_header(run: RunFile, index: int, exposures: np.ndarray, hdr: HDRWork) -> dict[str, Any]:
    """The header attributes of position ``index``'s OpenEXR: what the pixels are (units,
    colour space), how they were merged (the bracket's exposures, the method, the noise
    model), and where they come from (the run, the position, the light's and the arm's
    poses, the software)."""
    light = PoseSpec.of(run.header.light_poses[index])
    measured = run.measured_pose(index)
    attributes: dict[str, Any] = {
        "units": EXR_UNITS,
        "colourSpace": EXR_COLOUR_SPACE,
        "gainElectronsPerDN": float(hdr.noise.gain_e_per_dn),
        "bracketExposures_s": np.asarray(exposures, np.float32),
        "hdrMethod": f"{hdr.method}: the bracket's {len(exposures)} exposures merged into one rate (per second)",
        "runId": run.header.run_id,
        "position": int(index),
        "positionsInRun": int(run.n_positions),
        "lightPosition_m": np.asarray(light.position_m, np.float32),
        "lightRotation_deg": np.asarray(light.rotation_deg, np.float32),
        "software": f"mirrorgonio {__version__}",
        "comments": f"Position {index} (0-based) of {run.n_positions} of run {run.header.run_id}, merged by "
        f"mirrorgonio {__version__}; pixels: {EXR_UNITS.split(':')[0]}, camera RGB",
    }
    if measured is not None:
        arm = PoseSpec.of(measured)
        attributes["toolPositionMeasured_m"] = np.asarray(arm.position_m, np.float32)
        attributes["toolRotationMeasured_deg"] = np.asarray(arm.rotation_deg, np.float32)
    return attributes


def _write_images(
    folder: Path, index: int, radiance: np.ndarray, cfa: str, header: dict[str, Any] | None = None
) -> dict[str, Path]:
    rgb = superpixels(radiance, cfa, nonfinite=0.0)
    return {
        "exr": write_exr(folder / f"position-{index:03d}.exr", rgb, attributes=header),
        "png": write_png(folder / f"position-{index:03d}.png", rgb),
    }


def _estimate_at(
    run: RunFile,
    plan: SourcesPlan,
    index: int,
    rate: ElectronRates,
    variance: ElectronRates,
    usable: np.ndarray,
    lit: np.ndarray,
    cfa: str,
) -> SourceRow:
    """Every source's intensity at one position: templates unmixed, and the cell sums over
    the ``lit`` pixels."""

    geometry, builder = geometry_and_builder(run, plan.ball_centre, plan.camera)
    layout = list(plan.layout)
    pose = light_pose_at_position(run, geometry, index)
    estimate = unmix_position(index, rate, variance, usable, cfa, builder, layout, pose)
    sums = cell_sums(
        rate, lit, geometry, run.header.rig.camera.sensitivity_e_per_s, layout, pose, plan.cell_radius, cfa
    ).mean(axis=1)
    return SourceRow(
        estimate.theta,
        estimate.phi,
        estimate.intensity,
        estimate.sigma,
        sums,
        estimate.chi2,
        float(estimate.dof.sum()),
        float(estimate.signal.sum()),
    )
