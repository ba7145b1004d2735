"""The sources found in the data: a candidate grid, its local maxima, then their places refined."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
from threadpoolctl import threadpool_limits

from drivers.pose import Pose
from processing.trace import RigGeometry, trace_pixels
from processing.unmixing.problem import LayoutData, LayoutProblem
from processing.unmixing.sources import Source, SourcesError
from processing.unmixing.templates import TemplateBuilder
from processing.unmixing.unmix import unmix_position


def lit_box(
    rate: np.ndarray, ok: np.ndarray, pose: Pose, geometry: RigGeometry, core_fraction: float = 0.2
) -> tuple[float, float, float, float] | None:
    """(u0, u1, v0, v1) on the light plane of the chief rays of one position's brightest
    pixels (above ``core_fraction`` of its peak); None if nothing is lit."""
    lit = ok & np.isfinite(rate) & (rate > core_fraction * np.nanmax(np.where(ok, rate, 0.0)))
    rows, cols = np.nonzero(lit)
    if rows.size == 0:
        return None
    rays = trace_pixels(geometry, pose, cols.astype(float), rows.astype(float))
    if not np.any(rays.valid):
        return None
    u, v = rays.u[rays.valid], rays.v[rays.valid]
    return (float(u.min()), float(u.max()), float(v.min()), float(v.max()))


def candidate_grid(
    boxes: Iterable[tuple[float, float, float, float] | None], *, spacing: float = 1.5e-3, margin: float = 3e-3
) -> tuple[list[Source], np.ndarray, np.ndarray]:
    """Candidate point sources every ``spacing`` over the union of ``boxes`` (None ignored)
    plus ``margin``: (candidates, us, vs), the candidates row by row (v) along u."""
    lit = [b for b in boxes if b is not None]
    if not lit:
        raise SourcesError("no light in the data to find sources in")
    u0, u1 = min(b[0] for b in lit) - margin, max(b[1] for b in lit) + margin
    v0, v1 = min(b[2] for b in lit) - margin, max(b[3] for b in lit) + margin
    us = np.arange(math.floor(u0 / spacing), math.ceil(u1 / spacing) + 1) * spacing
    vs = np.arange(math.floor(v0 / spacing), math.ceil(v1 / spacing) + 1) * spacing
    candidates = [
        Source(f"c{i}-{j}", (float(u), float(v)), 0.25 * spacing) for j, v in enumerate(vs) for i, u in enumerate(us)
    ]
    return candidates, us, vs


def candidate_strength(
    rate: np.ndarray,
    variance: np.ndarray,
    ok: np.ndarray,
    pose: Pose,
    builder: TemplateBuilder,
    candidates: list[Source],
    cfa_pattern: str,
) -> np.ndarray:
    """Every candidate's unmixed intensity at one position, over the largest (so 1 at the
    strongest; zeros if none lights up). On one BLAS thread, as in a Dask worker: this is
    where :func:`refine_layout` starts, and it must start from the same bits wherever it runs."""

    with threadpool_limits(limits=1, user_api="blas"):
        estimate = unmix_position(-1, rate, variance, ok, cfa_pattern, builder, candidates, pose, region="union")
    values = np.nan_to_num(np.nanmean(estimate.intensity, axis=1))
    return values / values.max() if values.max() > 0 else np.zeros(len(candidates))


def sources_from_strength(
    strength: np.ndarray,
    us: np.ndarray,
    vs: np.ndarray,
    *,
    spacing: float = 1.5e-3,
    threshold: float = 0.05,
    min_separation: float = 2e-3,
) -> list[Source]:
    """The local maxima of the candidates' summed strength, refined and merged into sources."""
    grid = np.asarray(strength, float).reshape(len(vs), len(us))
    found = []
    peak = grid.max()
    if peak <= 0:
        raise SourcesError("no source stands out of the candidate grid")
    for j in range(len(vs)):
        for i in range(len(us)):
            value = grid[j, i]
            window = grid[max(0, j - 1) : j + 2, max(0, i - 1) : i + 2]
            if value < threshold * peak or value < window.max():
                continue
            jj, ii = np.mgrid[max(0, j - 1) : j + 2, max(0, i - 1) : i + 2]
            u = float((window * us[ii]).sum() / window.sum())
            v = float((window * vs[jj]).sum() / window.sum())
            found.append((u, v, float(window.sum())))
    # Peaks closer than the resolution are one source whose strength the grid shared out.
    merged: list[list[float]] = []
    for u, v, w in sorted(found, key=lambda p: -p[2]):
        for m in merged:
            if math.hypot(u - m[0] / m[2], v - m[1] / m[2]) < min_separation:
                m[0] += u * w
                m[1] += v * w
                m[2] += w
                break
        else:
            merged.append([u * w, v * w, w])
    return [Source(f"source-{k}", (m[0] / m[2], m[1] / m[2]), 0.5 * spacing) for k, m in enumerate(merged)]


@dataclass
class LayoutFit:
    """The sources :func:`refine_layout` settled on, and how well they explain the data.

    ``refined`` is False when no refinement could be made (``message`` says why) and
    ``sources`` are then the first guess unchanged; ``chi2`` and ``pixels`` are the
    weighted squared residual over the fitted pixels and their count (χ²/pixels ≈ 1 when
    the templates explain the data to its noise); ``steps`` holds (sources, χ²) after each
    accepted step.
    """

    sources: list[Source]
    refined: bool
    message: str
    chi2: float = float("nan")
    pixels: int = 0
    steps: list[tuple[int, float]] = field(default_factory=list)


def seeds_from_strength(
    strength: np.ndarray, us: np.ndarray, vs: np.ndarray, *, threshold: float = 0.05
) -> list[tuple[float, float]]:
    """The candidates of the grid that took at least ``threshold`` of the strongest one's
    strength: where the unmixing put light, so where a source the local maxima missed can be."""
    grid = np.asarray(strength, float).reshape(len(vs), len(us))
    peak = grid.max(initial=0.0)
    if peak <= 0:
        return []
    j, i = np.nonzero(grid >= threshold * peak)
    order = np.argsort(-grid[j, i], kind="stable")
    return [(float(us[i[k]]), float(vs[j[k]])) for k in order]


def refine_layout(
    data: list[LayoutData],
    builder: TemplateBuilder,
    cfa_pattern: str,
    first: list[Source],
    seeds: Sequence[tuple[float, float]] = (),
    *,
    min_gain: float = 0.02,
    min_share: float = 0.02,
    min_distance: float = 0.5e-3,
    max_radius: float = 1.5e-3,
    max_sources: int = 24,
    margin_px: int = 48,
    inset_px: int = 8,
    max_nfev: int = 40,
    screen_nfev: int = 4,
    screen_seeds: int = 2,
) -> LayoutFit:
    """Point sources moved to where their templates explain the data best, and added one
    at a time while each addition explains a share of what is left.

    The first guess (the candidate grid's local maxima) is resolution-limited: a source
    between grid points shares its light out with its neighbours, whose centroid pulls it
    towards the others, and a source whose light the grid gave to its neighbours has no
    local maximum at all. Here the sources' (u, v) are free and their intensities are
    solved for at every step (:class:`LayoutProblem`), so positions come out to a small
    fraction of the grid's spacing. Then each seed (:func:`seeds_from_strength`) farther
    than ``min_distance`` from every source is tried as one more source; the best is kept,
    and every position refitted, if it lowers χ² by at least ``min_gain`` of its value and
    carries at least ``min_share`` of the brightest source's light; the search stops at
    the first seed that does not, or at ``max_sources``. A seed is judged after
    ``screen_nfev`` steps of the whole fit, not where it stands (:meth:`_Refinement.grow`).
    Each source found carries its centre's 1σ (:meth:`LayoutProblem.centre_sigma`).

    Parameters
    ----------
    data : list of LayoutData
        A few merged positions spread over the sweep.
    builder : TemplateBuilder
        The templates of the processing.
    cfa_pattern : str
        The mosaic's colour filter layout.
    first : list of Source
        The first guess.
    seeds : sequence of (u, v)
        Where to look for sources the first guess missed, strongest first.

    Returns
    -------
    LayoutFit
        Unrefined (``refined`` False, ``message`` why) when no position has a window where
        the first guess's templates are all whole.
    """
    if not first:
        return LayoutFit([], False, "no first guess to refine")

    # One BLAS thread, as in a Dask worker: the fit is iterative and amplifies a product summed in another
    # order into the centres (~1e-11 m). Its matrices are a few columns wide: one thread is no slower.
    with threadpool_limits(limits=1, user_api="blas"):
        problem = LayoutProblem(data, builder, cfa_pattern, first, margin_px, inset_px)
        if not problem.windows or problem.pixels < 16:
            return LayoutFit(list(first), False, "no position has a window where every template is whole")
        fit = _Refinement(problem, max_radius, max_nfev)
        fit.refit(np.array([s.centre for s in first], float), float(np.median([s.radius for s in first])))
        fit.merge_close_guesses(min_distance)
        untried = [np.array(seed, float) for seed in seeds]
        while len(fit.centres) < max_sources:
            untried = [seed for seed in untried if np.min(np.hypot(*(fit.centres - seed).T)) >= min_distance]
            if not untried or not fit.grow(untried, min_gain, min_share, min_distance, screen_nfev, screen_seeds):
                break
        fit.drop_dark_sources()
        sigma = problem.centre_sigma(fit.centres, fit.radius)
        sources = [
            Source(f"source-{k}", (float(u), float(v)), fit.radius, (float(su), float(sv)))
            for k, ((u, v), (su, sv)) in enumerate(zip(fit.centres, sigma, strict=True))
        ]
        count = f"{len(sources)} source{'s' * (len(sources) != 1)}"
        return LayoutFit(
            sources,
            True,
            f"{count} of radius {fit.radius * 1e3:.2f} mm, χ² {fit.chi2:.4g} over {problem.pixels} pixels",
            fit.chi2,
            problem.pixels,
            fit.steps,
        )


class _Refinement:
    """The sources' centres and common radius as :func:`refine_layout` refits them, and its steps."""

    def __init__(self, problem: LayoutProblem, max_radius: float, max_nfev: int):
        self.problem, self.max_radius, self.max_nfev = problem, max_radius, max_nfev
        self.steps: list[tuple[int, float]] = []

    def refit(self, centres: np.ndarray, radius: float) -> None:
        """Every source's place and the common radius fitted from ``centres`` and ``radius``."""
        self.accept(*self.problem.fit(centres, radius, self.max_radius, self.max_nfev))

    def accept(self, centres: np.ndarray, radius: float, chi2: float) -> None:
        self.centres, self.radius, self.chi2 = centres, radius, chi2
        self.steps.append((len(centres), chi2))

    def merge_close_guesses(self, min_distance: float) -> None:
        """Two guesses of one source (the grid shares a source's light out) meet when fitted: the
        fainter goes, and the rest are refitted."""
        while len(self.centres) > 1:
            gap, i, j = closest_pair(self.centres)
            if gap >= min_distance:
                return
            light = self.problem.light(self.centres, self.radius)
            self.refit(np.delete(self.centres, i if light[i] < light[j] else j, axis=0), self.radius)

    def grow(
        self, untried: list, min_gain: float, min_share: float, min_distance: float, screen_nfev: int, screen_seeds: int
    ) -> bool:
        """One more source from ``untried`` (the seed taken is removed from it), if one passes
        the screen and, fitted, lowers χ² by ``min_gain`` with ``min_share`` of the light.

        The sources found so far may have widened their discs over a missed source's light
        (four guesses at 23.6 µm pixels grew to 1.3 mm for 0.5), and then one more source
        helps only once the discs shrink back. Where they stand, with the other sources and
        the radius held, the seeds' χ² then differ by 0.01-0.1 %: a poor ranking. So the
        ``screen_seeds`` best there are screened in turn, each after ``screen_nfev`` steps of
        the whole fit, and the first that reaches ``min_gain`` is taken.
        """
        problem, chi2 = self.problem, self.chi2
        trials = np.array([problem.chi2(np.vstack([self.centres, seed]), self.radius) for seed in untried])
        for k in np.argsort(trials)[:screen_seeds]:
            screened = problem.fit(np.vstack([self.centres, untried[k]]), self.radius, self.max_radius, screen_nfev)
            if screened[2] <= (1.0 - min_gain) * chi2:
                untried.pop(k)
                break
        else:
            return False
        grown, grown_radius, grown_chi2 = problem.fit(screened[0], screened[1], self.max_radius, self.max_nfev)
        light = problem.light(grown, grown_radius)
        too_close = closest_pair(grown)[0] < min_distance
        if grown_chi2 > (1.0 - min_gain) * chi2 or light[-1] < min_share * light.max() or too_close:
            return False
        self.accept(grown, grown_radius, grown_chi2)
        return True

    def drop_dark_sources(self) -> None:
        """A source left with no light (the unmixing gave it nothing anywhere) is not one."""
        keep = self.problem.light(self.centres, self.radius) > 0
        if not np.all(keep) and np.any(keep):
            self.refit(self.centres[keep], self.radius)


def closest_pair(centres: np.ndarray) -> tuple[float, int, int]:
    """(distance, i, j) of the two closest of ``centres`` (at least two)."""
    return min((math.dist(centres[i], centres[j]), i, j) for i in range(len(centres)) for j in range(i))
