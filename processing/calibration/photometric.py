"""Absolute photometry: the camera's photometric scale from a reference, and a light model in
candela and lumens through it (``docs/lab-guide.md``, "Absolute photometry").

The light model's intensity is the camera's signal: the channels' mean, per unit of the rig's
described gain and sensitivity. One number turns it into luminous intensity, candela per unit,
and it is a property of the camera (its pinhole, sensor and electronics), not of the light:
measured once against a reference, it holds for every run the camera takes.

Two references a lab can have (CIE 121, LM-79's "absolute photometry" with a calibrated
detector):

- **a reference lamp** of known luminous intensity in a stated direction (a standard lamp's
  certificate), mounted on the arm in place of the light and swept like one: the scale is the
  certificate's candela over the model's intensity of the lamp in that direction;
- **an illuminance meter's** reading at a known point in front of the light under test, the
  meter's head facing it: the scale is the reading over the model's illuminance there,
  computed in the near field (each source an inverse-square point,
  :meth:`processing.lightmodel.LightModel.irradiance`), each source weighed by its luminance.

A light of another colour than the reference gives another luminance per unit of camera
signal: the scale is carried over by the ratio of the two luminances through the camera's
colour matrices (:func:`processing.colour.luminance_over_reference`), and the matrices'
disagreement is taken as its uncertainty (a three-channel camera has a spectral mismatch,
CIE 53's f1′ for a photometer).

The 1σ of the scale combines, as independent fractions: the reference's own (the certificate's
or the meter's), the model's intensity where it was compared (its fit's covariance,
:meth:`processing.fit.IntensityFit.band`) and, for a meter, its placing (``position_uncertainty_m``
along the line to the light: the inverse square's slope). A light measured later adds its own
colour's mismatch and its fit's band at every angle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from drivers.contracts.photometric import PhotometricCalibration
from drivers.contracts.rig import Camera
from processing.colour import (
    PLANCKIAN_DUV,
    camera_to_xyz,
    chromaticity,
    luminance_over_reference,
    planckian_luminance_ratios,
)
from processing.lightmodel import LightModel, SourceModel

#: A source holding this share of a reference lamp's model's flux is the lamp; the others are
#: taken as the search's strays (a reflection, a hot pixel's streak) and named in an error if
#: no source holds it.
LAMP_FLUX_SHARE = 0.95


#: How far beyond the θ its sweep measured a lamp's certificate direction may lie (degrees): a
#: sweep that passes a few degrees off the axis still gives the on-axis intensity of a smooth lobe,
#: the fit's band saying how well.
EXTRAPOLATION_DEG = 5.0


class PhotometryError(ValueError):
    """A reference or a calibration that cannot give the camera's photometric scale (one line)."""


@dataclass(frozen=True)
class LampReference:
    """A reference lamp of known luminous intensity ``candela`` (1σ ``relative_uncertainty``)
    in the direction ``(theta_rad, phi_rad)`` of the light frame; ``source``: the lamp's source
    in the model (the only one, or the one holding :data:`LAMP_FLUX_SHARE` of the flux, if None)."""

    candela: float
    relative_uncertainty: float
    theta_rad: float = 0.0
    phi_rad: float = 0.0
    source: str | None = None
    name: str = "reference lamp"


@dataclass(frozen=True)
class MeterReference:
    """An illuminance meter reading ``lux`` (1σ ``relative_uncertainty``) at ``point_m`` of the
    light frame, its head facing the light frame's origin; its place known to
    ``position_uncertainty_m`` (1σ)."""

    lux: float
    relative_uncertainty: float
    point_m: tuple[float, float, float]
    position_uncertainty_m: float = 0.001
    name: str = "illuminance meter"


def _fluxes_and_colours(model: LightModel) -> tuple[np.ndarray, np.ndarray]:
    """Each source's flux (model units × sr) and its colour (camera RGB, mean 1)."""
    return (
        np.array([s.flux() for s in model.sources]),
        np.array([np.asarray(s.colour, dtype=float) for s in model.sources]),
    )


def model_unit(model: LightModel) -> tuple[float, float]:
    """``(gain_e_per_dn, sensitivity_e_per_s)`` that defined ``model``'s unit of intensity."""
    gain = model.provenance.get("gain_e_per_dn")
    camera = (model.provenance.get("rig_description") or {}).get("camera") or {}
    sensitivity = camera.get("sensitivity_e_per_s")
    if not (isinstance(gain, (int, float)) and gain > 0 and isinstance(sensitivity, (int, float)) and sensitivity > 0):
        raise PhotometryError(
            "light model: provenance: no gain_e_per_dn and rig_description.camera.sensitivity_e_per_s "
            "(a model written by mirrorgonio process has them): its unit of intensity is unknown"
        )
    return float(gain), float(sensitivity)


def _lamp_source(model: LightModel, name: str | None) -> SourceModel:
    if name is not None:
        try:
            return model.source(name)
        except ValueError as exc:
            raise PhotometryError(f"--source: {exc}") from None
    flux = np.array([s.flux() for s in model.sources])
    strongest = int(np.argmax(flux))
    if len(model.sources) > 1 and flux[strongest] < LAMP_FLUX_SHARE * flux.sum():
        names = ", ".join(s.name for s in model.sources)
        raise PhotometryError(
            f"the reference's light model has {len(model.sources)} sources ({names}) and none holds "
            f"{LAMP_FLUX_SHARE:.0%} of the flux: name the lamp's with --source"
        )
    return model.sources[strongest]


def _check_uncertainty(value: float, what: str) -> None:
    if not (math.isfinite(value) and 0.0 <= value < 1.0):
        raise PhotometryError(f"{what}: a 1-sigma fraction in [0, 1) (got {value:g})")


def calibrate(
    model: LightModel,
    reference: LampReference | MeterReference,
    *,
    run_id: str | None = None,
    made_utc: str | None = None,
) -> PhotometricCalibration:
    """The camera's photometric scale from ``model`` (the reference lamp's run, or the light
    the meter read) and ``reference``.

    Returns
    -------
    drivers.contracts.rig.PhotometricCalibration
        To be stored as the rig's ``[camera.photometric]``.

    Raises
    ------
    PhotometryError
        One line naming the option or the field: a direction outside the measured range, a
        meter behind the light or where the model gives no light, a model without its unit.

    Examples
    --------
    >>> from processing.fit import IntensityFit
    >>> fit = IntensityFit("gaussian", {"a": 2.0, "sigma": 0.5}, {"a": 0.002, "sigma": 0.001},
    ...                    np.diag([4e-6, 1e-6]), np.zeros(9), 1.0, 9, (0.0, 0.6), (0.0, 0.0))
    >>> unit = {"gain_e_per_dn": 5.0, "rig_description": {"camera": {"sensitivity_e_per_s": 1e3}}}
    >>> lamp = LightModel([SourceModel("lamp", (0.0, 0.0), 0.0005, fit)], provenance=unit)
    >>> scale = calibrate(lamp, LampReference(candela=150.0, relative_uncertainty=0.01))
    >>> scale.candela_per_unit, round(scale.relative_uncertainty, 5)
    (75.0, 0.01005)
    """
    gain, sensitivity = model_unit(model)
    _check_uncertainty(reference.relative_uncertainty, "reference uncertainty")
    if isinstance(reference, LampReference):
        if not (math.isfinite(reference.candela) and reference.candela > 0):
            raise PhotometryError(f"--reference-cd: a luminous intensity > 0 (got {reference.candela:g})")
        source = _lamp_source(model, reference.source)
        lo, hi = source.fit.theta_range
        reach = math.radians(EXTRAPOLATION_DEG)
        if not lo - reach <= reference.theta_rad <= hi + reach:
            raise PhotometryError(
                f"--theta-deg: {math.degrees(reference.theta_rad):g} deg lies more than {EXTRAPOLATION_DEG:g} deg "
                f"outside the θ the sweep measured the lamp at ({math.degrees(lo):.1f}-{math.degrees(hi):.1f} deg)"
            )
        intensity = float(source.intensity(reference.theta_rad, reference.phi_rad))
        sigma = float(source.fit.band(reference.theta_rad, reference.phi_rad))
        if not intensity > 0:
            raise PhotometryError(f"source {source.name}: no intensity in the reference's direction")
        scale = reference.candela / intensity
        fractions = [reference.relative_uncertainty, sigma / intensity]
        colour = np.asarray(source.colour, dtype=float)
        what = (
            f"{reference.name}: {reference.candela:g} cd ± {100 * reference.relative_uncertainty:.2g} % at θ "
            f"{math.degrees(reference.theta_rad):g}°, φ {math.degrees(reference.phi_rad):g}° (source {source.name})"
        )
    else:
        scale, fractions, colour = _meter_scale(model, reference)
        x, y, z = reference.point_m
        what = (
            f"{reference.name}: {reference.lux:g} lx ± {100 * reference.relative_uncertainty:.2g} % at "
            f"({1e3 * x:g}, {1e3 * y:g}, {1e3 * z:g}) mm of the light frame, facing the light"
        )
    uncertainty = math.sqrt(sum(f * f for f in fractions))
    if not (math.isfinite(scale) and scale > 0 and uncertainty < 1.0):
        raise PhotometryError(f"the reference gives no usable scale ({scale:g} cd per unit ± {uncertainty:.0%})")
    return PhotometricCalibration(
        candela_per_unit=scale,
        relative_uncertainty=uncertainty,
        reference_camera_rgb=(float(colour[0]), float(colour[1]), float(colour[2])),
        gain_e_per_dn=gain,
        sensitivity_e_per_s=sensitivity,
        reference=what,
        run_id=run_id,
        made_utc=made_utc,
    )


def _luminous_terms(
    model: LightModel, luminance: np.ndarray, point: np.ndarray, facing: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Each source's illuminance at ``point`` on a surface facing ``facing``, weighed by its
    luminance, and each term's 1σ from its fit's band."""
    terms, sigmas = np.zeros(len(model.sources)), np.zeros(len(model.sources))
    for i, (source, weight) in enumerate(zip(model.sources, luminance, strict=True)):
        alone = LightModel([source], provenance=model.provenance)
        terms[i] = weight * float(alone.irradiance(point[None, :], facing)[0])
        d = point - np.array([source.centre_m[0], source.centre_m[1], 0.0])
        theta, phi = math.acos(min(1.0, d[2] / float(np.linalg.norm(d)))), math.atan2(d[1], d[0])
        value = float(source.intensity(theta, phi))
        sigmas[i] = terms[i] * float(source.fit.band(theta, phi)) / value if value > 0 else 0.0
    return terms, sigmas


def _meter_scale(model: LightModel, reference: MeterReference) -> tuple[float, list[float], np.ndarray]:
    """The scale, its 1σ fractions and the light's mean colour from an illuminance reading."""
    if not (math.isfinite(reference.lux) and reference.lux > 0):
        raise PhotometryError(f"--illuminance-lux: a reading > 0 (got {reference.lux:g})")
    if not (math.isfinite(reference.position_uncertainty_m) and reference.position_uncertainty_m >= 0):
        raise PhotometryError(f"--position-uncertainty-m: a length >= 0 (got {reference.position_uncertainty_m:g})")
    point = np.asarray(reference.point_m, dtype=float)
    if not (np.all(np.isfinite(point)) and point[2] > 0):
        raise PhotometryError("--meter-at: the meter must be in front of the light (z > 0 in the light frame)")
    distance = float(np.linalg.norm(point))
    facing = -point / distance
    luminance = np.array([float(s.chromaticity.get("relative_luminance", 1.0)) for s in model.sources])
    terms, sigmas = _luminous_terms(model, luminance, point, facing)
    illuminance = float(terms.sum())
    if not illuminance > 0:
        raise PhotometryError("--meter-at: the light model gives no light there")
    # The placing's share: the illuminance's slope along the line to the light.
    step = 1e-4 * distance
    farther = float(_luminous_terms(model, luminance, point * (1.0 + step / distance), facing)[0].sum())
    fractions = [
        reference.relative_uncertainty,
        float(np.sqrt(np.sum(sigmas**2))) / illuminance,
        abs(illuminance - farther) / step / illuminance * reference.position_uncertainty_m,
    ]
    flux, colours = _fluxes_and_colours(model)
    # The relative luminances are over the flux-weighted mean colour's: that colour is the reference's.
    mixed = flux @ colours / float(flux.sum())
    return reference.lux / illuminance, fractions, mixed / mixed.mean()


def luminance_ratios(
    model: LightModel,
    fluxes_and_colours: tuple[np.ndarray, np.ndarray],
    reference_rgb: tuple[float, float, float] | None,
    camera_colour: dict[str, Any],
    camera: Camera,
) -> tuple[np.ndarray, np.ndarray, str]:
    """Each source's luminance per unit of camera signal over the reference's, and each
    ratio's 1σ (a fraction), with how they were found.

    Where the source and the reference lie near the Planckian locus (|Duv| at most
    :data:`~processing.colour.PLANCKIAN_DUV`), their spectra are taken as blackbodies' at
    their measured CCTs through the camera's described channels
    (:func:`~processing.colour.planckian_luminance_ratios`), and the 1σ is half the
    difference from the colour matrices' estimate; elsewhere the matrices' estimate, its 1σ
    the two matrices' disagreement. Without colour matrices or a reference colour: 1, the
    light taken as of the reference's spectrum (1σ 0, said in the note).
    """
    n = len(model.sources)
    if reference_rgb is None or not camera_colour:
        note = "camera signal only (no colour matrices, or no reference colour): for lights of the reference's spectrum"
        return np.ones(n), np.zeros(n), note
    flux, colours = fluxes_and_colours
    matrix, disagreement = luminance_over_reference(colours, flux, reference_rgb, camera_colour)
    reference = chromaticity(camera_to_xyz(reference_rgb, camera_colour))
    near = [
        s.chromaticity.get("cct_k") is not None and abs(float(s.chromaticity.get("duv", math.inf))) <= PLANCKIAN_DUV
        for s in model.sources
    ]
    if reference["cct_k"] is None or abs(reference["duv"]) > PLANCKIAN_DUV or not any(near):
        return matrix, 2.0 * disagreement, "the colour matrices' luminance over the reference's"
    planckian = planckian_luminance_ratios(
        [s.chromaticity["cct_k"] if ok else None for s, ok in zip(model.sources, near, strict=True)],
        float(reference["cct_k"]),
        camera,
    )
    ratios = np.where(near, planckian, matrix)
    sigma = np.where(near, 0.5 * np.abs(planckian - matrix) / planckian, 2.0 * disagreement)
    note = (
        "blackbodies at the measured CCTs through the camera's described channels (spectral-mismatch "
        "correction; the colour matrices' estimate for a light off the Planckian locus)"
    )
    return ratios, sigma, note


def absolute_photometry(
    model: LightModel,
    calibration: PhotometricCalibration,
    camera_colour: dict[str, Any],
    camera: Camera,
    origin: str,
) -> dict[str, Any]:
    """``model`` in candela and lumens through the camera's ``calibration``: the record the light
    model keeps as ``photometry.absolute`` (``docs/light-model.md``, "Absolute photometry").

    Parameters
    ----------
    model : LightModel
        Fitted, with its sources' colours and chromaticity.
    calibration : drivers.contracts.rig.PhotometricCalibration
        The camera's scale (the rig's ``[camera.photometric]``).
    camera_colour : dict
        The run's colour matrices (empty: the camera signal only, the light taken as the
        reference's colour).
    camera : drivers.contracts.rig.Camera
        The camera as described: its channels carry the scale across colours.
    origin : str
        Where the calibration was read (said in the record).
    """
    gain, sensitivity = model_unit(model)
    # The same camera described with another gain or sensitivity gives other model units.
    rescaled = (calibration.gain_e_per_dn / calibration.sensitivity_e_per_s) / (gain / sensitivity)
    scale = calibration.candela_per_unit * rescaled
    flux, colours = _fluxes_and_colours(model)
    ratios, spectral, colour_note = luminance_ratios(
        model, (flux, colours), calibration.reference_camera_rgb, camera_colour, camera
    )
    sources: list[dict[str, Any]] = []
    for source, ratio, mismatch, source_flux in zip(model.sources, ratios, spectral, flux, strict=True):
        per_unit = scale * float(ratio)
        fraction = math.hypot(calibration.relative_uncertainty, float(mismatch))
        theta = np.linspace(*source.fit.theta_range, 91)
        values = source.intensity(theta)
        peak = int(np.argmax(values))
        band = float(source.fit.band(theta[peak]))
        peak_fraction = math.hypot(fraction, band / float(values[peak])) if values[peak] > 0 else math.inf
        sources.append(
            {
                "name": source.name,
                "candela_per_unit": per_unit,
                "relative_uncertainty": fraction,
                "spectral_mismatch": float(mismatch),
                "peak_cd": per_unit * float(values[peak]),
                "peak_cd_sigma": per_unit * float(values[peak]) * peak_fraction,
                "peak_theta_deg": math.degrees(float(theta[peak])),
                "flux_lm": per_unit * float(source_flux),
            }
        )
    total = float(sum(s["flux_lm"] for s in sources))
    # The scale is common to every source (correlated); the colours' corrections independent.
    common = calibration.relative_uncertainty * total
    own = math.sqrt(sum((s["flux_lm"] * s["spectral_mismatch"]) ** 2 for s in sources))
    return {
        "intensity_units": "cd",
        "flux_units": "lm",
        "candela_per_unit": total / float(flux.sum()) if flux.sum() > 0 else scale,
        "reference_candela_per_unit": scale,
        "relative_uncertainty": math.hypot(calibration.relative_uncertainty, own / total if total > 0 else 0.0),
        "flux_lm": total,
        "flux_lm_sigma": math.hypot(common, own),
        "colour": colour_note,
        "calibration": {
            "from": origin,
            "reference": calibration.reference,
            "run_id": calibration.run_id,
            "made_utc": calibration.made_utc,
            "candela_per_unit": calibration.candela_per_unit,
            "relative_uncertainty": calibration.relative_uncertainty,
            "rescaled_by": rescaled,
        },
        "sources": sources,
    }


def luminous_model(model: LightModel, record: dict[str, Any]) -> LightModel:
    """``model`` with each source's intensity weighed by its luminance per unit over the
    reference's (``photometry.absolute``): the light files' model, whose every unit is then
    ``record["reference_candela_per_unit"]`` candela whatever the source's colour (its
    ``relative_luminance`` 1: the weighing is in the intensity)."""
    scale = float(record["reference_candela_per_unit"])
    per_source = {entry["name"]: float(entry["candela_per_unit"]) / scale for entry in record["sources"]}
    sources = [
        replace(
            source,
            fit=source.fit.scaled(per_source[source.name]),
            chromaticity={**source.chromaticity, "relative_luminance": 1.0} if source.chromaticity else {},
        )
        for source in model.sources
    ]
    return replace(model, sources=sources)


def luminous_intensity(record: dict[str, Any], source: SourceModel, theta: Any, phi: Any = 0.0) -> tuple[Any, Any]:
    """A source's luminous intensity (cd) and its 1σ at ``(θ, φ)`` from the light model's
    ``photometry.absolute`` record: the scale's and the colour's uncertainty with the fit's band."""
    entry = next(s for s in record["sources"] if s["name"] == source.name)
    values = entry["candela_per_unit"] * source.intensity(theta, phi)
    band = entry["candela_per_unit"] * source.fit.band(theta, phi)
    return values, np.hypot(values * entry["relative_uncertainty"], band)
