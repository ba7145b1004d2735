"""The offline processing of one run file, step by step, position by position.

Steps (``--steps``): ``hdr`` — merge each position's bracket (``processing.hdr``) and
write the results file, an OpenEXR and a PNG preview per position. Later steps (trace,
fit) build on the results file.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from acquisition.runfile import RunFile, RunFileError
from processing.hdr import HDRError, NoiseModel, estimate_noise, merge_raw, superpixels
from processing.images import write_exr, write_png
from processing.results import HDRInfo, ResultsWriter, results_path_for

log = logging.getLogger("mirrorgonio.processing")
STEPS = ("hdr", "sources")
ESTIMATORS = ("auto", "templates", "cell-sums")


class ProcessingError(ValueError):
    """A run that cannot be processed (one line naming the file and the cause)."""


@dataclass
class ProcessReport:
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
    spatial_resolution_m: float = float("nan")


def rig_noise(run: RunFile) -> NoiseModel:
    cam = run.header.rig.camera
    return NoiseModel(cam.gain_e_per_dn, cam.read_noise_e / cam.gain_e_per_dn, source="rig")


def choose_noise(run: RunFile, positions: np.ndarray, mode: str) -> NoiseModel:
    """The noise model: the rig's figures, or estimated from the brackets (median over a
    few positions), falling back to the rig's with the reason logged."""
    from_rig = rig_noise(run)
    if mode == "rig":
        return from_rig
    sample = positions[np.linspace(0, len(positions) - 1, min(5, len(positions))).astype(int)]
    estimates = []
    for index in sample:
        index = int(index)
        if len(run.exposures(index)) < 2:
            continue
        try:
            estimates.append(estimate_noise(run.frames(index), run.exposures(index), run.black_level(index)[0],
                                            white_level=int(run.white_level(index)[0])))  # fmt: skip
        except HDRError as exc:
            log.info("position %d: %s", index, exc)
    if not estimates:
        if mode == "estimated":
            raise ProcessingError(f"{run.path}: the noise model cannot be estimated from these brackets")
        log.warning("%s: noise model from the rig: the brackets did not allow an estimate", run.path)
        return from_rig
    gain = float(np.median([e.gain_e_per_dn for e in estimates]))
    read = float(np.median([e.read_noise_dn for e in estimates]))
    return NoiseModel(gain, read, source="estimated")


def process_run(run_path, out_dir=None, *, steps=("hdr",), method: str = "optimal", noise: str = "auto",
                progress: Callable[[int, int], None] | None = None, layout=None, estimator: str = "auto",
                fit_method: str = "gaussian", units: str = "relative", truth=None, ball_centre=None) -> ProcessReport:  # fmt: skip
    """Process one run file; results go beside it, or into ``out_dir``.

    ``truth`` (simulated runs only, given by the caller): ``truth(source, theta) -> intensity``,
    drawn beside the fits in the report (:mod:`processing.report`)."""
    unknown = [s for s in steps if s not in STEPS]
    if unknown:
        raise ProcessingError(f"--steps: unknown step {unknown[0]!r} (known: {', '.join(STEPS)})")
    run_path = Path(run_path)
    try:
        run = RunFile.open(run_path)
    except RunFileError as exc:
        raise ProcessingError(str(exc)) from None
    with run:
        positions = run.completed_positions()
        if positions.size == 0:
            raise ProcessingError(f"{run_path}: the run has no complete position (no frames to process)")
        out = Path(out_dir) if out_dir is not None else run_path.parent
        out.mkdir(parents=True, exist_ok=True)
        results_file = results_path_for(run_path, out)
        if "hdr" in steps:
            report = _hdr_step(run, run_path, out, results_file, positions, method, noise, progress)
        elif results_file.exists():
            from processing.results import Results

            with Results.open(results_file) as existing:
                report = ProcessReport(run_path, results_file, int(existing.hdr_done.sum()), existing.noise, {})
        else:
            raise ProcessingError(f"{results_file}: no HDR results to build on (run --steps hdr first)")
    if "sources" in steps:
        _sources_step(run_path, results_file, out, report, layout=layout, estimator=estimator,
                      fit_method=fit_method, units=units, truth=truth, ball_centre=ball_centre)  # fmt: skip
    return report


def layout_from_data(run: RunFile, results, ball_centre=None) -> list:
    """The sources found in the data (``processing.sources.find_layout``) at three
    positions spread over the sweep."""
    from processing.sources import SourcesError, TemplateBuilder, find_layout
    from processing.trace import RigGeometry

    rig = run.header.rig
    geometry = RigGeometry.from_rig(rig, ball_centre=ball_centre)
    builder = TemplateBuilder(geometry, rig.camera.sensitivity_e_per_s)
    positions = np.flatnonzero(results.hdr_done & run.complete)
    if positions.size == 0:
        raise ProcessingError(f"{run.path}: no position has both frames and an HDR result")
    picks = sorted({int(positions[int(q * (len(positions) - 1))]) for q in (0.25, 0.5, 0.75)})
    gain = results.noise.gain_e_per_dn
    rates, variances, usable, poses = [], [], [], []
    for index in picks:
        rate = results.radiance(index).astype(np.float64) * gain
        rates.append(rate)
        variances.append(results.variance(index).astype(np.float64) * gain * gain)
        usable.append(~results.saturated(index) & (results.count(index) > 0) & np.isfinite(rate))
        poses.append(_light_pose(run, geometry, index))
    try:
        found = find_layout(rates, usable, variances, poses, builder, results.cfa_pattern)
    except SourcesError as exc:
        raise ProcessingError(f"{run.path}: the sources could not be found in the data: {exc}") from None
    log.info("%s: %d sources found in the data at positions %s", run.path, len(found), picks)
    return found


def _hdr_step(run: RunFile, run_path: Path, out: Path, results_file: Path, positions, method, noise, progress):
    from acquisition import __version__

    images = out / f"{run_path.stem}.hdr"
    images.mkdir(exist_ok=True)
    model = choose_noise(run, positions, noise)
    cfa = run.cfa_pattern(int(positions[0]))[0]
    report = ProcessReport(run_path, results_file, int(positions.size), model, {"exr": [], "png": []})
    with ResultsWriter.create(results_file, run_id=run.header.run_id, run_file=str(run_path),
                              n_positions=run.n_positions, frame_shape=run.frame_shape,
                              software_version=__version__,
                              hdr=HDRInfo(method, model, rig_noise(run), cfa)) as writer:  # fmt: skip
        for done, index in enumerate(positions, start=1):
            index = int(index)
            try:
                merged = merge_raw(run.frames(index), run.exposures(index), run.black_level(index)[0],
                                   int(run.white_level(index)[0]), model, method=method)  # fmt: skip
            except HDRError as exc:
                raise ProcessingError(f"{run_path}: position {index}: {exc}") from None
            writer.write_hdr(index, merged)
            report.saturated_pixels += int(merged.saturated.sum())
            rgb = superpixels(np.where(np.isfinite(merged.radiance), merged.radiance, 0.0), cfa)
            report.outputs["exr"].append(write_exr(images / f"position-{index:03d}.exr", rgb))
            report.outputs["png"].append(write_png(images / f"position-{index:03d}.png", rgb))
            if progress:
                progress(done, int(positions.size))
    if report.saturated_pixels:
        log.warning("%s: %d pixel samples saturated even in the shortest exposure (flagged in the results)",
                    run_path, report.saturated_pixels)  # fmt: skip
    return report


def _sources_step(run_path: Path, results_file: Path, out: Path, report: ProcessReport, *, layout, estimator,
                  fit_method, units, truth=None, ball_centre=None) -> None:  # fmt: skip
    from processing.report import write_report
    from processing.results import Results
    from processing.sources import SourcesError, load_layout

    if estimator not in ESTIMATORS:
        raise ProcessingError(f"--estimator: {estimator!r} is not one of {', '.join(ESTIMATORS)}")
    with RunFile.open(run_path) as run, Results.open(results_file) as results:
        if layout is not None:
            try:
                sources = load_layout(layout)
            except SourcesError as exc:
                raise ProcessingError(str(exc)) from None
        else:
            sources = layout_from_data(run, results, ball_centre)
        samples, chosen, reason, footprint = estimate_sources(run, results, sources, estimator=estimator,
                                                              ball_centre=ball_centre)  # fmt: skip
        model = fit_light_model(run, sources, samples, method=fit_method, units=units, estimator=chosen,
                                footprint=footprint)  # fmt: skip
    model.provenance["ball_centre_m"] = list(ball_centre) if ball_centre is not None else "as described by the rig"
    model.provenance["layout"] = str(layout) if layout is not None else "found in the data (grid of candidates, NNLS)"
    report.light_model = model.save(out / f"{run_path.stem}.light.json")
    from processing.exports import write_ies, write_ldt, write_tm25

    stem = out / run_path.stem
    report.outputs["ies"] = [write_ies(model, stem.with_suffix(".ies"), luminaire=f"mirrorgonio run {run_path.stem}")]
    report.outputs["ldt"] = [write_ldt(model, stem.with_suffix(".ldt"), luminaire=f"mirrorgonio run {run_path.stem}")]
    report.outputs["tm25"] = [write_tm25(model, stem.with_suffix(".tm25ray"), n_rays=100_000, seed=0)]
    report.estimator, report.estimator_reason, report.spatial_resolution_m = chosen, reason, 2.0 * footprint
    report.samples = samples
    report.model = model
    with RunFile.open(run_path) as run:  # the report draws the rig's chief rays at the middle position
        report.outputs["report"] = [write_report(stem.with_suffix(".report.html"), model, run=run, samples=samples,
                                                 report=report, truth=truth)]  # fmt: skip


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
        per_pixel = max(math.hypot(rays.u[1] - rays.u[0], rays.v[1] - rays.v[0]),
                        math.hypot(rays.u[2] - rays.u[0], rays.v[2] - rays.v[0]))  # fmt: skip
        footprint = per_pixel * template.blur_radius_px
        break
    spacing = min((math.dist(a.centre, b.centre) for a in layout for b in layout if a is not b), default=math.inf)
    if requested != "auto":
        return requested, f"{requested} as requested", footprint
    if not math.isfinite(footprint):
        return "templates", "no source in view to size the footprint", footprint
    size = 2.0 * min(source.radius for source in layout)
    if 2.0 * footprint < spacing and 2.0 * footprint <= 2.0 * size:
        return "cell-sums", (f"the footprint ({2e3 * footprint:.2f} mm across) is smaller than the sources' spacing "
                             f"({1e3 * spacing:.2f} mm) and comparable to their size: flux sums are exact enough"), footprint  # fmt: skip
    # Measured: even a lone 2 mm LED under a 13 mm footprint is 3 % off with flux sums
    # (each pixel's chief ray misstates the direction its light left in), so a footprint
    # much larger than the emitters also calls for templates.
    return "templates", (f"the footprint ({2e3 * footprint:.2f} mm across) exceeds the sources' spacing "
                         f"({1e3 * spacing:.2f} mm) or size ({1e3 * size:.2f} mm): unmixing with templates"), footprint  # fmt: skip


def _check_view(run: RunFile, results, geometry, builder, layout, positions) -> None:
    """Refuse, in one line, a run the estimate cannot work with."""
    from processing.trace import ball_pixel_grid

    cols, rows = ball_pixel_grid(geometry)
    if cols.size == 0:
        raise ProcessingError(f"{run.path}: the ball is not in the camera's view (check camera.pose and ball.centre_m)")
    if all(results.saturated(int(i)).all() for i in positions):
        raise ProcessingError(f"{run.path}: every pixel is saturated even in the shortest exposure: take shorter exposures")
    seen = any(builder.build(source, _light_pose(run, geometry, int(i))) is not None
               for i in positions[:: max(1, len(positions) // 8)] for source in layout)  # fmt: skip
    if not seen:
        raise ProcessingError(f"{run.path}: the light never reflects into the camera at any position "
                              "(is it facing the ball?)")  # fmt: skip


def estimate_sources(run: RunFile, results, layout, *, estimator: str = "auto", progress=None, ball_centre=None):
    """Per-source samples of radiant intensity at every complete position."""
    from processing.sources import TemplateBuilder, cell_sums, unmix_position
    from processing.trace import RigGeometry

    rig = run.header.rig
    geometry = RigGeometry.from_rig(rig, ball_centre=ball_centre)
    builder = TemplateBuilder(geometry, rig.camera.sensitivity_e_per_s)
    positions = np.flatnonzero(results.hdr_done & run.complete)
    if positions.size == 0:
        raise ProcessingError(f"{run.path}: no position has both frames and an HDR result")
    _check_view(run, results, geometry, builder, layout, positions)
    middle = int(positions[len(positions) // 2])
    chosen, reason, footprint = choose_estimator(geometry, builder, layout, _light_pose(run, geometry, middle), estimator)
    log.info("%s: %s", run.path, reason)
    gain = results.noise.gain_e_per_dn
    spacing = min((math.dist(a.centre, b.centre) for a in layout for b in layout if a is not b), default=math.inf)
    cell_radius = min(0.5 * spacing, 3.0 * footprint) if math.isfinite(footprint) else 0.5 * spacing
    n, m = len(positions), len(layout)
    out = SourceSamples(positions, *(np.full((n, m), np.nan) for _ in range(4)), np.full((n, m, 3), np.nan),
                        np.full((n, m), np.nan))  # fmt: skip
    for row, index in enumerate(positions):
        index = int(index)
        pose = _light_pose(run, geometry, index)
        radiance = results.radiance(index).astype(np.float64) * gain
        variance = results.variance(index).astype(np.float64) * gain * gain
        usable = ~results.saturated(index) & (results.count(index) > 0) & np.isfinite(radiance)
        estimate = unmix_position(index, radiance, variance, usable, results.cfa_pattern, builder, layout, pose)
        out.theta[row], out.phi[row] = estimate.theta, estimate.phi
        lit = usable & (radiance > 3.0 * np.sqrt(np.where(np.isfinite(variance), variance, np.inf)))
        sums = cell_sums(radiance, lit, geometry, rig.camera.sensitivity_e_per_s, layout, pose, cell_radius,
                         results.cfa_pattern).mean(axis=1)  # fmt: skip
        out.cell_sum[row] = sums
        if chosen == "cell-sums":
            out.intensity[row] = sums
            out.sigma[row] = np.nan
        else:
            out.intensity_rgb[row] = estimate.intensity
            out.intensity[row] = np.nanmean(estimate.intensity, axis=1)
            out.sigma[row] = np.sqrt(np.nansum(estimate.sigma**2, axis=1)) / 3.0
        if progress:
            progress(row + 1, n)
    return out, chosen, reason, footprint


def fit_light_model(run: RunFile, layout, samples: SourceSamples, *, method: str = "gaussian", units: str = "relative",
                    estimator: str = "", footprint: float = float("nan")):  # fmt: skip
    """Fit every source's samples and assemble the light model."""
    from acquisition import __version__
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
        sources.append(SourceModel(source.name, source.centre, source.radius, fit, table))
    provenance = {"run_id": run.header.run_id, "run_file": str(run.path), "rig": run.header.rig.name,
                  "software_version": __version__, "method": estimator, "fit": method,
                  "spatial_resolution_m": 2.0 * footprint}  # fmt: skip
    return LightModel(sources, units=units, provenance=provenance)
