"""Continuous fits of one source's discrete radiant-intensity samples (``docs/measurement.md``, estimator 5).

The estimator of step 3 or 4 gives one sample of ``I_s(θ, φ)`` per schedule position and
source. This module fits them to a continuous model and reports what the data support:
the residuals, the parameter uncertainties (from the covariance of a fit weighted by the
samples' 1-σ errors, taken as absolute), and the θ (and φ) range the samples cover —
outside it the model is an extrapolation and :meth:`IntensityFit.evaluate` says so.

Methods (``method=``, the keys of :data:`FIT_METHODS`):

``"gaussian"``
    ``I = a·exp(−θ²/2σ²)``; with ``free_centre=True``, ``I = a·exp(−(θ−θ0)²/2σ²)``. The model
    the reference paper used for its simulated sources.
``"polynomial"``
    ``I = Σ_k c_k θ^k`` (θ in radians), weighted linear least squares; the degree is chosen
    by K-fold cross-validation over 1..8 (one-standard-error rule) unless ``degree=`` is
    given. The model the reference paper used for a real LED flashlight.
``"cos-power"``
    ``I = a·cos^μ θ`` (a generalised Lambertian lobe).
``"gaussian-2d"``
    an elliptical lobe ``I = a·exp(−θ²·(cos²(φ−φ0)/2σ₁² + sin²(φ−φ0)/2σ₂²))``, reported with
    σ₁ ≥ σ₂ and φ0 in [0, π), only when the samples cover azimuth (a straight sweep past
    the ball does not).

The non-linear models are fitted by :func:`scipy.optimize.curve_fit` with
``absolute_sigma=True``, started from a weighted log-linear fit. Every failure (too few
samples for the parameters, non-finite data, no convergence, unknown method or option)
raises :class:`FitError` with one line naming the source, the method and the cause.
"""

from __future__ import annotations

import inspect
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import OptimizeWarning, curve_fit

__all__ = ["FIT_METHODS", "FitError", "IntensityFit", "Samples", "fit_intensity"]

_HALF_PI = 0.5 * math.pi
# Samples this close to the axis carry no azimuth.
_AXIS_THETA = 1e-6


class FitError(ValueError):
    """A fit that cannot be made or read (one line: which source and method, and why)."""


# --------------------------------------------------------------------------- the samples


@dataclass(frozen=True)
class Samples:
    """One source's samples, one per schedule position.

    Parameters
    ----------
    theta, phi : array_like (n,)
        Direction of each sample in the light frame, radians: zenith from the light's +z,
        azimuth from +x.
    intensity : array_like (n,)
        Radiant intensity, W/sr (or relative units).
    sigma : array_like (n,)
        Its 1-σ uncertainty, in the same units; finite and positive.
    source : str, optional
        The source's name, used in error messages.
    """

    theta: np.ndarray
    phi: np.ndarray
    intensity: np.ndarray
    sigma: np.ndarray
    source: str = ""

    def __post_init__(self) -> None:
        arrays = {}
        for name in ("theta", "phi", "intensity", "sigma"):
            value = np.atleast_1d(np.asarray(getattr(self, name), dtype=float))
            if value.ndim != 1:
                raise FitError(f"{self._who()}samples: {name} must be one-dimensional, got shape {value.shape}")
            arrays[name] = value
        n = len(arrays["theta"])
        for name, value in arrays.items():
            if len(value) != n:
                raise FitError(f"{self._who()}samples: {name} has {len(value)} values, theta has {n}")
            object.__setattr__(self, name, value)

    def _who(self) -> str:
        return f"source {self.source!r}: " if self.source else ""

    def __len__(self) -> int:
        return len(self.theta)


def _angle_arc(angles: np.ndarray, period: float = 2 * math.pi) -> tuple[float, float]:
    """Smallest arc ``(start, span)`` of a circle of ``period`` holding every angle."""
    if len(angles) == 0:
        return 0.0, 0.0
    a = np.sort(np.mod(angles, period))
    gaps = np.diff(np.concatenate([a, [a[0] + period]]))
    i = int(np.argmax(gaps))  # the largest gap is what the samples do not cover
    start = a[(i + 1) % len(a)]
    span = period - gaps[i]
    return float(start), float(max(span, 0.0))


def _in_arc(angles: ArrayLike, start: float, span: float, period: float = 2 * math.pi, tol: float = 1e-9) -> np.ndarray:
    return np.mod(np.asarray(angles, dtype=float) - start + tol, period) <= span + 2 * tol


# --------------------------------------------------------------------------- the models


def _gaussian(theta: np.ndarray, phi: np.ndarray, p: dict[str, float]) -> np.ndarray:
    t0 = p.get("theta0", 0.0)
    return p["a"] * np.exp(-((theta - t0) ** 2) / (2.0 * p["sigma"] ** 2))


def _polynomial(theta: np.ndarray, phi: np.ndarray, p: dict[str, float]) -> np.ndarray:
    coefficients = [p[f"c{k}"] for k in range(len(p))]
    return np.polynomial.polynomial.polyval(theta, coefficients)


def _cos_power(theta: np.ndarray, phi: np.ndarray, p: dict[str, float]) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        return p["a"] * np.maximum(np.cos(theta), 0.0) ** p["mu"]


def _gaussian_2d(theta: np.ndarray, phi: np.ndarray, p: dict[str, float]) -> np.ndarray:
    d = phi - p["phi0"]
    q = np.cos(d) ** 2 / (2.0 * p["sigma1"] ** 2) + np.sin(d) ** 2 / (2.0 * p["sigma2"] ** 2)
    return p["a"] * np.exp(-(theta**2) * q)


_MODELS: dict[str, Callable[[np.ndarray, np.ndarray, dict[str, float]], np.ndarray]] = {
    "gaussian": _gaussian,
    "polynomial": _polynomial,
    "cos-power": _cos_power,
    "gaussian-2d": _gaussian_2d,
}
_TWO_D = {"gaussian-2d"}


# --------------------------------------------------------------------------- the result


def _enc(x: float) -> float | str:
    """A float for JSON: non-finite values as strings (``"nan"``, ``"inf"``, ``"-inf"``)."""
    x = float(x)
    return x if math.isfinite(x) else repr(x)


def _dec(x: float | str) -> float:
    return float(x)


def _enc_tree(obj):
    """``info`` for JSON: numpy values to plain Python, non-finite floats to strings."""
    if isinstance(obj, dict):
        return {str(k): _enc_tree(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, np.ndarray)):
        return [_enc_tree(v) for v in obj]
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return _enc(obj)
    return obj


@dataclass(eq=False)
class IntensityFit:
    """A continuous fit of one source's radiant intensity.

    Attributes
    ----------
    method : str
        The model, a key of :data:`FIT_METHODS`.
    params : dict of str to float
        Its parameters: angles in radians, intensities in the samples' units.
    uncertainties : dict of str to float
        1-σ uncertainty of each parameter, the square root of the covariance's diagonal
        (``inf`` where the samples do not determine the parameter).
    covariance : ndarray (p, p)
        Covariance of the parameters, in the order of ``params``.
    residuals : ndarray (n,)
        Data minus model at each sample.
    chi2_reduced : float
        ``Σ (residual/σ)² / (n − p)``; about 1 when the model and the stated errors fit.
    n_samples : int
        Number of samples fitted.
    theta_range, phi_range : tuple of float
        What the samples cover, radians. ``phi_range`` is the smallest arc holding every
        sample's azimuth, ``(start, end)`` with ``end`` possibly beyond 2π.
    info : dict
        Method-specific notes (chosen degree and cross-validation scores, warnings).
    """

    method: str
    params: dict[str, float]
    uncertainties: dict[str, float]
    covariance: np.ndarray
    residuals: np.ndarray
    chi2_reduced: float
    n_samples: int
    theta_range: tuple[float, float]
    phi_range: tuple[float, float]
    info: dict[str, Any] = field(default_factory=dict)

    def evaluate(self, theta: ArrayLike, phi: ArrayLike = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """The model at directions ``(θ, φ)`` and whether each one is extrapolated.

        Parameters
        ----------
        theta, phi : array_like
            Directions in the light frame, radians; broadcast against each other.

        Returns
        -------
        values : ndarray
            The model's intensity.
        extrapolated : ndarray of bool
            True outside the θ range the samples cover, or (for 2-D models) outside the
            azimuth arc they cover.
        """
        theta, phi = np.broadcast_arrays(np.asarray(theta, dtype=float), np.asarray(phi, dtype=float))
        values = np.asarray(_MODELS[self.method](theta, phi, self.params), dtype=float)
        lo, hi = self.theta_range
        tol = 1e-9 * max(1.0, abs(hi))
        extrapolated = (theta < lo - tol) | (theta > hi + tol)
        if self.method in _TWO_D:
            start, end = self.phi_range
            outside = ~_in_arc(phi, start, end - start)
            extrapolated = extrapolated | (outside & (theta > _AXIS_THETA))
        return values, extrapolated

    def __call__(self, theta: ArrayLike, phi: ArrayLike = 0.0) -> np.ndarray:
        """The model's intensity at ``(θ, φ)`` (see :meth:`evaluate`)."""
        return self.evaluate(theta, phi)[0]

    def scaled(self, factor: float) -> IntensityFit:
        """The fit of ``factor`` times the intensity: its intensity parameters (``a``, a
        polynomial's coefficients), their covariance and the residuals scaled; its shape and
        its χ² as they were.

        Examples
        --------
        >>> fit = IntensityFit("gaussian", {"a": 2.0, "sigma": 0.3}, {"a": 0.01, "sigma": 0.002},
        ...                    np.diag([1e-4, 4e-6]), np.ones(5), 1.0, 5, (0.0, 0.5), (0.0, 0.0))
        >>> twice = fit.scaled(2.0)
        >>> twice.params, twice.uncertainties["a"], float(twice(0.0)) == 2.0 * float(fit(0.0))
        ({'a': 4.0, 'sigma': 0.3}, 0.02, True)
        """
        names = list(self.params)
        scales = [float(factor) if scales_with else 1.0 for scales_with in intensity_parameters(self.method, names)]
        return IntensityFit(
            self.method,
            {name: self.params[name] * s for name, s in zip(names, scales, strict=True)},
            {name: self.uncertainties[name] * s for name, s in zip(names, scales, strict=True)},
            np.asarray(self.covariance, dtype=float) * np.outer(scales, scales),
            np.asarray(self.residuals, dtype=float) * factor,
            self.chi2_reduced,
            self.n_samples,
            self.theta_range,
            self.phi_range,
            dict(self.info),
        )

    def band(self, theta: ArrayLike, phi: ArrayLike = 0.0) -> np.ndarray:
        """The 1σ of the model's intensity at ``(θ, φ)`` from the parameters' covariance.

        ``σ_I² = J C J^T · max(1, χ²_ν)``: ``J`` the model's gradient in its parameters
        (central differences), the covariance inflated where the residuals say the samples'
        errors are too small. A fit by :func:`fit_with_model_error` holds the templates' model
        error in ``C`` as a scale common to the sweep, so the band is then at least ``ε I``.
        ``inf`` where a parameter is not determined.

        Examples
        --------
        >>> fit = IntensityFit("gaussian", {"a": 2.0, "sigma": 0.3}, {"a": 0.01, "sigma": 0.0},
        ...                    np.diag([1e-4, 0.0]), np.zeros(5), 1.0, 5, (0.0, 0.5), (0.0, 0.0))
        >>> [round(float(v), 4) for v in fit.band([0.0, 0.3])]
        [0.01, 0.0061]
        """
        theta, phi = np.broadcast_arrays(np.asarray(theta, dtype=float), np.asarray(phi, dtype=float))
        names = list(self.params)
        covariance = np.asarray(self.covariance, dtype=float)
        if not np.all(np.isfinite(covariance)) or any(not math.isfinite(self.uncertainties[n]) for n in names):
            return np.full(theta.shape, np.inf)
        model = _MODELS[self.method]
        gradient = np.empty((len(names), *theta.shape))
        for i, name in enumerate(names):
            step = 1e-6 * max(abs(self.params[name]), 1e-3)
            up = model(theta, phi, {**self.params, name: self.params[name] + step})
            down = model(theta, phi, {**self.params, name: self.params[name] - step})
            gradient[i] = (np.asarray(up, dtype=float) - np.asarray(down, dtype=float)) / (2.0 * step)
        variance = np.einsum("i...,ij,j...->...", gradient, covariance, gradient)
        inflation = max(1.0, self.chi2_reduced) if math.isfinite(self.chi2_reduced) else 1.0
        return np.sqrt(np.maximum(variance, 0.0) * inflation)

    def to_dict(self) -> dict[str, Any]:
        """A JSON-able record; :meth:`from_dict` restores it exactly."""
        return {
            "method": self.method,
            "params": {k: _enc(v) for k, v in self.params.items()},
            "uncertainties": {k: _enc(v) for k, v in self.uncertainties.items()},
            "covariance": [[_enc(v) for v in row] for row in np.asarray(self.covariance, dtype=float)],
            "residuals": [_enc(v) for v in np.asarray(self.residuals, dtype=float)],
            "chi2_reduced": _enc(self.chi2_reduced),
            "n_samples": int(self.n_samples),
            "theta_range": [_enc(v) for v in self.theta_range],
            "phi_range": [_enc(v) for v in self.phi_range],
            "info": _enc_tree(self.info),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> IntensityFit:
        """Rebuild a fit from :meth:`to_dict`'s record (:class:`FitError` naming a bad field)."""
        if not isinstance(d, dict):
            raise FitError(f"fit record: expected an object, got {type(d).__name__}")
        missing = [
            k
            for k in (
                "method",
                "params",
                "uncertainties",
                "covariance",
                "residuals",
                "chi2_reduced",
                "n_samples",
                "theta_range",
                "phi_range",
            )
            if k not in d
        ]
        if missing:
            raise FitError(f"fit record: missing {', '.join(missing)}")
        method = d["method"]
        if method not in _MODELS:
            raise FitError(f"fit record: method: unknown {method!r} (known: {', '.join(_MODELS)})")
        try:
            params = {str(k): _dec(v) for k, v in d["params"].items()}
            uncertainties = {str(k): _dec(v) for k, v in d["uncertainties"].items()}
            covariance = np.array([[_dec(v) for v in row] for row in d["covariance"]], dtype=float)
            residuals = np.array([_dec(v) for v in d["residuals"]], dtype=float)
            theta_range = tuple(_dec(v) for v in d["theta_range"])
            phi_range = tuple(_dec(v) for v in d["phi_range"])
            chi2 = _dec(d["chi2_reduced"])
            n = int(d["n_samples"])
        except (TypeError, ValueError, AttributeError) as e:
            raise FitError(f"fit record: {e}") from None
        expected = _expected_params(method, params)
        if set(params) != expected:
            raise FitError(
                f"fit record: params: {method} needs {', '.join(sorted(expected))}, got "
                f"{', '.join(sorted(params)) or 'none'}"
            )
        if covariance.shape != (len(params), len(params)):
            raise FitError(f"fit record: covariance: shape {covariance.shape}, expected {(len(params),) * 2}")
        if len(theta_range) != 2 or len(phi_range) != 2:
            raise FitError("fit record: theta_range and phi_range need two values each")
        info = d.get("info", {})
        if not isinstance(info, dict):
            raise FitError("fit record: info: expected an object")
        return cls(method, params, uncertainties, covariance, residuals, chi2, n, theta_range, phi_range, info)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, IntensityFit):
            return NotImplemented
        return self.to_dict() == other.to_dict()


def _expected_params(method: str, params: dict[str, float]) -> set[str]:
    if method == "gaussian":
        return {"a", "sigma", "theta0"} if "theta0" in params else {"a", "sigma"}
    if method == "polynomial":
        return {f"c{k}" for k in range(max(len(params), 1))}
    if method == "cos-power":
        return {"a", "mu"}
    return {"a", "sigma1", "sigma2", "phi0"}


# --------------------------------------------------------------------------- the estimators


def _label(method: str, samples: Samples) -> str:
    return f"{method} fit of source {samples.source!r}" if samples.source else f"{method} fit"


def _checked(samples: Samples, method: str, n_params: int) -> None:
    """Non-finite data or too few samples end the fit."""
    who = _label(method, samples)
    for name in ("theta", "phi", "intensity", "sigma"):
        bad = int(np.count_nonzero(~np.isfinite(getattr(samples, name))))
        if bad:
            raise FitError(f"{who}: {bad} non-finite {name} value{'s' if bad > 1 else ''}")
    if np.any(samples.sigma <= 0):
        raise FitError(f"{who}: sigma must be positive ({int(np.count_nonzero(samples.sigma <= 0))} are not)")
    if len(samples) < n_params + 1:
        raise FitError(f"{who}: {len(samples)} samples for {n_params} parameters (needs at least {n_params + 1})")


def _ranges(samples: Samples) -> tuple[tuple[float, float], tuple[float, float]]:
    theta_range = (float(np.min(samples.theta)), float(np.max(samples.theta)))
    off_axis = samples.phi[samples.theta > _AXIS_THETA]
    start, span = _angle_arc(off_axis)
    return theta_range, (start, start + span)


def _result(
    method: str,
    names: list[str],
    popt: np.ndarray,
    pcov: ArrayLike,
    samples: Samples,
    info: dict[str, Any] | None = None,
) -> IntensityFit:
    params = {k: float(v) for k, v in zip(names, popt, strict=True)}
    pcov = np.asarray(pcov, dtype=float)
    info = dict(info or {})
    with np.errstate(invalid="ignore"):
        errors = np.sqrt(np.where(np.diag(pcov) >= 0, np.diag(pcov), np.nan))
    # A variance of exactly 0 is SciPy's pseudo-inverse dropping a Jacobian too small to use: not
    # a parameter known perfectly, but one the samples do not determine.
    undetermined = ~np.isfinite(errors) | (errors == 0)
    if not np.all(np.isfinite(pcov)) or np.any(undetermined):
        info["warning"] = "covariance could not be estimated: the samples do not determine every parameter"
    errors = np.where(undetermined, np.inf, errors)
    model = _MODELS[method](samples.theta, samples.phi, params)
    residuals = samples.intensity - model
    dof = len(samples) - len(names)
    chi2 = float(np.sum((residuals / samples.sigma) ** 2) / dof)
    theta_range, phi_range = _ranges(samples)
    return IntensityFit(
        method,
        params,
        {k: float(e) for k, e in zip(names, errors, strict=True)},
        pcov,
        residuals,
        chi2,
        len(samples),
        theta_range,
        phi_range,
        info,
    )


def _curve_fit(
    method: str,
    f: Callable[..., np.ndarray],
    samples: Samples,
    p0: list[float],
    bounds: tuple[float | list[float], float | list[float]] = (-np.inf, np.inf),
) -> tuple[np.ndarray, np.ndarray]:
    who = _label(method, samples)
    x = np.vstack([samples.theta, samples.phi])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OptimizeWarning)
        try:
            popt, pcov = curve_fit(
                f, x, samples.intensity, p0=p0, sigma=samples.sigma, absolute_sigma=True, bounds=bounds, maxfev=20000
            )
        except RuntimeError as e:
            raise FitError(f"{who}: did not converge ({str(e).splitlines()[0]})") from None
        except ValueError as e:
            raise FitError(f"{who}: {str(e).splitlines()[0]}") from None
    if not np.all(np.isfinite(popt)):
        raise FitError(f"{who}: did not converge (non-finite parameters)")
    return popt, pcov


def _log_linear(columns: list[np.ndarray], samples: Samples) -> np.ndarray | None:
    """Weighted least squares of ``ln I`` on ``columns`` over the positive samples (start values)."""
    keep = samples.intensity > 0
    if np.count_nonzero(keep) < len(columns):
        return None
    y = np.log(samples.intensity[keep])
    w = samples.intensity[keep] / samples.sigma[keep]  # 1/σ of ln I
    X = np.column_stack([c[keep] for c in columns])
    coef, *_ = np.linalg.lstsq(X * w[:, None], y * w, rcond=None)
    return coef if np.all(np.isfinite(coef)) else None


def _fit_gaussian(samples: Samples, *, free_centre: bool = False) -> IntensityFit:
    """``I = a·exp(−θ²/2σ²)``, or ``a·exp(−(θ−θ0)²/2σ²)`` with ``free_centre=True``."""
    method = "gaussian"
    names = ["a", "sigma", "theta0"] if free_centre else ["a", "sigma"]
    _checked(samples, method, len(names))
    t = samples.theta
    # Without a downward curvature to start from (a few samples over a few degrees, noise
    # bending them upwards), start broad: σ twice the largest θ, where the lobe is near flat.
    # A start as narrow as the samples' span put them in the far tail (e^-355 of the peak
    # for 3 samples near 5.7°), where no step of the solver changed anything: it returned
    # its start, with "uncertainties" of 0.
    s0 = max(2.0 * float(np.max(np.abs(t))), float(np.ptp(t)), 1e-3)
    a0, t0 = float(np.max(samples.intensity)), float(t[np.argmax(samples.intensity)])
    if free_centre:
        c = _log_linear([np.ones_like(t), t, t**2], samples)
        if c is not None and c[2] < 0:
            s0 = math.sqrt(-1.0 / (2.0 * c[2]))
            t0 = -c[1] / (2.0 * c[2])
            a0 = math.exp(min(c[0] - c[1] ** 2 / (4.0 * c[2]), 700.0))
    else:
        c = _log_linear([np.ones_like(t), t**2], samples)
        if c is not None and c[1] < 0:
            s0, a0 = math.sqrt(-1.0 / (2.0 * c[1])), math.exp(min(c[0], 700.0))
    if free_centre:
        f: Callable[..., np.ndarray] = lambda x, a, s, th0: a * np.exp(-((x[0] - th0) ** 2) / (2.0 * s * s))  # noqa: E731
        p0, bounds = [a0, s0, t0], ([-np.inf, 1e-9, -np.inf], [np.inf, np.inf, np.inf])
    else:
        f = lambda x, a, s: a * np.exp(-(x[0] ** 2) / (2.0 * s * s))  # noqa: E731
        p0, bounds = [a0, s0], ([-np.inf, 1e-9], [np.inf, np.inf])
    popt, pcov = _curve_fit(method, f, samples, p0, bounds)
    return _result(method, names, popt, pcov, samples, {"free_centre": bool(free_centre)})


def _fit_cos_power(samples: Samples) -> IntensityFit:
    """``I = a·cos^μ θ``."""
    method = "cos-power"
    _checked(samples, method, 2)
    who = _label(method, samples)
    if np.any(samples.theta >= _HALF_PI):
        raise FitError(f"{who}: samples at θ ≥ 90° (behind the light plane)")
    t = samples.theta
    a0, mu0 = float(np.max(samples.intensity)), 1.0
    c = _log_linear([np.ones_like(t), np.log(np.cos(t))], samples)
    if c is not None and c[1] > 0:
        a0, mu0 = math.exp(min(c[0], 700.0)), float(c[1])
    f = lambda x, a, mu: a * np.cos(x[0]) ** mu  # noqa: E731
    popt, pcov = _curve_fit(method, f, samples, [a0, mu0])
    return _result(method, ["a", "mu"], popt, pcov, samples)


def _fit_gaussian_2d(samples: Samples, *, min_phi_span: float = math.radians(60.0)) -> IntensityFit:
    """``I = a·exp(−θ²·(cos²(φ−φ0)/2σ₁² + sin²(φ−φ0)/2σ₂²))``.

    The lobe is π-periodic in φ, so the coverage that counts is the azimuth arc of the
    samples modulo 180°; it must reach ``min_phi_span`` (radians, default 60°).
    """
    method = "gaussian-2d"
    _checked(samples, method, 4)
    who = _label(method, samples)
    off_axis = samples.theta > _AXIS_THETA
    _, span = _angle_arc(2.0 * samples.phi[off_axis])  # azimuth modulo π, doubled
    span *= 0.5
    if span < min_phi_span:
        raise FitError(
            f"{who}: the samples span only {math.degrees(span):.1f}° of azimuth (modulo 180°), "
            f"an elliptical lobe needs {math.degrees(min_phi_span):.0f}°: use a 1-D method or a schedule that "
            "covers azimuth"
        )
    t, p = samples.theta, samples.phi
    x, y = t * np.cos(p), t * np.sin(p)
    a0, s10, s20, phi0 = float(np.max(samples.intensity)), max(float(np.max(t)), 1e-3), None, 0.0
    c = _log_linear([np.ones_like(t), x * x, y * y, 2 * x * y], samples)
    if c is not None:
        m = -np.array([[c[1], c[3]], [c[3], c[2]]])
        w, v = np.linalg.eigh(m)
        if np.all(w > 0):
            s10, s20 = math.sqrt(1.0 / (2.0 * w[0])), math.sqrt(1.0 / (2.0 * w[1]))
            phi0 = math.atan2(v[1, 0], v[0, 0])
            a0 = math.exp(min(c[0], 700.0))
    s20 = s10 if s20 is None else s20

    def f(xx, a, s1, s2, f0):
        d = xx[1] - f0
        return a * np.exp(-(xx[0] ** 2) * (np.cos(d) ** 2 / (2 * s1 * s1) + np.sin(d) ** 2 / (2 * s2 * s2)))

    bounds = ([-np.inf, 1e-9, 1e-9, -np.inf], [np.inf, np.inf, np.inf, np.inf])
    popt, pcov = _curve_fit(method, f, samples, [a0, s10, s20, phi0], bounds)
    popt, pcov = np.array(popt, dtype=float), np.array(pcov, dtype=float)
    if popt[1] < popt[2]:  # canonical form: σ₁ ≥ σ₂, φ0 the azimuth of the wider axis
        swap = [0, 2, 1, 3]
        popt, pcov = popt[swap], pcov[np.ix_(swap, swap)]
        popt[3] += 0.5 * math.pi
    popt[3] = popt[3] % math.pi  # the lobe repeats every 180°
    return _result(method, ["a", "sigma1", "sigma2", "phi0"], popt, pcov, samples, {"phi_span_mod_pi": span})


def _wls(theta: np.ndarray, y: np.ndarray, sigma: np.ndarray, degree: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Weighted least squares of a power series in θ; ``(coefficients, covariance)`` or None if singular."""
    X = np.vander(theta, degree + 1, increasing=True)
    A = X / sigma[:, None]
    b = y / sigma
    scale = np.linalg.norm(A, axis=0)
    if np.any(scale == 0):
        return None
    U, s, Vt = np.linalg.svd(A / scale, full_matrices=False)
    if s[-1] <= s[0] * 1e-12:
        return None
    coef = (Vt.T @ ((U.T @ b) / s)) / scale
    cov = ((Vt.T / s**2) @ Vt) / np.outer(scale, scale)
    return coef, cov


def _fit_polynomial(
    samples: Samples, *, degree: int | None = None, max_degree: int = 8, folds: int = 5, rule: str = "one-se"
) -> IntensityFit:
    """``I = Σ_k c_k θ^k``: weighted linear least squares, degree by K-fold cross-validation.

    The samples are sorted by θ and dealt round-robin into ``folds`` folds, so that each
    fold spans the whole range (no fold is an extrapolation). The score of a degree is the
    mean over the folds of the mean squared normalised prediction error ``((I − Î)/σ)²`` of
    the held-out samples. ``rule="one-se"`` (default) takes the lowest degree whose score is
    within one standard error of the best (Hastie, Tibshirani & Friedman, *The Elements of
    Statistical Learning*, 2nd ed., §7.10): degrees beyond the true one win the raw minimum
    by chance about half the time. ``rule="min"`` takes the lowest score.
    """
    method = "polynomial"
    who = _label(method, samples)
    n = len(samples)
    info: dict = {}
    if degree is not None:
        if isinstance(degree, bool) or not isinstance(degree, (int, np.integer)) or degree < 0:
            raise FitError(f"{who}: degree must be a non-negative integer, got {degree!r}")
        degree = int(degree)
        _checked(samples, method, degree + 1)
        info["degree_source"] = "given"
    else:
        if rule not in ("one-se", "min"):
            raise FitError(f"{who}: rule must be 'one-se' or 'min', got {rule!r}")
        _checked(samples, method, 2)
        k = int(min(max(folds, 2), n))
        order = np.argsort(samples.theta, kind="stable")
        fold_of = np.empty(n, dtype=int)
        fold_of[order] = np.arange(n) % k
        smallest_train = n - int(np.max(np.bincount(fold_of)))
        top = min(int(max_degree), smallest_train - 2, n - 2)
        scores: dict[str, float] = {}
        errors: dict[str, float] = {}
        for d in range(1, top + 1):
            per_fold = []
            for j in range(k):
                train, test = fold_of != j, fold_of == j
                fit = _wls(samples.theta[train], samples.intensity[train], samples.sigma[train], d)
                if fit is None:
                    break
                pred = np.polynomial.polynomial.polyval(samples.theta[test], fit[0])
                per_fold.append(float(np.mean(((samples.intensity[test] - pred) / samples.sigma[test]) ** 2)))
            if len(per_fold) == k:
                scores[str(d)] = float(np.mean(per_fold))
                errors[str(d)] = float(np.std(per_fold, ddof=1) / math.sqrt(k))
        if not scores:
            raise FitError(
                f"{who}: {n} samples at {len(np.unique(samples.theta))} distinct θ are too few to choose a "
                "degree by cross-validation"
            )
        best = min(scores, key=lambda d: (scores[d], int(d)))
        limit = scores[best] + (errors[best] if rule == "one-se" else 0.0)
        degree = min(int(d) for d in scores if scores[d] <= limit)
        info.update(degree_source="cross-validation", rule=rule, folds=k, cv_scores=scores, cv_errors=errors)
    fit = _wls(samples.theta, samples.intensity, samples.sigma, degree)
    if fit is None:
        raise FitError(
            f"{who}: degree {degree} is not determined by samples at {len(np.unique(samples.theta))} distinct θ"
        )
    info["degree"] = degree
    return _result(method, [f"c{k}" for k in range(degree + 1)], fit[0], fit[1], samples, info)


FIT_METHODS: dict[str, Callable[..., IntensityFit]] = {
    "gaussian": _fit_gaussian,
    "polynomial": _fit_polynomial,
    "cos-power": _fit_cos_power,
    "gaussian-2d": _fit_gaussian_2d,
}
"""The named estimators of :func:`fit_intensity` (``method=``)."""


def fit_intensity(samples: Samples, method: str = "gaussian", **options: Any) -> IntensityFit:
    """Fit one source's samples to a continuous radiant intensity ``I(θ, φ)``.

    Parameters
    ----------
    samples : Samples
        The source's samples (θ, φ, intensity, 1-σ error), one per position.
    method : str
        A key of :data:`FIT_METHODS`: ``"gaussian"`` (``a·exp(−θ²/2σ²)``; option
        ``free_centre``), ``"polynomial"`` (``Σ c_k θ^k``; options ``degree``, ``max_degree``,
        ``folds``, ``rule``), ``"cos-power"`` (``a·cos^μ θ``) or ``"gaussian-2d"`` (elliptical lobe;
        option ``min_phi_span``).
    **options
        Passed to the estimator.

    Returns
    -------
    IntensityFit
        The parameters, their uncertainties and covariance, residuals (data − model),
        reduced χ² and the covered θ and φ ranges.

    Raises
    ------
    FitError
        Unknown method or option, non-finite data, too few samples, no convergence, or
        (``gaussian-2d``) samples that do not cover azimuth.

    Notes
    -----
    The samples are weighted by their ``sigma`` taken as absolute errors (``curve_fit``
    with ``absolute_sigma=True``), so the uncertainties do not rescale with χ².

    Examples
    --------
    >>> theta = np.radians(np.linspace(3, 41, 66))
    >>> s = Samples(theta, np.zeros(66), 2.0 * np.exp(-theta**2 / (2 * 0.3**2)), np.full(66, 0.01))
    >>> fit = fit_intensity(s, "gaussian")
    >>> round(fit.params["sigma"], 6)
    0.3
    """
    if not isinstance(samples, Samples):
        raise FitError(f"{method} fit: expected Samples, got {type(samples).__name__}")
    estimator = FIT_METHODS.get(method)
    if estimator is None:
        raise FitError(f"{_label(str(method), samples)}: unknown method (known: {', '.join(FIT_METHODS)})")
    allowed = [p.name for p in inspect.signature(estimator).parameters.values() if p.kind is p.KEYWORD_ONLY]
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise FitError(
            f"{_label(method, samples)}: unknown option {', '.join(unknown)} (allowed: {', '.join(allowed) or 'none'})"
        )
    return estimator(samples, **options)


def intensity_parameters(method: str, names: list[str]) -> list[bool]:
    """Which of a fit's parameters are in intensity units (they scale with the intensity): a
    gaussian's or a cos-power's ``a``, a polynomial's coefficients."""
    return [name == "a" or method == "polynomial" for name in names]
