"""One run file processed: what is given and what is fitted decided once, then straight passes.

:func:`process_run` checks its options (:class:`~processing.options.ProcessingOptions`),
makes the plan (:func:`~processing.light_run.plan.plan_processing`) and hands both to a
:class:`LightRun`, whose passes are:

1. the merge (``hdr``): every position's bracket merged into the results file; with the
   layout given and nothing to fit first, the same task also unmixes the position (one
   pass in all);
2. the sources settled (``sources``): searched for in the data at a few merged positions,
   and the camera's numbers fitted there as the plan says;
3. the estimate: every merged position unmixed with the settled sources and camera;
4. the fits, the light model, the light files and the report.

Each step says how far it is through ``progress`` (:mod:`processing.light_run.progress`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, Final

import numpy as np

from drivers.contracts.photometric import PhotometricCalibration
from drivers.contracts.rig import RigError, load_rig
from drivers.contracts.runfile import CorruptFrame, RunFile, RunFileError
from drivers.contracts.version import __version__
from processing.light_run.checksums import sound_positions
from processing.light_run.errors import ProcessingError, open_run
from processing.light_run.from_data import camera_at_layout, fitted_camera, layout_and_camera
from processing.light_run.geometry import CameraFit, measured_point_spread
from processing.light_run.noise import choose_noise, report_gain_mismatch
from processing.light_run.output_guard import check_outputs, output_path
from processing.light_run.outputs import SourcesToFinish, finish_sources
from processing.light_run.plan import FRESNEL_MISMATCH_WARNING, RIG_FIT_MIN_POSITIONS, ProcessingPlan, plan_processing
from processing.light_run.point_spread import TOO_FEW, point_spread_from_data, refinement_positions
from processing.light_run.position import (
    HDRWork,
    PositionResult,
    PositionWork,
    SourceRow,
    SourcesPlan,
    process_position,
)
from processing.light_run.progress import Steps
from processing.light_run.records import ProcessReport
from processing.light_run.samples import plan_sources
from processing.light_run.self_calibration import layout_and_rig, rig_at_layout
from processing.options import ProcessingOptions
from processing.parallel import Compute
from processing.radiometry import rig_noise
from processing.report.context import Truth
from processing.results import HDRInfo, Results, ResultsError, ResultsWriter, results_path_for
from processing.steps import Step
from processing.trace import RigGeometry
from processing.unmixing.measured import PointSpreadError, virtual_image_distance
from processing.unmixing.point_spread_fit import PointSpreadRefinement
from processing.unmixing.sources import Source

log = logging.getLogger("mirrorgonio.processing")

#: The share of a position's pixels saturated in every exposure above which the run is refused.
SATURATED_RUN_SHARE = 0.99


def process_run(
    run_path: str | os.PathLike[str],
    out_dir: str | os.PathLike[str] | None,
    options: ProcessingOptions,
    *,
    compute: Compute | None = None,
    progress: Callable[..., None] | None = None,
    truth: Truth | None = None,
) -> ProcessReport:
    """Process one run file; results go beside it, or into ``out_dir``.

    Parameters
    ----------
    run_path : path-like
        The run file; a run still being written is processed up to its last complete
        position. It is opened once here, for the whole processing (the position tasks open
        it themselves, wherever they run).
    out_dir : path-like or None
        Folder for the results (None: the run's folder).
    options : ProcessingOptions
        What is asked (:meth:`~processing.options.ProcessingOptions.checked` makes them from
        names): ``steps``, ``method``, ``noise``, ``layout`` (a TOML file; without one the
        sources are searched for in the data), ``estimator``, ``fit_method``, ``units``,
        ``ball_centre``, ``images``, ``fit_aperture`` (``auto``: fitted where the sources are
        searched for, the rig's diameter kept if that fit fails; ``always``: fitted with a
        layout too, a failed fit fails the processing), ``fit_sensor_distance`` (``never`` by
        default; it takes minutes), ``calibrate_rig`` and the light files' names.
    compute : Compute, optional
        Where the position tasks run (:func:`processing.parallel.open_compute`); default:
        in this process, one after the other.
    progress : callable, optional
        ``progress(step, done, total)`` as each step starts (``done = 0``), after every
        position of the steps over the positions (``hdr``, ``estimate``) and as the others
        end; ``step`` is a name of :data:`processing.light_run.progress.STEPS`, in their
        order. A callable of two parameters is called ``progress(done, total)`` after every
        position task, counted over the passes.
    truth : callable, optional
        Simulated runs only, given by the caller: ``truth(source, theta) -> intensity``,
        drawn beside the fits in the report (:mod:`processing.report`).

    Raises
    ------
    ProcessingError
        One line naming the file or the option, before any work for a bad option: an
        unreadable, truncated or corrupt run, nothing complete, a run the estimate cannot
        work with.
    """
    with open_run(run_path) as run:
        return LightRun(run, out_dir, options, compute or Compute(), progress, truth).process()


class LightRun:
    """One run's processing under a plan: its state between the passes, and the passes.

    The run file is opened by the caller and read through ``run`` alone; the plan is made
    here, once, from the options and the run's header (the measured point spread, read and
    checked before any work).
    """

    def __init__(
        self,
        run: RunFile,
        out_dir: str | os.PathLike[str] | None,
        options: ProcessingOptions,
        compute: Compute,
        progress: Callable[..., None] | None,
        truth: Truth | None,
    ) -> None:
        self.run, self.run_path, self.options, self.compute, self.truth = run, run.path, options, compute, truth
        self.out = Path(out_dir) if out_dir is not None else self.run_path.parent
        self.results_file = results_path_for(self.run_path, self.out)
        self.steps = Steps(progress)
        self.timings: dict[str, float] = {}
        self.rows: dict[int, SourceRow] = {}
        self.saturated_share: dict[int, float] = {}
        self.step, self.step_done = "hdr", 0  # the pass over the positions under way, and its positions done
        # The measured point spread's record, where there is one: it leaves no aperture to fit.
        self.point_spread: dict[str, Any] | None = self._point_spread() if Step.SOURCES in options.steps else None
        self.photometric = self._photometric_calibration() if Step.SOURCES in options.steps else None
        self.plan: Final[ProcessingPlan] = plan_processing(options, point_spread_measured=self.point_spread is not None)
        # The positions to process and the report's count and noise model: _start's, before any pass.
        self.positions: np.ndarray = np.empty(0, dtype=np.intp)
        outputs: dict[str, list[Path]] = {"exr": [], "png": []} if self.plan.merge else {}
        self.report = ProcessReport(self.run_path, self.results_file, 0, rig_noise(run), outputs)

    def process(self) -> ProcessReport:
        started = time.perf_counter()
        sources = None
        check_outputs(self.run_path, self.run.header.run_id, self.out, self.options.overwrite)
        self._start()
        if self.plan.fused:  # with the layout known, each position is merged and unmixed by one task
            assert self.plan.layout is not None  # fused: the layout is given
            sources = plan_sources(
                self.run, self.plan.layout, self.options.estimator, self.options.ball_centre, self.positions
            )
        if self.plan.merge:
            with self._timed("positions"):
                self._positions_step("hdr")
                self._merge_pass(sources)
            if not self.plan.fused:
                self._refuse_if_saturated()
        if self.plan.estimate:
            if not self.plan.fused:
                sources = self._settle_sources()
                with self._timed("sources"):
                    self._positions_step("estimate")
                    self._estimate_pass(sources)
            self._refuse_if_saturated()
            assert sources is not None  # made for the fused merge, or settled above
            finish_sources(
                SourcesToFinish(
                    self.run,
                    self.out,
                    self.options,
                    self.report,
                    sources,
                    self.positions,
                    self.rows,
                    self.timings,
                    self.steps,
                    compute=self.compute,
                    truth=self.truth,
                    photometric=self.photometric,
                )
            )
        self.timings["total"] = time.perf_counter() - started
        self.report.timings = {k: round(v, 3) for k, v in self.timings.items()}
        self.report.task_stages = {k: round(v, 3) for k, v in self.report.task_stages.items()}
        return self.report

    # --- the passes -------------------------------------------------------------------------------
    def _refuse_if_saturated(self) -> None:
        """One line where every position's frames are saturated even in the shortest exposure:
        nearly every pixel, since the rings of a Fresnel point spread leave a few of the light's
        image below full well however bright it is."""
        if self.saturated_share and all(
            self.saturated_share.get(int(i), 0.0) >= SATURATED_RUN_SHARE for i in self.positions
        ):
            raise ProcessingError(
                f"{self.run_path}: the frames are saturated even in the shortest exposure "
                f"({100 * SATURATED_RUN_SHARE:.0f} % of the pixels or more at every position): take shorter exposures"
            )

    def _start(self) -> None:
        """The positions to process and the report, with the merge's noise model."""
        run = self.run
        try:
            positions = run.completed_positions()
        except RunFileError as exc:
            raise ProcessingError(str(exc)) from None
        if positions.size == 0:
            raise ProcessingError(f"{self.run_path}: the run has no complete position (no frames to process)")
        with self._step("checksums"):  # the frames to merge; merged before, only the ambient ones
            sound, skipped = self._sound_positions(positions if self.plan.merge else positions[:0])
        self.out.mkdir(parents=True, exist_ok=True)
        if self.plan.merge:
            positions = sound
            with self._step("noise"):
                self.report.noise = choose_noise(run, positions, self.options.noise, self.compute)
            self.report.positions = int(positions.size)
        else:
            positions = self._merged_before()
        self.report.skipped_corrupt = skipped
        if self.plan.estimate:
            report_gain_mismatch(run, self.report.noise)
        self.positions = positions
        if self.plan.long_sweep.calibrate_rig and not self.plan.camera(int(positions.size)).calibrate_rig:
            log.info(
                "%s: %d merged positions: the rig is held as described (the self-calibration needs %d)",
                self.run_path,
                positions.size,
                RIG_FIT_MIN_POSITIONS,
            )
        self.report.n_positions = run.n_positions
        self.report.point_spread = self.point_spread
        self.report.partial = positions.size < run.n_positions
        self.report.compute = self.compute.description
        self.steps.positions_total = self.plan.passes * int(positions.size)

    def _photometric_calibration(self) -> tuple[PhotometricCalibration, str] | None:
        """The camera's photometric scale and where it was read, checked before any work: the
        ``photometric_calibration`` option's rig file, else the run's own rig; None where the
        light files get another scale or neither holds one."""
        options = self.options
        if options.lamp_lumens is not None or options.candela_per_unit is not None:
            return None
        path = options.photometric_calibration
        if path is None:
            own = self.run.header.rig.camera.photometric
            return None if own is None else (own, "the run's rig, [camera.photometric]")
        try:
            calibration = load_rig(path).camera.photometric
        except RigError as exc:
            raise ProcessingError(f"--photometric-calibration: {exc}") from None
        if calibration is None:
            raise ProcessingError(
                f"--photometric-calibration: {path}: no [camera.photometric] in it (mirrorgonio "
                "calibrate-photometry writes one)"
            )
        return calibration, f"{path}, [camera.photometric]"

    def _point_spread(self) -> dict[str, Any] | None:
        """The measured point spread the rig names, read and checked before any work: its record
        (with the Fresnel number's mismatch to this run), or None where the rig has none."""
        rig = self.run.header.rig
        try:
            measured = measured_point_spread(rig)
        except PointSpreadError as exc:
            raise ProcessingError(str(exc)) from None
        if measured is None:
            return None
        geometry = RigGeometry.from_rig(rig)
        poses = rig.light_poses()
        light = poses[len(poses) // 2].position
        needed = virtual_image_distance(
            float(np.linalg.norm(geometry.camera_centre - geometry.ball_centre)),
            float(np.linalg.norm(light - geometry.ball_centre)),
            float(geometry.ball_radius),
        )
        z2 = float(geometry.sensor_distance)
        mismatch = (1.0 / measured.distance_m + 1.0 / z2) / (1.0 / needed + 1.0 / z2) - 1.0
        if abs(mismatch) > FRESNEL_MISMATCH_WARNING:
            log.warning(
                "%s: the point spread was measured with the LED %.0f mm in front of the pinhole, where the "
                "light's image lies %.0f mm: its Fresnel number is %+.1f %% off (place the LED there)",
                self.run_path,
                1e3 * measured.distance_m,
                1e3 * needed,
                100 * mismatch,
            )
        return {**measured.record(), "virtual_image_m": needed, "fresnel_number_mismatch": mismatch}

    def _sound_positions(self, positions: np.ndarray) -> tuple[np.ndarray, list[CorruptFrame]]:
        """Every frame the processing will read (the positions', the ambient calibration sets')
        read through its checksum, before any work (:func:`~processing.light_run.checksums.sound_positions`):
        the positions to process and the frames skipped. A corrupt ambient set is left out of the
        self-calibration."""
        ambient = [pair for pair in self.run.calibration_sets() if pair[0] == "ambient"]
        return sound_positions(self.run, self.run_path, positions, ambient, self.options.ignore_corrupt)

    def _merged_before(self) -> np.ndarray:
        """The positions an earlier ``hdr`` step merged (the report's count and noise model from its results)."""
        try:
            with Results.open(self.results_file) as existing:
                done = existing.hdr_done & self.run.complete
                self.report.positions, self.report.noise = int(done.sum()), existing.noise
        except ResultsError:
            raise ProcessingError(f"{self.results_file}: no HDR results to build on (run --steps hdr first)") from None
        positions = np.flatnonzero(done)
        if positions.size == 0:
            raise ProcessingError(f"{self.run_path}: no position has both frames and an HDR result")
        return positions

    def _merge_pass(self, sources: SourcesPlan | None) -> None:
        """Merge every position (and unmix it, with ``sources``) on the cluster; write the
        results as they come."""
        run = self.run
        folder = output_path(self.run_path, self.out, ".hdr")  # the position files, and the images beside them
        folder.mkdir(exist_ok=True)
        try:
            cfa = run.cfa_pattern(int(self.positions[0]))[0]
        except RunFileError as exc:
            raise ProcessingError(str(exc)) from None
        noise, method = self.report.noise, str(self.options.method)  # a plain str: HDF5 attributes take no enum
        hdr = HDRWork(method, noise, cfa, str(folder) if self.options.images else None)
        work = PositionWork(str(self.run_path), str(self.results_file), hdr, sources)
        images: dict[int, dict[str, Path]] = {}
        with ResultsWriter.create(
            self.results_file,
            run_id=run.header.run_id,
            run_file=str(self.run_path),
            n_positions=run.n_positions,
            frame_shape=run.frame_shape,
            software_version=__version__,
            hdr=HDRInfo(method, noise, rig_noise(run), cfa),
        ) as writer:

            def write(index: int, result: PositionResult) -> None:
                writer.commit_position(index, result.saturation_level)
                self.report.saturated_pixels += result.saturated
                images[index] = result.images
                self._collect(index, result)

            self.compute.map_unordered(process_position, self._indices(), work, on_result=write)
        for index in sorted(images):
            for kind, path in images[index].items():
                self.report.outputs.setdefault(kind, []).append(path)
        if self.report.saturated_pixels:
            log.warning(
                "%s: %d pixel samples saturated even in the shortest exposure (flagged in the results)",
                self.run_path,
                self.report.saturated_pixels,
            )

    def _settle_sources(self) -> SourcesPlan:
        """The sources to estimate with (given, or searched for) and the camera as the plan fits it."""
        plan, options, args = self.plan, self.options, (self.run, self.results_file, self.positions)
        fits = plan.camera(int(self.positions.size))
        if fits.calibrate_rig:
            return self._calibrated_sources()
        if plan.search:
            with self._step("layout"):
                found, aperture, distance = layout_and_camera(*args, options.ball_centre, self.compute, fits)
            layout: Sequence[Source] = found.sources
            how = (
                "candidate grid (NNLS), then positions and radius fitted: "
                if found.refined
                else "candidate grid (NNLS) only: "
            )
            self.report.layout_search = how + found.message
        else:
            assert plan.layout is not None  # given, where the plan does not search for it
            layout = plan.layout
            aperture = distance = None
            if fits.fit_aperture or fits.fit_sensor_distance:
                with self._step("camera"):
                    aperture, distance = camera_at_layout(*args, layout, options.ball_centre, self.compute, fits)
        self.report.aperture_fit, self.report.sensor_distance_fit = aperture, distance
        camera = self._refined_point_spread(layout, fitted_camera(aperture, distance))
        return plan_sources(self.run, layout, options.estimator, options.ball_centre, self.positions, camera)

    def _calibrated_sources(self) -> SourcesPlan:
        """The sources (searched for, or given) with the rig fitted to the data with them."""
        plan, options, args = self.plan, self.options, (self.run, self.results_file, self.positions)
        with self._step("calibration", timing="layout"):
            if plan.search:
                found, calibration = layout_and_rig(*args, options.ball_centre, self.compute)
                self.report.layout_search = f"candidate grid (NNLS), then positions and radius fitted: {found.message}"
                layout: Sequence[Source] = found.sources
            else:
                assert plan.layout is not None  # given, where the plan does not search for it
                layout = plan.layout
                calibration = rig_at_layout(*args, layout, options.ball_centre, self.compute)
        self.report.rig_calibration = calibration
        camera = self._refined_point_spread(layout, CameraFit(rig=calibration.correction))
        return plan_sources(self.run, layout, options.estimator, options.ball_centre, self.positions, camera)

    def _refined_point_spread(self, layout: Sequence[Source], camera: CameraFit) -> CameraFit:
        """``camera`` with the point spread refined from the sweep, where the plan asks for it and
        the held-out positions support it (:mod:`processing.light_run.point_spread`)."""
        if self.plan.point_spread == "never":
            return camera
        if refinement_positions(self.positions) is None:  # a short sweep: said, but no step to show
            too_few = PointSpreadRefinement(None, False, TOO_FEW.format(self.positions.size))
            self.report.point_spread_refinement = too_few.record()
            return camera
        with self._step("point-spread"):
            refinement = point_spread_from_data(
                self.run,
                self.results_file,
                self.positions,
                layout,
                self.options.ball_centre,
                self.compute,
                camera,
                force=self.plan.point_spread == "always",
            )
        self.report.point_spread_refinement = refinement.record()
        log.info("%s: point spread from the sweep: %s", self.run_path, refinement.message)
        return camera if refinement.correction is None else replace(camera, point_spread=refinement.correction)

    def _estimate_pass(self, sources: SourcesPlan) -> None:
        """Unmix every merged position with ``sources`` (read back from the results file)."""
        work = PositionWork(str(self.run_path), str(self.results_file), None, sources)
        self.compute.map_unordered(process_position, self._indices(), work, on_result=self._collect)

    # --- bookkeeping ------------------------------------------------------------------------------
    def _collect(self, index: int, result: PositionResult) -> None:
        self.report.add_task(result)
        self.saturated_share[index] = result.saturated_share
        if result.sources is not None:
            self.rows[index] = result.sources
        self.step_done += 1
        self.steps.advance(self.step, self.step_done, int(self.positions.size))

    def _positions_step(self, step: str) -> None:
        """A pass over the positions begins: ``step`` counts them."""
        self.step, self.step_done = step, 0
        self.steps.start(step, int(self.positions.size))

    def _indices(self) -> list[int]:
        return [int(i) for i in self.positions]

    def _timed(self, stage: str) -> _Stage:
        return _Stage(self.timings, stage)

    @contextlib.contextmanager
    def _step(self, step: str, timing: str | None = None) -> Iterator[None]:
        """A step done in one go: reported as it starts and ends, its time in ``timings``
        (under ``timing``, default the step's name)."""
        self.steps.start(step)
        with self._timed(timing or step):
            yield
        self.steps.end(step)


class _Stage:
    """Adds the wall time of a ``with`` block to ``timings[stage]``."""

    def __init__(self, timings: dict[str, float], stage: str) -> None:
        self.timings, self.stage = timings, stage

    def __enter__(self) -> None:
        self.started = time.perf_counter()

    def __exit__(self, *exc: object) -> None:
        self.timings[self.stage] = self.timings.get(self.stage, 0.0) + time.perf_counter() - self.started
