"""What a light run writes at its end: the light model, the IES, LDT and TM-25 files, the report."""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drivers.contracts.photometric import PhotometricCalibration
from drivers.contracts.rig import rig_to_toml_dict, write_rig
from drivers.contracts.runfile import CorruptFrame, RunFile
from drivers.contracts.version import __version__
from processing.calibration.photometric import absolute_photometry, luminous_model
from processing.exports.ies import write_ies
from processing.exports.ldt import write_ldt
from processing.exports.pbrt import write_pbrt_lights
from processing.exports.tm25 import write_tm25
from processing.light_run.from_data import FIT_FRACTIONS, spread_over
from processing.light_run.light_fit import fit_light_model
from processing.light_run.output_guard import output_path
from processing.light_run.position import SourceRow, SourcesPlan
from processing.light_run.progress import Steps
from processing.light_run.quality import judge
from processing.light_run.records import ProcessReport, RigCalibration, camera_provenance
from processing.light_run.samples import assemble_samples
from processing.lightmodel import LightModel
from processing.options import ProcessingOptions
from processing.parallel import Compute
from processing.photometry import summarize
from processing.report.context import Truth
from processing.report.page import write_report
from processing.results import run_name

log = logging.getLogger("mirrorgonio.processing")


@dataclass
class SourcesToFinish:
    """What :func:`finish_sources` writes from: the run, the estimate, and where and how.

    Attributes
    ----------
    run : RunFile
        The run, open (the light model's fit and the report read its header and poses).
    out : Path
        The folder the outputs go to.
    options : ProcessingOptions
        What the processing was asked.
    report : ProcessReport
        The processing's report, completed here (the model, the samples, the outputs).
    sources : SourcesPlan
        The sources and the camera the positions were estimated with.
    positions : ndarray of int
        The positions estimated, and ``rows`` each one's estimate.
    timings : dict
        The stages' seconds, added to here (``fit``, ``photometry``, ``exports``, ``report``).
    steps : Steps
        Told as ``fits``, ``exports`` and ``report`` start and end.
    compute : Compute, optional
        Where the report's sections are drawn (default: here).
    truth : callable, optional
        The simulated truth, drawn beside the fits in the report.
    photometric : tuple, optional
        The camera's photometric calibration and where it was read: the model is then also
        in candela and lumens (``photometry.absolute``), and so are the light files.
    """

    run: RunFile
    out: Path
    options: ProcessingOptions
    report: ProcessReport
    sources: SourcesPlan
    positions: np.ndarray
    rows: dict[int, SourceRow]
    timings: dict[str, float]
    steps: Steps
    compute: Compute | None = None
    truth: Truth | None = None
    photometric: tuple[PhotometricCalibration, str] | None = None


def finish_sources(done: SourcesToFinish) -> None:
    """Assemble the samples, fit, and write the light model, the light files and the report
    (the steps ``fits``, ``exports`` and ``report`` said to ``done.steps`` as they start and end)."""
    run, out, options, report = done.run, done.out, done.options, done.report
    plan, timings, steps = done.sources, done.timings, done.steps
    run_path = run.path
    samples = assemble_samples(done.positions, done.rows, plan)
    steps.start("fits")
    clock = time.perf_counter()
    model = fit_light_model(
        run,
        list(plan.layout),
        samples,
        method=options.fit_method,
        units=options.units,
        estimator=plan.estimator,
        footprint=plan.footprint,
    )
    timings["fit"] = time.perf_counter() - clock
    steps.end("fits")
    name = run_name(run_path)
    record_provenance(model, report, plan, options, out / name, done.positions, done.rows)
    clock = time.perf_counter()
    model.photometry = summarize(model, options.extrapolation).record()
    if done.photometric is not None:
        calibration, origin = done.photometric
        model.photometry["absolute"] = absolute_photometry(
            model, calibration, run.header.camera_colour, run.header.rig.camera, origin
        )
    timings["photometry"] = time.perf_counter() - clock
    report.light_model = model.save(output_path(run_path, out, ".light.json"))

    def light_files() -> dict[str, list[Path]]:
        started = time.perf_counter()
        files = write_light_files(model, run_path, out, options)
        timings["exports"] = time.perf_counter() - started
        steps.end("exports")
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
        steps.start("exports")
        exports = pool.submit(light_files)
        steps.start("report")
        clock = time.perf_counter()
        drawn = write_report(  # the report draws the rig's chief rays at the middle position
            output_path(run_path, out, ".report.html"),
            model,
            run=run,
            samples=samples,
            report=report,
            truth=done.truth,
            compute=done.compute,
        )
        timings["report"] = time.perf_counter() - clock
        steps.end("report")
        report.outputs.update(exports.result())
    report.outputs["report"] = [drawn]


def write_light_files(
    model: LightModel, run_path: Path, out: Path, options: ProcessingOptions
) -> dict[str, list[Path]]:
    """The IES, LDT, TM-25 and pbrt-v4 files of ``model``, with the names, the lamp flux or calibration
    and the ray count of ``options`` (the luminaire named after the run where none is given)."""
    luminaire = options.luminaire or f"mirrorgonio run {run_name(run_path)}"
    absolute = model.photometry.get("absolute")
    calibration = options.candela_per_unit
    if absolute is not None:  # each source weighed by its own luminance, one scale for all
        model, calibration = luminous_model(model, absolute), absolute["reference_candela_per_unit"]
    photometric: dict[str, Any] = {  # what the IES and the LDT say alike
        "lamp_lumens": options.lamp_lumens,
        "calibration": calibration,
        "luminaire": luminaire,
        "lamp": options.lamp,
        "extrapolation": options.extrapolation,
    }
    ies = write_ies(
        model, output_path(run_path, out, ".ies"), manufacturer=options.manufacturer or "unknown", **photometric
    )
    ldt = write_ldt(
        model, output_path(run_path, out, ".ldt"), company=options.manufacturer or "mirrorgonio", **photometric
    )
    tm25 = write_tm25(
        model,
        output_path(run_path, out, ".tm25ray"),
        n_rays=options.rays,
        seed=0,
        name=options.luminaire,
        manufacturer=options.manufacturer or "unknown",
        calibration=calibration,
        lamp_lumens=options.lamp_lumens,
    )
    pbrt = write_pbrt_lights(
        model,
        output_path(run_path, out, ".pbrt") / "light.pbrt",
        calibration=calibration,
        extrapolation=options.extrapolation,
    )
    return {"ies": [ies], "ldt": [ldt], "tm25": [tm25], "pbrt": pbrt}


def record_provenance(
    model: LightModel,
    report: ProcessReport,
    plan: SourcesPlan,
    options: ProcessingOptions,
    stem: Path,
    positions: np.ndarray,
    rows: dict[int, SourceRow],
) -> None:
    """How the light model came to be, in its provenance (the ball's centre, the layout, the
    camera's numbers, the self-calibration), and the verdict on it (``quality``)."""
    ball_centre = plan.ball_centre
    model.provenance["ball_centre_m"] = list(ball_centre) if ball_centre is not None else "as described by the rig"
    model.provenance["layout"] = (
        str(options.layout) if options.layout is not None else f"found in the data: {report.layout_search}"
    )
    model.provenance["aperture_m"] = camera_provenance(report.aperture_fit, "--fit-aperture")
    model.provenance["sensor_distance_m"] = camera_provenance(report.sensor_distance_fit, "--fit-sensor-distance")
    if report.point_spread is not None:
        model.provenance["point_spread"] = report.point_spread
    if report.point_spread_refinement is not None:
        model.provenance["point_spread_refinement"] = report.point_spread_refinement
    if report.skipped_corrupt:  # --ignore-corrupt: the frames the run file failed to give back
        model.provenance["skipped_corrupt"] = skipped_record(report.skipped_corrupt)
    if report.rig_calibration is not None:
        report.outputs["rig"] = [record_calibration(model.provenance, report.rig_calibration, stem)]
    calibration = report.rig_calibration
    if calibration is not None:
        fit_positions: list[int] | None = list(calibration.positions)
    else:  # the layout search's refinement, where the sources were searched for
        fit_positions = spread_over(positions, FIT_FRACTIONS) if options.layout is None else None
    report.quality = judge(rows, calibration, fit_positions)
    model.quality = report.quality.record()
    refinement = report.point_spread_refinement
    if refinement is not None and refinement.get("needed"):  # the check says what the refinement changed
        model.quality["point_spread_refined"] = refinement["message"]
    if not report.quality.ok:
        log.warning("%s: %s", report.run_file, report.quality.line())


def skipped_record(corrupt: list[CorruptFrame]) -> dict[str, list]:
    """The frames ``--ignore-corrupt`` skipped, as the light model's ``skipped_corrupt`` holds them:
    the positions left out, and each frame (``where``, ``position``, ``frame``, ``exposure_s``,
    ``cause``)."""
    return {
        "positions": sorted({frame.position for frame in corrupt if frame.position is not None}),
        "frames": [frame.record() for frame in corrupt],
    }


def record_calibration(provenance: dict, calibration: RigCalibration, stem: Path) -> Path:
    """The self-calibration in the light model's provenance (``rig_calibration``; the rig as
    fitted becomes its ``rig_description``, the one described ``rig_described``), and the rig
    as fitted written beside it (``RUN.rig-fitted.toml``, a rig file the daemon and later
    processing can take). The rig file's path."""
    provenance["rig_described"] = provenance["rig_description"]
    provenance["rig_description"] = rig_to_toml_dict(calibration.rig)
    provenance["rig_calibration"] = calibration.record()
    if calibration.rig.camera.thin_lens is None:
        provenance["aperture_m"] = calibration.camera_record("pinhole")
    provenance["sensor_distance_m"] = calibration.camera_record("sensor_distance")
    note = (
        f"The rig of run {stem.name} as fitted to its data by mirrorgonio {__version__} (self-calibration):\n"
        + "\n".join(f"  {line}" for line in calibration.summary())
    )
    return write_rig(calibration.rig, stem.with_name(f"{stem.name}.rig-fitted.toml"), note)  # output_path's name
