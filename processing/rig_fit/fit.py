"""The rig's numbers fitted to the data with the sources' places: :func:`fit_rig`."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import cast

import numpy as np
from scipy.optimize import OptimizeResult, least_squares
from threadpoolctl import threadpool_limits

from drivers.contracts.rig import Tolerances
from drivers.pose import Pose
from processing.rig_fit.correction import FITTED, HELD, RigCorrection, bounds
from processing.rig_fit.problem import RigProblem
from processing.rig_fit.silhouette import SilhouetteTerm
from processing.trace import light_pose_at
from processing.unmixing.problem import LayoutData, LayoutProblem, clustered_sigma, scaled_sigma
from processing.unmixing.sources import Source, SourcesError
from processing.unmixing.templates import TemplateBuilder

#: Why the aperture's shape is held where the templates are geometric-Airy.
ROUND_TEMPLATES = "the geometric-Airy templates draw a round aperture: its shape is the Fresnel templates' to fit"


@dataclass(frozen=True)
class RigFit:
    """What :func:`fit_rig` found.

    Attributes
    ----------
    correction : RigCorrection
        The fitted numbers (:data:`~processing.rig_fit.correction.FITTED`), in their fit units.
    sigma : tuple of float
        Each one's 1σ: the larger of the statistical one (the fit's Jacobian with the residuals'
        scatter, χ² per degree of freedom, as independent noise) and the one the positions'
        disagreement gives (a sandwich clustered by position: the templates' error is shared by
        a position's pixels, so they are not independent evidence).
    statistical : tuple of float
        The statistical 1σ alone: the searches' test of having settled (a step within it).
    sources : list of Source
        The sources at their fitted places.
    chi2_described, chi2 : float
        The templates' χ² over ``pixels`` with the rig as described (the sources refitted there
        first) and as fitted.
    pixels : int
    at_bound : tuple of str
        Fitted numbers that ended at their tolerance's bound (the description is further off, or
        something else is).
    silhouette : dict
        The silhouette's term at the fitted rig (:meth:`SilhouetteTerm.record`), empty without one.
    """

    correction: RigCorrection
    sigma: tuple[float, ...]
    sources: list[Source]
    chi2_described: float
    chi2: float
    pixels: int
    evaluations: int
    at_bound: tuple[str, ...] = ()
    silhouette: dict = field(default_factory=dict)
    held: dict[str, str] = field(default_factory=lambda: dict(HELD))
    statistical: tuple[float, ...] = ()

    def record(self) -> dict:
        """A JSON-able record: each fitted number with its 1σ, the held ones with why, χ²/pixel."""
        return {
            "fitted": {
                n.name: {"value": round(v, 6), "sigma": round(s, 6), "unit": n.unit, "what": n.what}
                for n, v, s in zip(FITTED, self.correction.values, self.sigma, strict=True)
                if n.name not in self.held
            },
            "held": dict(self.held),
            "chi2_per_pixel_described": round(self.chi2_described / self.pixels, 5),
            "chi2_per_pixel": round(self.chi2 / self.pixels, 5),
            "pixels": self.pixels,
            "evaluations": self.evaluations,
            "at_bound": list(self.at_bound),
            "silhouette": dict(self.silhouette),
        }


def fit_rig(
    data: list[LayoutData],
    builder: TemplateBuilder,
    cfa_pattern: str,
    layout: list[Source],
    tolerances: Tolerances,
    light_axis: np.ndarray,
    silhouette: SilhouetteTerm | None = None,
    *,
    start: RigCorrection | None = None,
    hold_sources: bool = False,
    max_radius: float = 1.5e-3,
    max_nfev: int = 40,
    margin_px: int = 48,
    inset_px: int = 8,
) -> RigFit:
    """The correction of the rig, and the sources' places, that explain the data best.

    The templates' χ² over a few merged positions spread over the sweep (the pixels of
    :class:`~processing.unmixing.problem.LayoutProblem`, fixed by the ``layout`` as found
    through the rig corrected by ``start``), together with the ball's silhouette where
    ``silhouette`` is given and the tolerances as each number's prior 1σ, minimised by a bounded
    least-squares fit (``scipy.optimize.least_squares``, trust-region reflective) over the
    fitted numbers (within the rig's ``tolerances``), the sources' centres and their common
    radius (held as given with ``hold_sources``). ``builder`` is the rig as described; the
    data's positions carry the arm's tool poses (``LayoutData.tool``): the light's poses follow
    the arm's corrected frame.

    Raises
    ------
    SourcesError
        No sources, a position without its tool pose, or no position with a window where
        every template is whole.
    """
    if not layout:
        raise SourcesError("no sources to fit the rig at")
    if any(item.tool is None for item in data):
        raise SourcesError("the rig's fit needs every position's tool pose")
    start = start or RigCorrection.of(np.zeros(len(FITTED)), light_axis)
    tools = cast(list[Pose], [item.tool for item in data])
    with threadpool_limits(limits=1, user_api="blas"):  # one order of sums, as in refine_layout
        at_start = start.apply(builder.geometry)  # the pixels chosen where the layout was found
        problem = LayoutProblem(
            [replace(item, pose=light_pose_at(at_start, tool)) for item, tool in zip(data, tools, strict=True)],
            replace(builder, geometry=at_start),
            cfa_pattern,
            layout,
            margin_px,
            inset_px,
        )
        if not problem.windows or problem.pixels < 16:
            raise SourcesError("no position has a window where every template is whole")
        limit = bounds(tolerances, builder.geometry, shape=builder.pupil is not None)
        held = limit == 0.0  # a number the templates cannot see (the aperture's shape, round templates)
        rig = RigProblem(problem, builder.geometry, tools, light_axis, silhouette, np.where(held, np.inf, limit))
        centres = np.array([s.centre for s in layout], float)
        radius = min(float(np.median([s.radius for s in layout])), max_radius)
        rig.set_correction(RigCorrection.of(np.zeros(len(FITTED)), light_axis))
        chi2_described = (
            problem.chi2(centres, radius) if hold_sources else problem.fit(centres, radius, max_radius, 8)[2]
        )
        vector = _Vector(limit, centres, radius, max_radius, hold_sources)
        residuals = _LastResiduals(lambda x: rig.residuals(*vector.unpack(x, light_axis)))
        result = least_squares(
            residuals,
            vector.pack(start.vector, centres, radius),
            jac=lambda x: forward_jacobian(residuals, x, vector.bounds, order=vector.cheapest_first()),
            bounds=vector.bounds,
            xtol=1e-4,
            ftol=1e-6,
            max_nfev=max_nfev,
        )
        correction, fitted_centres, fitted_radius = vector.unpack(result.x, light_axis)
        geometry = rig.set_correction(correction)
        chi2 = problem.chi2(fitted_centres, fitted_radius)
    at_bound = tuple(
        number.name
        for number, value, bound in zip(FITTED, correction.values, limit, strict=True)
        if bound > 0 and abs(value) >= bound * (1.0 - 1e-3)
    )
    statistical, sigma, centre_sigma = _sigmas(result, problem, held, vector)
    sources = [
        replace(source, centre=(float(u), float(v)), radius=fitted_radius, centre_sigma=where)
        for source, (u, v), where in zip(layout, fitted_centres, centre_sigma, strict=True)
    ]
    return RigFit(
        correction,
        tuple(float(s) for s in sigma),
        sources,
        chi2_described,
        chi2,
        problem.pixels,
        int(result.nfev),
        at_bound,
        silhouette.record(geometry) if silhouette is not None else {},
        HELD | {name: ROUND_TEMPLATES for name, hold in zip((n.name for n in FITTED), held, strict=True) if hold},
        tuple(float(s) for s in statistical),
    )


class _Vector:
    """The fit's vector: the correction in its units, then (unless held) the sources' centres
    and their common radius in millimetres (least_squares' relative step of 0.01 is then
    10-40 µm, a small fraction of a pixel on the sensor)."""

    def __init__(self, limit: np.ndarray, centres: np.ndarray, radius: float, max_radius: float, hold: bool) -> None:
        self.centres, self.radius, self.hold = centres, radius, hold
        self.fitted = limit > 0  # the correction's numbers in the vector (the others held at 0)
        self.n = int(np.count_nonzero(self.fitted))
        free = 0 if hold else centres.size + 1
        lower = np.concatenate([-limit[self.fitted], np.full(free, -np.inf)])
        upper = np.concatenate([limit[self.fitted], np.full(free, np.inf)])
        if not hold:
            lower[-1], upper[-1] = 0.02, max_radius * 1e3
        self.bounds = (lower, upper)

    def pack(self, correction: np.ndarray, centres: np.ndarray, radius: float) -> np.ndarray:
        numbers = correction[self.fitted]
        x = numbers if self.hold else np.concatenate([numbers, centres.ravel() * 1e3, [radius * 1e3]])
        lower, upper = self.bounds
        return np.clip(x, lower + 1e-9, upper - 1e-9)

    def cheapest_first(self) -> np.ndarray:
        """The vector's indices, the sources' centres first (each moves one source's templates),
        then the radius and the rig's numbers (each moves them all)."""
        if self.hold:
            return np.arange(self.n)
        radius = self.n + self.centres.size
        return np.concatenate([np.arange(self.n, radius), [radius], np.arange(self.n)])

    def unpack(self, x: np.ndarray, light_axis: np.ndarray) -> tuple[RigCorrection, np.ndarray, float]:
        values = np.zeros(self.fitted.size)
        values[self.fitted] = x[: self.n]
        correction = RigCorrection.of(values, light_axis)
        if self.hold:
            return correction, self.centres, self.radius
        return correction, x[self.n : -1].reshape(-1, 2) * 1e-3, float(x[-1]) * 1e-3


class _LastResiduals:
    """The residual function, remembering its last value: the Jacobian at a point starts from
    the residuals the fit has just computed there."""

    def __init__(self, fun: Callable[[np.ndarray], np.ndarray]) -> None:
        self.fun = fun
        self.x: np.ndarray | None = None
        self.value: np.ndarray | None = None

    def __call__(self, x: np.ndarray) -> np.ndarray:
        self.x, self.value = np.array(x, float), self.fun(x)
        return self.value

    def at(self, x: np.ndarray) -> np.ndarray:
        if self.x is not None and self.value is not None and np.array_equal(self.x, x):
            return self.value
        return self(x)


def forward_jacobian(
    fun: _LastResiduals,
    x: np.ndarray,
    bounds: tuple[np.ndarray, np.ndarray],
    *,
    order: np.ndarray,
    rel_step: float = 0.01,
) -> np.ndarray:
    """Forward differences as least_squares' ``2-point`` takes them (scipy ≥ 1.17: a step of
    ``rel_step · |x|`` signed as x, √ε·max(1, |x|) where that is none, turned back where it
    would leave the bounds), column by column in ``order``.

    The order is the point: a source's centre moves that source's templates alone, and the
    problem keeps the templates of the point itself (:meth:`LayoutProblem._column`) only for a
    while. Taken first, right after the residuals there, the sources' columns rebuild one
    source each; taken after the rig's numbers (each of which rebuilds every template), they
    found the point's templates gone and rebuilt them all: with 13 sources the Jacobian cost
    47 evaluations' templates, now about 23.
    """
    f0 = fun.at(x)
    lower, upper = bounds
    sign = np.where(x >= 0, 1.0, -1.0)
    h = rel_step * sign * np.abs(x)
    # Where that is no step (x = 0), machine precision's: √ε · max(1, |x|), as scipy does.
    h = np.where((x + h) - x == 0, math.sqrt(np.finfo(float).eps) * sign * np.maximum(1.0, np.abs(x)), h)
    outside = (x + h > upper) | (x + h < lower)
    h = np.where(outside, -h, h)
    jac = np.empty((f0.size, x.size))
    for i in order:
        step = x.copy()
        step[i] += h[i]
        jac[:, i] = (fun.fun(step) - f0) / (step[i] - x[i])
    return jac


def _sigmas(
    result: OptimizeResult, problem: LayoutProblem, held: np.ndarray, vector: _Vector
) -> tuple[np.ndarray, np.ndarray, list[tuple[float, float] | None]]:
    """Each number's statistical 1σ (:func:`~processing.unmixing.problem.scaled_sigma`) and the one
    reported: the larger of it and the clustered sandwich's
    (:func:`~processing.unmixing.problem.clustered_sigma`, one cluster per position's pixels); 0
    for the held ones. Then each source's centre's 1σ (m) the same way, from the same joint
    covariance (so with the rig's numbers' correlations), or None for each where they were held."""
    statistical, sigma = np.zeros(len(FITTED)), np.zeros(len(FITTED))
    n = result.x.size
    scaled = scaled_sigma(result.jac, result.fun, n)
    reported = np.maximum(scaled, clustered_sigma(result.jac, result.fun, problem.blocks, n))
    statistical[~held], sigma[~held] = scaled[: vector.n], reported[: vector.n]
    if vector.hold:
        return statistical, sigma, [None] * len(vector.centres)
    centres = reported[vector.n : -1].reshape(-1, 2) * 1e-3
    return statistical, sigma, [(float(u), float(v)) for u, v in centres]
