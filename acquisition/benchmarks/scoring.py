"""How a fitted source is scored against the simulated truth.

``docs/measurement.md`` ("The ground-truth reference simulation"): every fit is compared with the truth
emitter it stands for over the θ range its samples cover,
``error = RMS(I_fit − I_true) / max(I_true)``. ``bench accuracy``, ``bench tolerance`` and
``mirrorgonio demo`` all score this way.

Where the light frame the model was made in is not the truth's (the light's mount or the
arm's base frame described off: the model then places the same emission in another frame),
the two are compared as the rig sees them: ``frame``, the model's light frame in the truth's,
maps each direction the samples left in, and each source's place, into the truth's frame.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from drivers.pose import Pose
from processing.fit import FitError, IntensityFit, Samples, fit_intensity
from processing.light_run.records import ProcessReport
from processing.light_run.samples import SourceSamples
from processing.lightmodel import LightModel, SourceModel
from sim_devices.lights import Emitter, TruthLight


def fitted(report: ProcessReport) -> tuple[SourceSamples, LightModel]:
    """The samples and the light model of a processing that ran the ``sources`` step."""
    samples, model = report.samples, report.model
    if not isinstance(samples, SourceSamples) or not isinstance(model, LightModel):
        raise TypeError("the processing made no light model (it ran without the sources step)")
    return samples, model


def score_fit(fit: IntensityFit, truth_emitter: Emitter, theta_samples: ArrayLike) -> tuple[float, float, float]:
    """The error of ``fit`` against ``truth_emitter`` over the θ range of ``theta_samples``.

    Parameters
    ----------
    fit : callable
        The fitted intensity, I(θ) in W/sr for θ in radians.
    truth_emitter
        The truth's emitter (``intensity_w_sr(θ)``).
    theta_samples : array_like
        The θ (radians) of the samples the fit was made from.

    Returns
    -------
    tuple of float
        ``RMS(I_fit − I_true) / max(I_true)`` over 200 angles spanning the samples' θ, and
        that span's ends in degrees.
    """
    lo, hi = float(np.min(theta_samples)), float(np.max(theta_samples))
    grid = np.linspace(lo, hi, 200)
    true = truth_emitter.intensity_w_sr(grid)
    error = math.sqrt(float(np.mean((fit(grid) - true) ** 2))) / float(np.max(true))
    return error, math.degrees(lo), math.degrees(hi)


def score_fit_in_frame(source: SourceModel, truth_emitter: Emitter, frame: Pose) -> tuple[float, float, float]:
    """:func:`score_fit` for a source whose light frame is ``frame`` in the truth's: along the
    directions its samples left in (in the model's frame, in position order, 200 points
    between them), the fit against the truth at the same directions seen in the truth's frame."""
    theta = np.asarray(source.samples["theta"], float)
    phi = np.asarray(source.samples.get("phi") or np.zeros_like(theta), float)
    order = np.argsort(np.asarray(source.samples.get("position") or np.arange(theta.size), float), kind="stable")
    theta, phi = theta[order], phi[order]
    along = np.linspace(0.0, theta.size - 1.0, 200)
    direction = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)
    path = np.stack([np.interp(along, np.arange(theta.size), direction[:, i]) for i in range(3)], axis=-1)
    path /= np.linalg.norm(path, axis=1, keepdims=True)
    model_theta = np.arccos(np.clip(path[:, 2], -1.0, 1.0))
    model_phi = np.arctan2(path[:, 1], path[:, 0])
    seen = path @ frame.rotation.T
    true = truth_emitter.intensity_w_sr(np.arccos(np.clip(seen[:, 2], -1.0, 1.0)), np.arctan2(seen[:, 1], seen[:, 0]))
    error = math.sqrt(float(np.mean((source.fit(model_theta, model_phi) - true) ** 2))) / float(np.max(true))
    return error, math.degrees(float(theta.min())), math.degrees(float(theta.max()))


def source_place(source: SourceModel, frame: Pose | None) -> np.ndarray:
    """A source's centre on the truth's light plane: (u, v), its model frame mapped by ``frame``."""
    centre = np.array([*source.centre_m, 0.0])
    return centre[:2] if frame is None else (frame.rotation @ centre + frame.position)[:2]


def score_sources(
    model: LightModel,
    samples: SourceSamples,
    truth_light: TruthLight,
    *,
    matched: bool,
    fit_method: str = "gaussian",
    cell_sums: bool = True,
    frame: Pose | None = None,
) -> dict:
    """Each truth emitter's fitted source scored against it (:func:`score_fit`).

    ``matched``: the sources were found in the data, so each emitter is scored against the
    nearest source found (``sources[i]["centre_error_um"]`` says how far; ``matched`` in the
    result lists which source each took); otherwise source k is emitter k. ``cell_sums``:
    also score a fit of the chief-ray cell sums at the same positions. ``frame``: the model's
    light frame in the truth's (:func:`score_fit_in_frame`), None where they are one."""
    found = np.array([source_place(s, frame) for s in model.sources], float).reshape(-1, 2)
    out_sources, taken = [], []
    for k, emitter in enumerate(truth_light.emitters):
        if matched:  # the source found nearest the emitter
            distances = np.hypot(*(found - np.asarray(emitter.centre_m, float)).T)
            k = int(np.argmin(distances))
            taken.append(k)
        source = model.sources[k]
        theta = np.asarray(source.samples["theta"])
        if frame is None:
            error, lo, hi = score_fit(source.fit, emitter, theta)
        else:
            error, lo, hi = score_fit_in_frame(source, emitter, frame)
        entry = {
            "name": emitter.name,
            "rms_rel_error": round(error, 6),
            "theta_min_deg": round(lo, 2),
            "theta_max_deg": round(hi, 2),
            "fit": {k2: round(v, 6) for k2, v in source.fit.params.items()},
            "fit_sigma": {k2: round(v, 8) for k2, v in source.fit.uncertainties.items()},
        }
        if matched:
            entry["found_as"] = source.name
            entry["centre_error_um"] = round(1e6 * float(distances[k]), 1)
            offset = found[k] - np.asarray(emitter.centre_m, float)
            entry["centre_offset_um"] = [round(1e6 * float(d), 1) for d in offset]
            if source.centre_sigma_m is not None:
                entry["centre_sigma_um"] = [round(1e6 * s, 2) for s in source.centre_sigma_m]
            entry["found_radius_mm"] = round(1e3 * source.radius_m, 3)
            entry["true_radius_mm"] = round(1e3 * emitter.radius_m, 3)
        entry["coverage"] = coverage(source, emitter, frame)
        if cell_sums:
            entry.update(_score_cell_sums(samples, k, emitter, theta, fit_method))
        if fit_method == "cos-power":
            entry["mu_fit"] = source.fit.params.get("mu")
            entry["mu_true"] = getattr(emitter.intensity, "mu", None)
        out_sources.append(entry)
    result = {"sources": out_sources, "matched": taken, "coverage": coverage_share(out_sources)}
    if matched:
        result |= _relative_places(found[taken], truth_light, out_sources)
    return result


def _relative_places(places: np.ndarray, truth_light: TruthLight, scored_sources: list[dict]) -> dict:
    """The sources' places against the truth's after their common offset: what the data fix
    where the rig's frame is only known up to the turns the self-calibration cannot tell apart
    (the camera's roll or its place around the ball take the light around the ball with them)."""
    offsets = places - np.array([e.centre_m for e in truth_light.emitters], float)
    common = offsets.mean(axis=0)
    for entry, offset in zip(scored_sources, offsets - common, strict=True):
        entry["centre_error_relative_um"] = round(1e6 * float(np.hypot(*offset)), 1)
    return {"centre_offset_um": [round(1e6 * float(x), 1) for x in common]}


#: The truth's parameter each fitted gaussian parameter stands for, in the fit's units.
_GAUSSIAN_TRUTH = {"a": lambda law: law.peak_w_sr, "sigma": lambda law: math.radians(law.sigma_deg)}


def coverage(source: SourceModel, emitter: Emitter, frame: Pose | None) -> dict:
    """How many of the source's quoted 1σ cover the truth: its samples' error bars (each
    sample's intensity against the truth's in the same direction, seen through ``frame``), its
    fit's 1σ band on I(θ, φ) at the same directions, and its fit's parameters (a gaussian's
    peak and width against the truth's gaussian, where the frames agree in direction: a
    turned frame makes the truth's lobe another function)."""
    theta = np.asarray(source.samples["theta"], float)
    phi = np.asarray(source.samples.get("phi") or np.zeros_like(theta), float)
    direction = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)
    if frame is not None:
        direction = direction @ frame.rotation.T
    true = emitter.intensity_w_sr(
        np.arccos(np.clip(direction[:, 2], -1.0, 1.0)), np.arctan2(direction[:, 1], direction[:, 0])
    )
    error = np.abs(np.asarray(source.samples["intensity"], float) - true)
    # The fit's 1σ band at the same directions, against the truth there.
    band_error = np.abs(source.intensity(theta, phi) - true)
    out = {
        "samples_within": int(np.count_nonzero(error <= np.asarray(source.samples["sigma"], float))),
        "samples": int(theta.size),
        "band_within": int(np.count_nonzero(band_error <= source.fit.band(theta, phi))),
        "band": int(theta.size),
    }
    law = getattr(emitter, "intensity", None)
    turned = frame is not None and frame.distance_to(Pose(0.0, 0.0, 0.0))[1] > math.radians(0.2)
    if source.fit.method == "gaussian" and getattr(law, "model", "") == "gaussian" and not turned:
        params = [name for name in _GAUSSIAN_TRUTH if name in source.fit.params]
        within = [
            abs(source.fit.params[name] - _GAUSSIAN_TRUTH[name](law)) <= source.fit.uncertainties[name]
            for name in params
        ]
        out |= {"parameters_within": int(sum(within)), "parameters": len(params)}
    return out


def coverage_share(scored_sources: list[dict]) -> dict:
    """The share of quoted 1σ that cover the truth over all sources: parameters, samples and
    the fits' I(θ) band (a true 1σ covers 68 %)."""
    share = {}
    for kind in ("parameters", "samples", "band"):
        total = sum(entry["coverage"].get(kind, 0) for entry in scored_sources)
        within = sum(entry["coverage"].get(f"{kind}_within", 0) for entry in scored_sources)
        share[kind] = round(within / total, 3) if total else None
    return share


def _score_cell_sums(samples: SourceSamples, k: int, emitter: Emitter, theta: np.ndarray, fit_method: str) -> dict:
    """Source ``k``'s chief-ray cell sums fitted and scored like the source's own fit."""
    ok = np.isfinite(samples.cell_sum[:, k]) & np.isfinite(samples.theta[:, k])
    try:
        cell = Samples(
            samples.theta[ok, k],
            samples.phi[ok, k],
            samples.cell_sum[ok, k],
            np.full(ok.sum(), 0.01 * np.nanmax(samples.cell_sum[:, k])),
        )
        cell_fit = fit_intensity(cell, method=fit_method)
        return {"cell_sum_rms_rel_error": round(score_fit(cell_fit, emitter, theta)[0], 6)}
    except FitError as exc:
        return {"cell_sum_rms_rel_error": None, "cell_sum_note": str(exc)}
