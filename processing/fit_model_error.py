"""Fits whose uncertainties hold the templates' model error: :func:`fit_with_model_error`
(``docs/light-model.md``, "The samples' σ carry the model error" and "Uncertainties")."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
from scipy.optimize import brentq

from processing.fit import IntensityFit, Samples, fit_intensity, intensity_parameters


def fit_with_model_error(samples: Samples, method: str = "gaussian", **options: Any) -> tuple[IntensityFit, Samples]:
    """:func:`fit_intensity` with each sample's σ widened by the estimate's model error.

    A sample's σ from the unmixing counts the pixels' photon and read noise only; the templates'
    own error (their point spread, the rig's last error) moves every sample by more, in
    proportion to its intensity. So the model error is estimated from the fit's residuals as a
    fraction ε of the fitted intensity, the one for which ``Σ r²/(σ² + ε²m²) = n − p`` (the
    Birge ratio made 1 with a term of the right form), and the fit made again with
    ``σ' = √(σ² + ε²m²)``: its uncertainties then cover the scatter the data show. ε is 0 where
    the noise alone explains the residuals.

    Returns
    -------
    (IntensityFit, Samples)
        The fit with the widened σ (``info["model_error"]`` is ε, ``info["chi2_reduced_noise"]``
        the reduced χ² with the noise alone) and the samples with the widened σ.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> theta = np.radians(np.linspace(3, 41, 66))
    >>> truth = 2.0 * np.exp(-theta**2 / (2 * 0.3**2))
    >>> measured = truth * (1 + 0.05 * rng.standard_normal(66))  # 5 % model error, σ says 0.1 %
    >>> fit, widened = fit_with_model_error(Samples(theta, np.zeros(66), measured, 0.001 * truth))
    >>> round(fit.info["model_error"], 2), round(fit.chi2_reduced, 3)
    (0.05, 1.0)
    """
    fit = fit_intensity(samples, method, **options)
    noise_only, widened, epsilon = fit.chi2_reduced, samples, 0.0
    for _ in range(2):  # the fit moves a little with its weights; twice is settled to 1e-3 of ε
        model = np.abs(samples.intensity - fit.residuals)
        epsilon = _model_error(samples.sigma, fit.residuals, model, len(fit.params))
        if epsilon == 0.0:
            break
        widened = replace(samples, sigma=np.sqrt(samples.sigma**2 + (epsilon * model) ** 2))
        fit = fit_intensity(widened, method, **options)
    fit.info["model_error"] = round(epsilon, 6)
    fit.info["chi2_reduced_noise"] = round(noise_only, 4)
    return _with_scale_error(fit, epsilon), widened


def _with_scale_error(fit: IntensityFit, epsilon: float) -> IntensityFit:
    """``fit`` with a scale error ε common to all its samples in its covariance.

    The templates are one model for every position (their point spread, the rig's last error):
    the part of their error that the widened σ treats as independent averages down over the
    samples, but a share of it is common to the sweep and does not. Taken whole as a common
    scale (the conservative reading: ``docs/light-model.md``, "Uncertainties"), it adds
    ``ε² p pᵀ`` to the covariance, ``p`` the intensity parameters (0 for the shape's), so that
    the intensity's band is at least ``ε I`` everywhere.
    """
    if epsilon <= 0.0:
        return fit
    names = list(fit.params)
    p = np.array(
        [
            fit.params[n] if scales else 0.0
            for n, scales in zip(names, intensity_parameters(fit.method, names), strict=True)
        ]
    )
    covariance = np.asarray(fit.covariance, dtype=float) + epsilon**2 * np.outer(p, p)
    uncertainties = {
        n: (math.sqrt(covariance[i, i]) if math.isfinite(fit.uncertainties[n]) else math.inf)
        for i, n in enumerate(names)
    }
    return replace(fit, covariance=covariance, uncertainties=uncertainties)


def _model_error(sigma: np.ndarray, residuals: np.ndarray, model: np.ndarray, parameters: int) -> float:
    """The ε ≥ 0 with ``Σ r²/(σ² + ε²m²) = n − p`` (0 where the noise explains ``r``)."""
    dof = max(1, residuals.size - parameters)

    def excess(epsilon: float) -> float:
        return float(np.sum(residuals**2 / (sigma**2 + (epsilon * model) ** 2))) - dof

    if excess(0.0) <= 0.0:
        return 0.0
    high = 1.0
    while excess(high) > 0.0 and high < 1e3:
        high *= 4.0
    return float(brentq(excess, 0.0, high, xtol=1e-6))
