"""The templates' χ² over a few merged positions, as the layout search and the camera fits minimise it."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares

from drivers.pose import Pose
from processing.hdr.mosaic import cfa_channels
from processing.trace import RigGeometry
from processing.unmixing.sources import Source
from processing.unmixing.templates import TemplateBuilder
from processing.unmixing.unmix import nnls_via_cholesky, place_template


@dataclass(frozen=True)
class LayoutData:
    """One position's merged mosaic for the layout search: e⁻/s, (e⁻/s)², usable pixels, the
    light's pose, and the arm's tool pose it was taken at (for fits that move the arm's frame)."""

    rate: np.ndarray
    variance: np.ndarray
    usable: np.ndarray
    pose: Pose
    tool: Pose | None = None


class LayoutProblem:
    """The weighted residual of the data against templates of point sources at free (u, v),
    their intensities solved for (NNLS, per position and channel) at every evaluation: the
    positions are the only parameters left (variable projection, Golub & Pereyra 1973).

    Pixels are fixed once (a least-squares residual keeps its length): at each position
    the window where every first-guess template is whole, less ``inset_px`` on each side,
    with templates given ``margin_px`` of diffraction around their core (plus the spread of
    the first guess's images) so that the window holds every source's light and most of
    its diffraction; outside a template's patch the data still hold its diffraction tail,
    which a cut template would call a residual (at the true layout the residual RMS was
    5-9 σ over the union of 32 px patches, 1.03 σ where every template is whole).
    """

    def __init__(
        self,
        data: list[LayoutData],
        builder: TemplateBuilder,
        cfa_pattern: str,
        first: list[Source],
        margin_px: int,
        inset_px: int,
    ):

        # Every template must cover the whole window, so each is given ``margin_px`` beyond the
        # spread of the first guess's images as well (the window is the patches' intersection).
        # A wider diffraction margin only pads a template's patch (``TemplateBuilder._render``), so
        # the windows follow from the first guess's templates built once, at the builder's margin.
        first_built = [[t for t in (builder.build(s, item.pose) for s in first) if t is not None] for item in data]
        spread = max(
            [max(np.ptp([t.row0 for t in built]), np.ptp([t.col0 for t in built])) for built in first_built if built],
            default=0,
        )
        self.builder = replace(builder, airy_margin_px=max(builder.airy_margin_px, margin_px + int(spread)))
        pad = self.builder.airy_margin_px - builder.airy_margin_px if builder.diffraction else 0
        self.windows = []
        self.window_data: list[int] = []  # which item of ``data`` each window is
        self._columns: dict[tuple[object, int, float, float, float], list[np.ndarray]] = {}
        self._geometry_key: object = None
        for index, (item, built) in enumerate(zip(data, first_built, strict=True)):
            if not built:
                continue
            h, w = item.rate.shape
            top = max(0, max(t.row0 for t in built) - pad + inset_px)
            left = max(0, max(t.col0 for t in built) - pad + inset_px)
            bottom = min(h, min(t.row0 + t.image.shape[1] for t in built) + pad - inset_px)
            right = min(w, min(t.col0 + t.image.shape[2] for t in built) + pad - inset_px)
            if bottom - top < 8 or right - left < 8:
                continue
            rows, cols = np.mgrid[top:bottom, left:right]
            channel = cfa_channels(cfa_pattern, rows, cols)
            rate = np.asarray(item.rate[top:bottom, left:right], float)
            var = np.asarray(item.variance[top:bottom, left:right], float)
            ok = (
                np.asarray(item.usable[top:bottom, left:right], bool) & np.isfinite(rate) & np.isfinite(var) & (var > 0)
            )
            picks = [ok & (channel == c) for c in range(3)]
            weights = [1.0 / np.sqrt(var[pick]) for pick in picks]
            self.window_data.append(index)
            self.windows.append(
                (
                    item.pose,
                    (top, bottom, left, right),
                    channel,
                    picks,
                    weights,
                    [rate[pick] * weight for pick, weight in zip(picks, weights, strict=True)],
                )
            )
        self.pixels = sum(int(np.count_nonzero(pick)) for window in self.windows for pick in window[3])

    def _column(self, p: int, u: float, v: float, radius: float) -> list[np.ndarray]:
        """The template of a unit source at (u, v) over window ``p``: per channel, its values
        at that channel's fitted photosites."""
        key = (self._geometry_key, p, u, v, radius)
        column = self._columns.get(key)
        if column is not None:
            return column
        pose, window, channel, picks, *_ = self.windows[p]
        top, bottom, left, right = window
        image = np.zeros((bottom - top, right - left))
        template = self.builder.build(Source("trial", (u, v), radius), pose)
        if template is not None:
            place_template(template, window, channel, image)
        column = [image[pick] for pick in picks]
        if len(self._columns) >= 64 * len(self.windows):  # a Jacobian's worth several times over; oldest out
            for old in list(self._columns)[: len(self._columns) // 2]:
                del self._columns[old]
        self._columns[key] = column
        return column

    def set_aperture(self, radius: float) -> None:
        """Build the templates through an aperture of ``radius`` from now on (the pixels stay)."""

        self.set_geometry(replace(self.builder.geometry, aperture_radius=radius))

    def set_geometry(self, geometry: RigGeometry, key: object = None) -> None:
        """Build the templates through ``geometry`` from now on (the pixels stay). A ``key`` that
        names the geometry keeps the templates built through it for when it comes back (a
        Jacobian's columns move one number at a time); without one they are dropped."""
        self.builder = replace(self.builder, geometry=geometry)
        self._geometry_key = key
        if key is None:
            self._columns.clear()

    def set_poses(self, poses: list[Pose]) -> None:
        """The light's pose at each window's position (``poses[i]`` for the window of ``data[i]``)."""
        self.windows = [(poses[i], *window[1:]) for i, window in zip(self.window_data, self.windows, strict=True)]

    def solve(self, centres: np.ndarray, radius: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(weighted residuals, intensities (positions, 3, sources)) for discs of ``radius`` (one
        for all, or one per source) at ``centres`` (S, 2), in metres."""
        residuals, intensities = [], np.zeros((len(self.windows), 3, len(centres)))
        for p, (_, _, _, _, weights, targets) in enumerate(self.windows):
            radii = np.broadcast_to(np.asarray(radius, float), (len(centres),))  # one radius, or each source's
            columns = [self._column(p, float(u), float(v), float(r)) for (u, v), r in zip(centres, radii, strict=True)]
            for c in range(3):
                a = np.stack([column[c] for column in columns], axis=1) * weights[c][:, None]
                gram = a.T @ a
                # A source the ball does not show here has a zero column: a ridge keeps Cholesky whole.
                ridge = 1e-12 * max(float(np.trace(gram)), 1e-300) * np.eye(len(columns))
                x = nnls_via_cholesky(a, targets[c], gram + ridge, maxiter=100 * len(columns))
                intensities[p, c] = x
                residuals.append(a @ x - targets[c])
        return np.concatenate(residuals), intensities

    @property
    def blocks(self) -> list[int]:
        """How many residuals each window (one position) gives, in the residuals' order."""
        return [sum(int(np.count_nonzero(pick)) for pick in window[3]) for window in self.windows]

    def centre_sigma(self, centres: np.ndarray, radius: float) -> np.ndarray:
        """Each centre's 1σ (S, 2), metres, at the fitted ``centres`` and common ``radius``: the
        larger of :func:`scaled_sigma` and :func:`clustered_sigma` (one cluster per position), from
        a forward-difference Jacobian over the centres and the radius (10 µm steps, as the fit's)."""
        x = np.append(np.asarray(centres, float).ravel(), radius) * 1e3
        base = self.solve(x[:-1].reshape(-1, 2) * 1e-3, x[-1] * 1e-3)[0]
        jac = np.empty((base.size, x.size))
        for i in range(x.size):
            step = 0.01 * max(1.0, abs(x[i]))
            moved = x.copy()
            moved[i] += step
            jac[:, i] = (self.solve(moved[:-1].reshape(-1, 2) * 1e-3, moved[-1] * 1e-3)[0] - base) / step
        n = x.size - 1
        sigma = np.maximum(scaled_sigma(jac, base, n), clustered_sigma(jac, base, self.blocks, n))
        return sigma.reshape(-1, 2) * 1e-3

    def chi2(self, centres: np.ndarray, radius: float | np.ndarray) -> float:
        r, _ = self.solve(centres, radius)
        return float(r @ r)

    def light(self, centres: np.ndarray, radius: float | np.ndarray) -> np.ndarray:
        """Each source's intensity summed over the positions and channels (0: it explains nothing)."""
        return self.solve(centres, radius)[1].sum(axis=(0, 1))

    def fit(
        self, centres: np.ndarray, radius: float, max_radius: float, max_nfev: int
    ) -> tuple[np.ndarray, float, float]:
        """Centres (S, 2) and the discs' common radius moved to the least χ²; (centres, radius, χ²).

        The radius is fitted because it moves the centres: the ball maps a disc onto the
        sensor unevenly, so a template of the wrong size puts its light's centre elsewhere
        (0.25 mm too large a radius drew sources 4 mm apart 30 µm closer together)."""

        def residuals(x):
            return self.solve(x[:-1].reshape(-1, 2) * 1e-3, x[-1] * 1e-3)[0]

        # In millimetres, so that least_squares' relative step (0.01 of max(1, |x|)) is 10-40 µm:
        # a small fraction of a pixel on the sensor, large against the templates' rounding.
        start = np.append(np.asarray(centres, float).ravel() * 1e3, min(radius, max_radius) * 1e3)
        lower = np.full(start.size, -np.inf)
        upper = np.full(start.size, np.inf)
        lower[-1], upper[-1] = 0.02, max_radius * 1e3
        result = least_squares(
            residuals, start, bounds=(lower, upper), diff_step=0.01, xtol=2e-4, ftol=1e-5, max_nfev=max_nfev
        )
        # result.fun is the residual at result.x: χ² without solving there again.
        return result.x[:-1].reshape(-1, 2) * 1e-3, float(result.x[-1]) * 1e-3, float(result.fun @ result.fun)


def scaled_sigma(jac: np.ndarray, residuals: np.ndarray, n: int) -> np.ndarray:
    """The first ``n`` parameters' 1σ: ``(JᵀJ)⁻¹`` scaled by the residuals' χ² per degree of
    freedom (so that a misfit the noise does not explain widens them)."""
    dof = max(1, residuals.size - jac.shape[1])
    scale = float(residuals @ residuals) / dof
    covariance = np.linalg.pinv(jac.T @ jac) * scale
    return np.sqrt(np.clip(np.diag(covariance)[:n], 0.0, None))


def clustered_sigma(jac: np.ndarray, residuals: np.ndarray, blocks: list[int], n: int) -> np.ndarray:
    """The first ``n`` parameters' 1σ from a sandwich clustered by position (Liang & Zeger 1986):
    ``B M B`` with ``B = (JᵀJ)⁻¹`` and ``M = G/(G−1) Σ_g (J_gᵀ r_g)(J_gᵀ r_g)ᵀ``, one cluster per
    position's pixels (``blocks``, in the residuals' order), every further row (the silhouette's,
    the priors') its own. The pixels of a position share the templates' error there; the
    positions, seen from different places, are the evidence that is close to independent.

    Examples
    --------
    >>> rng = np.random.default_rng(1)
    >>> jac = np.ones((400, 1))  # one number, seen by every pixel alike
    >>> shared = np.repeat(rng.normal(0.0, 1.0, 4), 100)  # each position's pixels off together
    >>> residuals = shared + 0.1 * rng.standard_normal(400)
    >>> bool(clustered_sigma(jac, residuals, [100] * 4, 1)[0] > 5 * scaled_sigma(jac, residuals, 1)[0])
    True
    """
    bread = np.linalg.pinv(jac.T @ jac)
    edges = np.cumsum([0, *blocks])
    scores = [jac[a:b].T @ residuals[a:b] for a, b in zip(edges[:-1], edges[1:], strict=True)]
    scores += [jac[i] * residuals[i] for i in range(int(edges[-1]), residuals.size)]
    groups = len(scores)
    meat = sum(np.outer(g, g) for g in scores) * groups / max(1, groups - 1)
    covariance = bread @ meat @ bread
    return np.sqrt(np.clip(np.diag(covariance)[:n], 0.0, None))
