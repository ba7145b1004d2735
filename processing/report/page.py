"""The light report's page: its sections drawn here or by the cluster's workers, written as one HTML file."""

from __future__ import annotations

import gc
import html
import logging
import math
import os
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from drivers.contracts.runfile import RunFile
from processing.calibration import BallFit
from processing.lightmodel import LightModel
from processing.parallel import Compute
from processing.report.colour import TITLE as COLOUR_TITLE
from processing.report.colour import colour_section
from processing.report.context import (
    MiddlePosition,
    ReportContext,
    RunReport,
    SampleColumns,
    Truth,
    middle_position,
    report_context,
    trace_middle,
)
from processing.report.markup import FigureEncoder, html_note, write_page
from processing.report.photometry import PHOTOMETRY_TITLE, photometry_section
from processing.report.sections import (
    SECTIONS,
    angles_section,
    calibration_section,
    coverage_section,
    header_table,
    intensity_section,
    layout_section,
    previews_section,
    residuals_section,
)
from processing.report.trust import quality_banner, skipped_note

if TYPE_CHECKING:
    import distributed

log = logging.getLogger("mirrorgonio.processing")


#: The sections drawn from the context alone (the model, the samples and the middle position's chief
#: rays): a cluster's workers can draw them, each in its own process, while this process draws the
#: rest. Drawing is mostly matplotlib's text rendering, Python holding the GIL: threads would not
#: share it out, processes do. Measured on 2 cores, a whole run's page: 0.62 s in one process, of
#: which these five sections 0.5 s (50-150 ms each); 0.37-0.55 s with two workers drawing them.
_REMOTE_SECTIONS: dict[str, Callable[[ReportContext, SampleColumns | None], str]] = {
    SECTIONS[0]: lambda ctx, samples: intensity_section(ctx),
    SECTIONS[1]: lambda ctx, samples: layout_section(ctx),
    SECTIONS[2]: lambda ctx, samples: coverage_section(ctx, samples),
    SECTIONS[3]: lambda ctx, samples: angles_section(ctx),
    SECTIONS[4]: lambda ctx, samples: residuals_section(ctx),
}


#: The remote sections that read the chief rays themselves (the others get the context without them).
_NEEDS_RAYS = frozenset({SECTIONS[3]})


def draw_section(name: str, ctx: ReportContext, samples: SampleColumns | None) -> str:
    """One of :data:`_REMOTE_SECTIONS` drawn here, its figures encoded here: a task a Dask
    worker runs for :func:`write_report`."""
    ctx = replace(ctx, encoder=None)
    return guarded(name, lambda: _REMOTE_SECTIONS[name](ctx, samples))


class _RemoteSections:
    """The sections :func:`write_report` hands to a cluster's workers; each one the workers
    could not draw is drawn here when asked for, with the same result."""

    def __init__(self, compute: Compute | None, samples: SampleColumns | None) -> None:
        self.compute = compute if compute is not None and getattr(compute, "dask", False) else None
        self.samples = samples
        self.futures: dict[str, distributed.Future[str]] = {}

    def start(self, name: str, ctx: ReportContext) -> None:
        if self.compute is None:
            return
        shipped = replace(ctx, encoder=None)
        if name not in _NEEDS_RAYS and ctx.geometry is not None:  # the rays are most of its bytes (~6 MB)
            shipped.geometry = replace(ctx.geometry, rays=None)
        try:
            self.futures[name] = self.compute.submit(draw_section, name, shipped, self.samples)
        except Exception as exc:  # noqa: BLE001 - e.g. a truth callable that does not pickle: draw it here
            log.info("report: %s drawn in this process (%s: %s)", name, type(exc).__name__, exc)

    def result(self, name: str, ctx: ReportContext) -> str:
        future = self.futures.pop(name, None)
        if future is not None:
            try:
                return future.result()
            except Exception as exc:  # noqa: BLE001 - a lost worker, an unpicklable result: draw it here
                log.warning(
                    "report: %s: the worker could not draw it (%s: %s); drawn here", name, type(exc).__name__, exc
                )
        return guarded(name, lambda: _REMOTE_SECTIONS[name](ctx, self.samples))


def write_report(
    path: str | os.PathLike[str],
    model: LightModel,
    *,
    run: RunFile | None = None,
    samples: SampleColumns | None = None,
    report: RunReport | None = None,
    truth: Truth | None = None,
    calibration: BallFit | dict[str, Any] | None = None,
    compute: Compute | None = None,
) -> Path:
    """Write the run's report: one self-contained HTML file.

    Parameters
    ----------
    path : path-like
        The HTML file to write (its folder is created).
    model : LightModel
        The measured light.
    run : RunFile, optional
        The (open) run file: its rig and poses give the chief-ray figure, the pixel's
        footprint and the calibration's sensitivity. Without it those say so.
    samples : SourceSamples, optional
        The pipeline's per-position samples (every position, including those without an
        estimate); without them the model's sample tables are used.
    report : ProcessReport, optional
        The pipeline's report: estimator and its reason, noise model, spatial resolution
        and the HDR previews.
    truth : callable, optional
        ``truth(source, theta) -> intensity`` for a simulated run (see the module's notes).
    calibration : BallFit or dict, optional
        A calibration of the ball's position (:func:`processing.calibration.calibrate_ball`,
        or :func:`~processing.calibration.compare_with_rig`'s dict). Also looked for on
        ``report.calibration``, in ``model.provenance["calibration"]`` and, when the run file
        offers one, in ``run.calibration_image()``; without any the section says
        "no calibration image in this run".
    compute : processing.parallel.Compute, optional
        A Dask cluster (the processing's): its workers draw the sections that need only the
        model and the samples (:data:`_REMOTE_SECTIONS`) while this process draws the others.
        A section a worker cannot draw (the inputs do not pickle, the worker is lost) is drawn
        here instead; the page is the same either way.

    Returns
    -------
    Path
        The file written.
    """
    # The report makes some 10⁵ short-lived objects (matplotlib's artists hold reference cycles), which
    # can set off a full collection: with the process's objects set aside (frozen) it walks only the
    # report's own, instead of everything the processing built (0.1-0.3 s on a whole run's heap).
    # A process that froze objects itself manages its collector: it is left alone.
    freeze = gc.get_freeze_count() == 0
    if freeze:
        gc.freeze()
    try:
        return _write_report(Path(path), model, run, samples, report, truth, calibration, compute)
    finally:
        if freeze:
            gc.unfreeze()


def guarded(title: str, build: Callable[[], str]) -> str:
    """A section's HTML, or a note saying why it could not be drawn (one section's failure never stops the page)."""
    try:
        return build()
    except Exception as exc:  # noqa: BLE001
        log.warning("report: %s: %s", title, exc, exc_info=True)
        return html_note(f"this section could not be drawn: {type(exc).__name__}: {exc}")


def _write_report(
    path: Path,
    model: LightModel,
    run: RunFile | None,
    samples: SampleColumns | None,
    report: RunReport | None,
    truth: Truth | None,
    calibration: BallFit | dict[str, Any] | None,
    compute: Compute | None = None,
) -> Path:
    resolution = float(model.provenance.get("spatial_resolution_m") or float("nan"))
    if not math.isfinite(resolution) and report is not None:
        resolution = float(getattr(report, "spatial_resolution_m", float("nan")))
    ctx = report_context(model, samples=samples, truth=truth, resolution_m=resolution)

    def traced(step: Callable[[], MiddlePosition]) -> MiddlePosition | None:
        try:
            return step()
        except Exception as exc:  # a figure never stops the processing
            log.warning("report: chief rays at the middle position: %s", exc, exc_info=True)
            ctx.geometry_note = f"the chief rays could not be traced: {exc}"
            return None

    intensity, layout, coverage, angles, residuals, calibrated, previews = SECTIONS
    # The workers start on the sections that need no chief rays while this process traces them;
    # those that need them follow the trace. This process's worker thread meanwhile takes the
    # calibration and the previews.
    elsewhere = _RemoteSections(compute, samples)
    for name in (intensity, residuals, coverage):
        elsewhere.start(name, ctx)
    position = None
    if run is None:
        ctx.geometry_note = "no run file given to the report: the rig and the poses are unknown"
    else:
        position = traced(lambda: middle_position(run, samples))
    # One worker thread takes what runs mostly in C, outside the GIL, while this thread draws: the
    # calibration's sensitivity (numpy on large arrays: it overlaps the trace below), the previews'
    # decoding and the figures' PNG encoding (OpenCV, ISA-L). Its tasks run in the order given.
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="mirrorgonio-report") as pool:
        ctx.encoder = FigureEncoder(pool)
        built: dict[str, str | Future[str]] = {
            calibrated: pool.submit(
                guarded, calibrated, lambda: calibration_section(model, run, report, calibration, position)
            ),
            previews: pool.submit(guarded, previews, lambda: previews_section(report, run, model, path, position)),
        }
        if position is not None:
            ctx.geometry = traced(lambda: trace_middle(position, model))
        for name in (angles, layout):
            elsewhere.start(name, ctx)
        photometry = guarded(PHOTOMETRY_TITLE, lambda: photometry_section(model, ctx.encoder))
        for name in (intensity, residuals, coverage, angles, layout):  # drawn here if not by a worker
            built[name] = elsewhere.result(name, ctx)
        run_id = model.provenance.get("run_id") or (run.header.run_id if run is not None else "")
        title = f"mirrorgonio light report: {run_id}" if run_id else "mirrorgonio light report"
        body = [
            f"<h1>{html.escape(title)}</h1>",
            quality_banner(model),
            skipped_note(model),
            header_table(model, run, report, samples, resolution),  # the run, the time: above the sections
            f"<h2>{html.escape(PHOTOMETRY_TITLE)}</h2>\n{ctx.encoder.fill(photometry)}",
        ]
        colour = guarded(COLOUR_TITLE, lambda: colour_section(model, ctx.encoder))
        for name in SECTIONS:
            entry = built[name]
            content = entry.result() if isinstance(entry, Future) else entry
            body.append(f"<h2>{html.escape(name)}</h2>\n{ctx.encoder.fill(content)}")
            if name == intensity:
                body.append(f"<h2>{html.escape(COLOUR_TITLE)}</h2>\n{ctx.encoder.fill(colour)}")
    return write_page(path, title, body)
