"""The camera's numbers fitted to the data: the aperture's diameter and the sensor distance."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import minimize_scalar
from threadpoolctl import threadpool_limits

from processing.unmixing.problem import LayoutData, LayoutProblem
from processing.unmixing.sources import Source, SourcesError
from processing.unmixing.templates import TemplateBuilder


@dataclass(frozen=True)
class ApertureFit:
    """The camera's aperture diameter (the pinhole's) that the data favour, :func:`fit_aperture`.

    ``chi2`` and ``chi2_described`` are the weighted squared residual over ``pixels`` at the
    fitted and at the described diameter; ``evaluations`` counts the χ² computed."""

    diameter_m: float
    described_m: float
    chi2: float
    chi2_described: float
    pixels: int
    evaluations: int


def fit_aperture(
    data: list[LayoutData],
    builder: TemplateBuilder,
    cfa_pattern: str,
    layout: list[Source],
    *,
    bounds: tuple[float, float] = (0.75, 1.25),
    xatol: float = 1e-4,
    margin_px: int = 48,
    inset_px: int = 8,
) -> ApertureFit:
    """The aperture diameter whose templates, at the sources' known places, explain the data best.

    The aperture sets the point spread's size, and the unmixing is a deconvolution: a
    description 1 % off put the fits 4-5 % off the truth on the demo rig, 10 % off 42-48 %
    (``mirrorgonio bench tolerance``). The data tell it apart: χ² of the templates over the
    pixels of :class:`LayoutProblem` (their intensities solved for by NNLS) rose from 1.066
    to 1.09-1.13 a pixel over 72 845 pixels with the diameter 1 % off. So the diameter is
    the minimum of that χ² over ``bounds`` × the described one (bounded Brent search,
    ``scipy.optimize.minimize_scalar``, to ``xatol`` of the described diameter). The pixels
    stay those where the narrowest aperture tried gives whole templates, so that every trial
    is judged on the same pixels.

    Parameters
    ----------
    data : list of LayoutData
        A few merged positions spread over the sweep.
    builder : TemplateBuilder
        The templates as the rig is described.
    cfa_pattern : str
        The mosaic's colour filter layout.
    layout : list of Source
        The sources, known (their centres and radii are held).

    Raises
    ------
    SourcesError
        No position with a window where every template is whole, or the best diameter at a
        bound of the search (the description is further off than ``bounds``, or the
        templates cannot explain the data).
    """

    if not layout:
        raise SourcesError("no sources to fit the aperture at")
    described = builder.geometry.aperture_radius
    narrowest = replace(builder, geometry=replace(builder.geometry, aperture_radius=described * bounds[0]))
    centres = np.array([s.centre for s in layout], float)
    radii = np.array([s.radius for s in layout], float)

    def chi2_at(problem: LayoutProblem, scale: float) -> float:
        problem.set_aperture(described * scale)
        return problem.chi2(centres, radii)

    scale, chi2, chi2_described, pixels, evaluations = _fit_scale(
        data,
        narrowest,
        cfa_pattern,
        layout,
        margin_px,
        inset_px,
        bounds,
        xatol,
        chi2_at,
        "aperture",
        lambda x: f"{2e3 * described * x:.4g} mm",
    )
    return ApertureFit(2.0 * described * scale, 2.0 * described, chi2, chi2_described, pixels, evaluations)


def _fit_scale(
    data: list[LayoutData],
    builder: TemplateBuilder,
    cfa_pattern: str,
    layout: list[Source],
    margin_px: int,
    inset_px: int,
    bounds: tuple[float, float],
    xatol: float,
    chi2_at: Callable[[LayoutProblem, float], float],
    what: str,
    shown: Callable[[float], str],
) -> tuple[float, float, float, int, int]:
    """The factor in ``bounds`` on one of the camera's described numbers whose templates explain
    the data best (bounded Brent search, ``scipy.optimize.minimize_scalar``, to ``xatol``):
    (factor, χ² there, χ² at 1, pixels, evaluations). ``chi2_at(problem, factor)`` sets the
    trial on the :class:`LayoutProblem` (its pixels fixed by ``builder``) and returns χ²;
    ``shown(factor)`` is the number as an error names it. A best factor at a bound is an error."""

    with threadpool_limits(limits=1, user_api="blas"):  # as in refine_layout: one order of sums
        problem = LayoutProblem(data, builder, cfa_pattern, list(layout), margin_px, inset_px)
        if not problem.windows or problem.pixels < 16:
            raise SourcesError("no position has a window where every template is whole")
        evaluations = 0

        def chi2(factor: float) -> float:
            nonlocal evaluations
            evaluations += 1
            return chi2_at(problem, factor)

        best = minimize_scalar(chi2, bounds=bounds, method="bounded", options={"xatol": xatol})
        at_described = chi2(1.0)
    factor = float(best.x)
    if min(factor - bounds[0], bounds[1] - factor) <= 2 * xatol:
        raise SourcesError(
            f"the best {what} lies at the search's bound ({shown(factor)}, {100 * (factor - 1):+.1f} % "
            f"of the described {shown(1.0)})"
        )
    return factor, float(best.fun), at_described, problem.pixels, evaluations


@dataclass(frozen=True)
class SensorDistanceFit:
    """:func:`fit_sensor_distance`'s result: the distance, and χ² there and at the described one."""

    sensor_distance_m: float
    described_m: float
    chi2: float
    chi2_described: float
    pixels: int
    evaluations: int
    sources_refitted: bool


def fit_sensor_distance(
    data: list[LayoutData],
    builder: TemplateBuilder,
    cfa_pattern: str,
    layout: list[Source],
    *,
    refit: bool = True,
    bounds: tuple[float, float] = (0.98, 1.02),
    xatol: float = 2e-4,
    max_radius: float = 1.5e-3,
    max_nfev: int = 40,
    margin_px: int = 48,
    inset_px: int = 8,
) -> SensorDistanceFit:
    """The sensor distance (pinhole to sensor) whose templates explain the data best.

    It sets the image's scale: 0.5 % too long made the search for the sources on the demo rig
    add four that are not there (fits 38 % off), and χ² with those nine did not give it away
    (``mirrorgonio bench tolerance``). Held at the sources such a search found, χ² is least
    near the wrong distance too: the spurious sources lock it. So with ``refit`` (sources found
    in the data) the sources' centres and common radius are fitted again at every trial
    distance (:meth:`LayoutProblem.fit`, as many sources as ``layout`` has) and the distance
    is the one whose best layout explains the data best: on the demo rig described 0.5 %
    long, seven sources found, χ²/pixel 1.185 as described and 1.060-1.061 at 0.994-0.995 of it
    (the truth: 0.99502). Without ``refit`` (sources whose places are known) they are held.
    A bounded Brent search (``scipy.optimize.minimize_scalar``) over ``bounds`` × the described
    distance, to ``xatol`` of it; the pixels are those of the described geometry's windows.

    Raises
    ------
    SourcesError
        No sources, no position with a window where every template is whole, or the best
        distance at a bound of the search.
    """
    if not layout:
        raise SourcesError("no sources to fit the sensor distance at")
    described = builder.geometry.sensor_distance
    centres = np.array([s.centre for s in layout], float)
    radii = np.array([s.radius for s in layout], float)

    def chi2_at(problem: LayoutProblem, scale: float) -> float:
        problem.set_geometry(builder.geometry.with_sensor_distance(described * scale))
        if refit:
            return problem.fit(centres, float(np.median(radii)), max_radius, max_nfev)[2]
        return problem.chi2(centres, radii)

    scale, chi2, chi2_described, pixels, evaluations = _fit_scale(
        data,
        builder,
        cfa_pattern,
        layout,
        margin_px,
        inset_px,
        bounds,
        xatol,
        chi2_at,
        "sensor distance",
        lambda x: f"{1e3 * described * x:.3f} mm",
    )
    return SensorDistanceFit(described * scale, described, chi2, chi2_described, pixels, evaluations, refit)
