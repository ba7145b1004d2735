"""The rig fitted to the data together with the sources found in it (self-calibration).

A lab's rig description is a few tenths of a degree and a millimetre off, and the templates
are so sharp that such an error, left in, ruins the light model: the search explains the
misplaced light with sources that are not there. So the geometry is settled first, and the
sources found again through it:

1. the ball's silhouette on the run's ambient frames (where it has them) moves the camera's
   yaw, pitch and distance onto the ball (:func:`~processing.rig_fit.coarse_correction`): an
   error of ten pixels in the ball's image is beyond any local fit's reach;
2. the sources are searched for through the rig so corrected
   (:func:`~processing.light_run.from_data.layout_from_data`);
3. the rig's numbers and the sources' places are fitted together to five merged positions
   spread over the sweep, with the silhouette, within the rig's tolerances
   (:func:`~processing.rig_fit.fit_rig`; one task);
4. 2 and 3 again through the rig as fitted, until the correction moves by less than its
   uncertainty: a source the first search added to soak up the misfit is gone once the rig
   explains the light.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from drivers.contracts.runfile import FrameCorruptError, RunFile
from processing.calibration import CalibrationError
from processing.light_run.errors import ProcessingError, open_run
from processing.light_run.from_data import FIT_FRACTIONS, BallCentre, layout_data, layout_from_data, spread_over
from processing.light_run.geometry import CameraFit, geometry_and_builder
from processing.light_run.position import prepare_task
from processing.light_run.records import RigCalibration
from processing.parallel import Compute
from processing.rig_fit import (
    FITTED,
    RigCorrection,
    RigFit,
    SilhouetteTerm,
    coarse_correction,
    fit_rig,
    fitted_rig,
    silhouette_term,
)
from processing.rig_fit.correction import bounds
from processing.unmixing.search import LayoutFit
from processing.unmixing.sources import Source, SourcesError

log = logging.getLogger("mirrorgonio.processing")


def layout_and_rig(
    run: RunFile,
    results_file: str | Path,
    positions: ArrayLike,
    ball_centre: BallCentre,
    compute: Compute,
    *,
    max_searches: int = 3,
) -> tuple[LayoutFit, RigCalibration]:
    """The sources found in the data and the rig fitted with them (the module's steps); the
    layout is the last fit's sources, at their places through the rig as fitted.

    Raises
    ------
    ProcessingError
        The sources cannot be found, or the rig's fit fails (one line naming the run). Ambient
        frames that show no ball are said in the log and the calibration's record, and the rig
        is fitted without them.
    """
    positions = np.asarray(positions)
    silhouette, start, limit, frames = _start(run, ball_centre)
    picks = spread_over(positions, FIT_FRACTIONS)
    correction = start
    fit: RigFit | None = None
    for search in range(1, max_searches + 1):
        camera = CameraFit(rig=None if correction.is_null() else correction)
        found = layout_from_data(run, results_file, positions, ball_centre, compute, camera=camera)
        new = _fit_task(run, results_file, ball_centre, picks, found.sources, correction, silhouette, compute)
        settled = fit is not None and _settled(fit, new, limit)
        log.info(
            "%s: the rig fitted through search %d: χ²/pixel %.4f as described, %.4f fitted (%s)",
            run.path,
            search,
            new.chi2_described / new.pixels,
            new.chi2 / new.pixels,
            ", ".join(f"{n.name} {v:+.3g} {n.unit}" for n, v in zip(FITTED, new.correction.values, strict=True)),
        )
        fit, correction = new, new.correction
        if settled:
            break
    assert fit is not None  # max_searches >= 1
    calibration = _calibration(run, fit, start, frames, search, picks, ball_centre)
    layout = LayoutFit(fit.sources, True, f"{found.message}; then fitted with the rig", fit.chi2, fit.pixels)
    return layout, calibration


def rig_at_layout(
    run: RunFile,
    results_file: str | Path,
    positions: ArrayLike,
    layout: Sequence[Source],
    ball_centre: BallCentre,
    compute: Compute,
) -> RigCalibration:
    """The rig fitted to the data at a given ``layout`` (its places and sizes held: a known
    light calibrates the rig), from the silhouette's start where the run has ambient frames.

    Raises
    ------
    ProcessingError
        The rig's fit fails (one line naming the run).
    """
    silhouette, start, _, frames = _start(run, ball_centre)
    picks = spread_over(np.asarray(positions), FIT_FRACTIONS)
    fit = _fit_task(run, results_file, ball_centre, picks, layout, start, silhouette, compute, hold_sources=True)
    return _calibration(run, fit, start, frames, 0, picks, ball_centre)


def _start(run: RunFile, ball_centre: BallCentre) -> tuple[SilhouetteTerm | None, RigCorrection, np.ndarray, str]:
    """The silhouette on the run's ambient frames (None without them, or where they show no
    ball), the coarse correction it gives (none without it), the fit's bounds, and which frames
    the silhouette came from or why there is none."""
    geometry, builder = geometry_and_builder(run, ball_centre)
    limit = bounds(run.header.rig.tolerances, geometry, shape=builder.pupil is not None)
    try:
        silhouette = silhouette_term(run, geometry)
    # A light or its housing before the ball, a dark room, or (--ignore-corrupt; refused before any
    # work without it) a corrupt ambient frame: go on without it.
    except (CalibrationError, FrameCorruptError) as exc:
        why = f"unusable: {exc}"
    else:
        if silhouette is not None:
            return silhouette, coarse_correction(silhouette, geometry, limit), limit, silhouette.frames
        why = "none: the run has no ambient calibration frames"
    log.warning(
        "%s: the ball's silhouette: %s; the rig is fitted to the sweep alone, from the description (an error of "
        "the ball's image beyond a few pixels is out of its reach)",
        run.path,
        why,
    )
    return None, RigCorrection(), limit, why


def _fit_task(
    run: RunFile,
    results_file: str | Path,
    ball_centre: BallCentre,
    picks: Sequence[int],
    layout: Sequence[Source],
    start: RigCorrection,
    silhouette: SilhouetteTerm | None,
    compute: Compute,
    *,
    hold_sources: bool = False,
) -> RigFit:
    """:func:`_fitted_rig` as a task on ``compute``; its failure as one line."""
    task = (_fitted_rig, str(run.path), results_file, ball_centre, tuple(picks), tuple(layout), start, silhouette)
    try:
        if compute.dask:
            return compute.submit(*task, hold_sources).result()
        return _fitted_rig(*task[1:], hold_sources)
    except SourcesError as exc:
        raise ProcessingError(f"{run.path}: the rig's fit: {exc}") from None


def _calibration(
    run: RunFile,
    fit: RigFit,
    start: RigCorrection,
    frames: str,
    searches: int,
    picks: Sequence[int],
    ball_centre: BallCentre,
) -> RigCalibration:
    rig = fitted_rig(run.header.rig, fit.correction, None if ball_centre is None else np.asarray(ball_centre))
    return RigCalibration(fit, start, frames, searches, tuple(int(i) for i in picks), rig)


def _settled(before: RigFit, after: RigFit, limit: np.ndarray) -> bool:
    """The correction moved by less than its statistical 1σ (or a fiftieth of its tolerance) in
    every number."""
    moved = np.abs(after.correction.vector - before.correction.vector)
    return bool(np.all(moved <= np.maximum(np.asarray(after.statistical or after.sigma), 0.02 * limit)))


def _fitted_rig(
    run_path: str,
    results_file: str | Path,
    ball_centre: BallCentre,
    picks: Sequence[int],
    layout: Sequence[Source],
    start: RigCorrection,
    silhouette: SilhouetteTerm | None,
    hold_sources: bool,
) -> RigFit:
    """:func:`processing.rig_fit.fit_rig` on the merged positions ``picks`` (a task)."""
    prepare_task()

    with open_run(run_path) as run:
        data, builder, cfa = layout_data(run, results_file, ball_centre, picks)
        middle = data[len(data) // 2].pose
        axis = middle.rotation @ np.array([0.0, 0.0, 1.0])
        return fit_rig(
            data,
            builder,
            cfa,
            list(layout),
            run.header.rig.tolerances,
            axis,
            silhouette,
            start=RigCorrection.of(start.vector, axis),
            hold_sources=hold_sources,
        )
