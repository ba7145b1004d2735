"""The sources and the camera's numbers found in the merged positions, each a task on the cluster."""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import replace
from functools import partial
from typing import TypeVar, cast

import numpy as np
from numpy.typing import ArrayLike

from drivers.contracts.runfile import RunFile
from processing.light_run.errors import ProcessingError, open_run
from processing.light_run.geometry import CameraFit, geometry_and_builder
from processing.light_run.plan import CameraFits
from processing.light_run.position import prepare_task
from processing.light_run.records import FittedNumber
from processing.parallel import Compute
from processing.radiometry import electron_rates, radiometric_gain
from processing.results import Results
from processing.trace import light_pose_at, light_pose_at_position
from processing.unmixing.camera_fit import ApertureFit, SensorDistanceFit, fit_aperture, fit_sensor_distance
from processing.unmixing.problem import LayoutData
from processing.unmixing.search import (
    LayoutFit,
    candidate_grid,
    candidate_strength,
    lit_box,
    refine_layout,
    seeds_from_strength,
    sources_from_strength,
)
from processing.unmixing.sources import Source, SourcesError
from processing.unmixing.templates import TemplateBuilder

log = logging.getLogger("mirrorgonio.processing")

#: A file's path as the functions here take it.
PathArg = str | os.PathLike[str]
#: The ball's centre in the rig frame (metres), or None where the rig description's stands.
BallCentre = Sequence[float] | np.ndarray | None

_Fit = TypeVar("_Fit", ApertureFit, SensorDistanceFit)


#: Where along the sweep the layout's refinement and the camera's fits take their positions. Five:
#: fitted to three, the centres of noise-free data come out 1.4-5.6 µm off and the fits 0.06-0.26 %
#: off the truth; to five, 1.1-3.8 µm and 0.02-0.10 % (as with the true layout), in 1.5 times the time.
FIT_FRACTIONS = (1 / 6, 2 / 6, 3 / 6, 4 / 6, 5 / 6)


def layout_from_data(
    run: RunFile,
    results_file: PathArg,
    positions: ArrayLike | None = None,
    ball_centre: BallCentre = None,
    compute: Compute | None = None,
    camera: CameraFit | None = None,
) -> LayoutFit:
    """The sources found in the data (``docs/light-model.md``): the candidate grid at three
    positions spread over the sweep (:func:`~processing.unmixing.search.lit_box`,
    :func:`~processing.unmixing.search.candidate_grid`, :func:`~processing.unmixing.search.candidate_strength`,
    each position a task on ``compute``), its local maxima as the first guess, then
    :func:`~processing.unmixing.search.refine_layout` at five positions (one task: it needs the
    positions together). A :class:`processing.unmixing.search.LayoutFit`."""

    if positions is None:
        with Results.open(results_file) as results:
            positions = np.flatnonzero(results.hdr_done & run.complete)
    positions = np.asarray(positions)
    if positions.size == 0:
        raise ProcessingError(f"{run.path}: no position has both frames and an HDR result")
    picks = spread_over(positions, (0.25, 0.5, 0.75))
    compute = compute or Compute()
    args = (str(run.path), str(results_file), ball_centre, camera)
    boxes: dict[int, tuple[float, float, float, float] | None] = {}
    compute.map_unordered(_layout_box_at, picks, *args, on_result=boxes.__setitem__)
    try:
        candidates, us, vs = candidate_grid([boxes[i] for i in picks])
        strengths: dict[int, np.ndarray] = {}
        compute.map_unordered(_candidate_strength_at, picks, *args, tuple(candidates), on_result=strengths.__setitem__)
        strength = cast(np.ndarray, sum(strengths[i] for i in picks))  # picks is not empty
        first = sources_from_strength(strength, us, vs)
    except SourcesError as exc:
        raise ProcessingError(f"{run.path}: the sources could not be found in the data: {exc}") from None
    spread = spread_over(positions, FIT_FRACTIONS)
    refine = (_refined_layout, *args, tuple(spread), first, seeds_from_strength(strength, us, vs))
    fit = compute.submit(*refine).result() if compute.dask else _refined_layout(*refine[1:])
    if not fit.refined:
        log.warning("%s: the layout found in the data is the candidate grid's (%s)", run.path, fit.message)
    log.info("%s: %d sources found in the data at positions %s (%s)", run.path, len(fit.sources), picks, fit.message)
    return fit


#: χ²/pixel of the templates above which the aperture's fit warns. With the description right it
#: is 1.06 on the demo rig (the templates' small model error); with the ball described 0.2 mm off
#: along z, 1.35 after the fit, and with the other errors of ``bench tolerance``, 1.5-22.
CHI2_PER_PIXEL_WARNING = 1.2


def aperture_from_data(
    run: RunFile,
    results_file: PathArg,
    positions: ArrayLike,
    layout: Sequence[Source],
    ball_centre: BallCentre = None,
    compute: Compute | None = None,
    sensor_distance: float | None = None,
) -> FittedNumber:
    """The camera's aperture diameter fitted to five merged positions spread over the sweep,
    at the sources of ``layout`` (:func:`processing.unmixing.camera_fit.fit_aperture`, one task on
    ``compute``; the sensor ``sensor_distance`` behind it, or as the rig says)."""
    picks = spread_over(np.asarray(positions), FIT_FRACTIONS)
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
    return _fitted_number(fit, fit.diameter_m, fit.described_m, picks)


def sensor_distance_from_data(
    run: RunFile,
    results_file: PathArg,
    positions: ArrayLike,
    layout: Sequence[Source],
    ball_centre: BallCentre = None,
    compute: Compute | None = None,
    *,
    aperture: float | None = None,
    refit: bool = True,
) -> FittedNumber:
    """The sensor distance fitted to five merged positions spread over the sweep, at the sources
    of ``layout``, refitted at each trial distance with ``refit`` (sources found in the data;
    :func:`processing.unmixing.camera_fit.fit_sensor_distance`, one task on ``compute``; the
    aperture ``aperture`` across, or as the rig says)."""
    picks = spread_over(np.asarray(positions), FIT_FRACTIONS)
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
    return replace(
        _fitted_number(fit, fit.sensor_distance_m, fit.described_m, picks), sources_refitted=fit.sources_refitted
    )


def _fit_from_data(
    run: RunFile,
    option: str,
    task: Callable[..., _Fit],
    results_file: PathArg,
    ball_centre: BallCentre,
    picks: list[int],
    layout: Sequence[Source],
    camera: CameraFit,
    compute: Compute | None,
    *extra: object,
) -> _Fit:
    """One of the camera's fits as a task on ``compute``; its failure as one line naming ``option``."""
    args = (str(run.path), str(results_file), ball_centre, tuple(picks), tuple(layout), camera, *extra)
    compute = compute or Compute()
    try:
        return compute.submit(task, *args).result() if compute.dask else task(*args)
    except SourcesError as exc:
        raise ProcessingError(f"{run.path}: {option}: {exc}") from None


def _fitted_number(
    fit: ApertureFit | SensorDistanceFit, fitted_m: float, described_m: float, picks: Iterable[int]
) -> FittedNumber:
    return FittedNumber(
        fitted_m,
        described_m,
        round(fit.chi2 / fit.pixels, 5),
        round(fit.chi2_described / fit.pixels, 5),
        fit.pixels,
        tuple(int(i) for i in picks),
        fit.evaluations,
    )


def warn_if_unexplained(run: RunFile, aperture: FittedNumber | None) -> None:
    """Say so when the templates, with the aperture fitted, still leave the data unexplained."""
    if aperture is not None and (aperture.chi2_per_pixel or 0.0) > CHI2_PER_PIXEL_WARNING:
        log.warning(
            "%s: with the aperture fitted the templates still explain the data only to χ²/pixel %.3g: other "
            "numbers of the rig description (the ball's place and radius, the sensor distance) may be off "
            "(docs/light-model.md; --fit-sensor-distance fits the last)",
            run.path,
            aperture.chi2_per_pixel,
        )


def _fitted_aperture(
    run_path: str,
    results_file: str,
    ball_centre: BallCentre,
    picks: Sequence[int],
    layout: Sequence[Source],
    camera: CameraFit,
) -> ApertureFit:
    """:func:`processing.unmixing.camera_fit.fit_aperture` on the merged positions ``picks`` (a task)."""
    prepare_task()

    with open_run(run_path) as run:
        data, builder, cfa = layout_data(run, results_file, ball_centre, picks, camera)
        return fit_aperture(data, builder, cfa, list(layout))


def _fitted_sensor_distance(
    run_path: str,
    results_file: str,
    ball_centre: BallCentre,
    picks: Sequence[int],
    layout: Sequence[Source],
    camera: CameraFit,
    refit: bool,
) -> SensorDistanceFit:
    """:func:`processing.unmixing.camera_fit.fit_sensor_distance` on the merged positions ``picks`` (a task)."""
    prepare_task()

    with open_run(run_path) as run:
        data, builder, cfa = layout_data(run, results_file, ball_centre, picks, camera)
        return fit_sensor_distance(data, builder, cfa, list(layout), refit=refit)


def layout_data(
    run: RunFile, results_file: PathArg, ball_centre: BallCentre, picks: Iterable[int], camera: CameraFit | None = None
) -> tuple[list[LayoutData], TemplateBuilder, str]:
    """The merged positions ``picks`` as the layout fits take them: (data, builder, cfa pattern)."""

    geometry, builder = geometry_and_builder(run, ball_centre, camera)
    data: list[LayoutData] = []
    cfa = "RGGB"
    for index in picks:
        rate, var, usable, cfa = _merged_rates(run, str(results_file), index)
        measured = run.measured_pose(index)
        tool = measured if measured is not None else run.header.tool_poses[index]
        data.append(LayoutData(rate, var, usable, light_pose_at(geometry, tool), tool))
    return data, builder, cfa


def camera_at_layout(
    run: RunFile,
    results_file: PathArg,
    positions: ArrayLike,
    layout: Sequence[Source],
    ball_centre: BallCentre,
    compute: Compute,
    fits: CameraFits,
) -> tuple[FittedNumber | None, FittedNumber | None]:
    """The camera's numbers ``fits`` says, at the sources of a given ``layout`` (held at each
    trial): (aperture, sensor distance), each None where not fitted. The sensor distance
    first, the aperture at it."""
    distance = aperture = None
    if fits.fit_sensor_distance:
        distance = sensor_distance_from_data(run, results_file, positions, layout, ball_centre, compute, refit=False)
    if fits.fit_aperture:
        aperture = aperture_from_data(
            run, results_file, positions, layout, ball_centre, compute, sensor_distance=_fitted_m(distance)
        )
        warn_if_unexplained(run, aperture)
    return aperture, distance


def layout_and_camera(
    run: RunFile,
    results_file: PathArg,
    positions: ArrayLike,
    ball_centre: BallCentre,
    compute: Compute,
    fits: CameraFits,
    *,
    max_searches: int = 3,
    settle: float = 0.01,
    settle_distance: float = 5e-4,
) -> tuple[LayoutFit, FittedNumber | None, FittedNumber | None]:
    """The sources found in the data (:func:`layout_from_data`) and the camera's numbers
    ``fits`` says at them: the sensor distance (:func:`sensor_distance_from_data`, the sources
    refitted at each trial), then the aperture (:func:`aperture_from_data`). Returns (layout
    fit, aperture, sensor distance), each None where not fitted; :func:`fitted_camera` makes
    the camera to estimate with from them.

    A search made with a wrong aperture explains the templates' wrong width with sources that
    are not there, and the aperture fitted at those is off too; a wrong sensor distance adds
    sources as well. So the search is made again with what was fitted, and the fits made
    again at what it finds, until the aperture moves by less than ``settle`` and the distance
    by less than ``settle_distance`` (at most ``max_searches`` searches).

    A fit ``fits`` does not require that fails (its best at a bound of the search) is logged
    and the last search's sources kept, with the camera they were found with (the number's
    record then says ``failed``); a required one raises :class:`ProcessingError`.
    """
    camera = CameraFit()
    aperture: FittedNumber | None = None
    distance: FittedNumber | None = None
    moved = (0.0, 0.0)
    for search in range(1, max_searches + 1):
        found = layout_from_data(run, results_file, positions, ball_centre, compute, camera=camera)
        if not fits.fits_camera:
            return found, None, None
        at = (run, results_file, positions, found.sources, ball_centre, compute)
        if fits.fit_sensor_distance:
            distance = _fitted_or_kept(
                partial(sensor_distance_from_data, *at, aperture=camera.aperture_m),
                distance,
                fits.sensor_distance_fit_required,
                search,
            )
        if fits.fit_aperture and not (distance is not None and distance.failed):
            aperture = _fitted_or_kept(
                partial(aperture_from_data, *at, sensor_distance=_fitted_m(distance)),
                aperture,
                fits.aperture_fit_required,
                search,
            )
        if any(fit is not None and fit.failed for fit in (aperture, distance)):
            return found, aperture, distance
        new = fitted_camera(aperture, distance)
        moved = (
            _moved(camera.aperture_m, new.aperture_m, aperture),
            _moved(camera.sensor_distance_m, new.sensor_distance_m, distance),
        )
        camera = new
        if moved[0] < settle and moved[1] < settle_distance:
            break
    else:
        log.warning(
            "%s: the camera's numbers fitted to the data had not settled after %d searches for the sources "
            "(the aperture moved %.2g %%, the sensor distance %.2g %% at the last)",
            run.path,
            max_searches,
            100 * moved[0],
            100 * moved[1],
        )
    warn_if_unexplained(run, aperture)  # the last fit's: the searches before it may have left spurious sources
    return found, aperture, distance


def _fitted_or_kept(
    fit: Callable[[], FittedNumber], last: FittedNumber | None, required: bool, search: int
) -> FittedNumber:
    """``fit()`` with the search it followed; where it fails and is not ``required``, the last
    fit (or none) with the reason, logged."""
    try:
        return replace(fit(), searches=search)
    except ProcessingError as exc:
        if required:
            raise
        before = _fitted_m(last)
        kept = "the rig's number" if before is None else f"the number fitted before, {1e3 * before:.4g} mm"
        log.warning("%s (the sources are estimated with %s)", exc, kept)
        return replace(last or FittedNumber(), failed=str(exc))


def _fitted_m(fit: FittedNumber | None) -> float | None:
    return None if fit is None else fit.fitted_m


def _moved(before: float | None, after: float | None, fit: FittedNumber | None) -> float:
    """How far a fitted number moved, relative (0 when it was not fitted)."""
    if after is None:
        return 0.0
    if before is None:
        assert fit is not None and fit.described_m is not None  # a fitted number has its fit, and the rig's
        before = fit.described_m
    return abs(after / before - 1.0)


def fitted_camera(aperture: FittedNumber | None, distance: FittedNumber | None) -> CameraFit:
    """The camera the sources are estimated with: each number its fit's, where it was fitted."""
    return CameraFit(_fitted_m(aperture), _fitted_m(distance))


def spread_over(positions: np.ndarray, fractions: Iterable[float]) -> list[int]:
    """The positions at these fractions of the way through ``positions`` (each once, in order)."""
    return sorted({int(positions[int(q * (len(positions) - 1))]) for q in fractions})


def _refined_layout(
    run_path: str,
    results_file: str,
    ball_centre: BallCentre,
    camera: CameraFit | None,
    picks: Iterable[int],
    first: list[Source],
    seeds: Sequence[tuple[float, float]],
) -> LayoutFit:
    """:func:`processing.unmixing.search.refine_layout` on the merged positions ``picks`` (a task)."""
    prepare_task()

    with open_run(run_path) as run:
        data, builder, cfa = layout_data(run, results_file, ball_centre, picks, camera)
        return refine_layout(data, builder, cfa, first, seeds)


def _merged_rates(run: RunFile, results_file: str, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    with Results.open(results_file) as results:
        rate, var, usable = electron_rates(
            results.radiance(index),
            results.variance(index),
            results.count(index),
            results.saturated(index),
            radiometric_gain(run),
        )
        return rate, var, usable, results.cfa_pattern


def _layout_box_at(
    index: int, run_path: str, results_file: str, ball_centre: BallCentre, camera: CameraFit | None
) -> tuple[float, float, float, float] | None:
    """The lit box of one merged position (a task)."""
    prepare_task()

    with open_run(run_path) as run:
        geometry, _ = geometry_and_builder(run, ball_centre, camera)
        rate, _, usable, _ = _merged_rates(run, results_file, index)
        return lit_box(rate, usable, light_pose_at_position(run, geometry, index), geometry)


def _candidate_strength_at(
    index: int,
    run_path: str,
    results_file: str,
    ball_centre: BallCentre,
    camera: CameraFit | None,
    candidates: Iterable[Source],
) -> np.ndarray:
    """The candidates' strengths at one merged position (a task)."""
    prepare_task()

    with open_run(run_path) as run:
        geometry, builder = geometry_and_builder(run, ball_centre, camera)
        rate, var, usable, cfa = _merged_rates(run, results_file, index)
        return candidate_strength(
            rate, var, usable, light_pose_at_position(run, geometry, index), builder, list(candidates), cfa
        )
