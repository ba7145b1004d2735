"""Every source's samples fitted, and the light model assembled with its provenance."""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np

from drivers.contracts.runfile import RunFile
from drivers.contracts.version import __version__
from processing.colour import THETA_BIN_DEG, binned_colour, colour_section, over_theta, relative_luminance
from processing.fit import FitError, Samples
from processing.fit_model_error import fit_with_model_error
from processing.light_run.errors import ProcessingError
from processing.light_run.samples import SourceSamples
from processing.lightmodel import LightModel, SourceModel, samples_table
from processing.radiometry import radiometric_gain
from processing.unmixing.sources import Source

log = logging.getLogger("mirrorgonio.processing")


def source_colour(intensity_rgb: np.ndarray) -> tuple[float, float, float]:
    """A source's ``(R, G, B)`` (mean 1) from its per-channel intensities at every position
    (n, 3): each channel's sum over the positions where all three are measured, over the
    channel means' sum, so that the strong samples count most. Grey (1, 1, 1) where the
    channels were not measured apart (cell sums) or sum to nothing.

    The colour is taken as one for all directions: an LED's spectrum shifts little with
    angle next to the intensity's own change, and the samples are too few per direction to
    fit a colour each.
    """
    rgb = np.asarray(intensity_rgb, dtype=float).reshape(-1, 3)
    both = np.all(np.isfinite(rgb), axis=1)
    sums = rgb[both].sum(axis=0)
    if not both.any() or not np.all(sums > 0):
        return (1.0, 1.0, 1.0)
    red, green, blue = sums / sums.mean()
    return (float(red), float(green), float(blue))


def source_chromaticity(theta: np.ndarray, intensity_rgb: np.ndarray, camera_colour: dict) -> dict:
    """A source's colour record (:func:`processing.colour.colour_section`) from its samples'
    per-channel intensities, with its colour over θ (:func:`processing.colour.over_theta`);
    empty where the channels were not measured apart (cell sums)."""
    rgb = np.asarray(intensity_rgb, dtype=float).reshape(-1, 3)
    both = np.all(np.isfinite(rgb), axis=1) & np.isfinite(theta)
    sums = rgb[both].sum(axis=0)
    if not both.any() or not np.all(sums > 0):
        return {}
    section = colour_section(sums, camera_colour)
    section["over_theta"] = over_theta(theta[both], rgb[both], camera_colour)
    return section


def _band(source: SourceModel, lo: float, hi: float, nodes: int = 16, n_phi: int = 72) -> tuple[float, float]:
    """``(∫ I_s dΩ, ∫ θ I_s dΩ)`` over ``lo ≤ θ ≤ hi`` (radians): Gauss–Legendre in θ, the mean over
    ``n_phi`` azimuths for a fit that depends on φ."""
    x, w = np.polynomial.legendre.leggauss(nodes)
    theta = 0.5 * (hi - lo) * (x + 1.0) + lo
    weights = 0.5 * (hi - lo) * w * np.sin(theta) * 2.0 * np.pi
    if source.fit.method == "gaussian-2d":
        phi = np.arange(n_phi) * (2.0 * np.pi / n_phi)
        values = source.intensity(theta[:, None], phi[None, :]).mean(axis=1)
    else:
        values = source.intensity(theta)
    return float(np.sum(values * weights)), float(np.sum(theta * values * weights))


def light_over_theta(sources: Sequence[SourceModel], camera_colour: dict, bin_deg: float = THETA_BIN_DEG) -> dict:
    """The whole light's colour over θ: in each bin of ``bin_deg`` up to the largest θ measured, the
    sources' camera RGB weighed by their flux in the bin (``∫ I_s dΩ`` of their fits), each source's
    RGB its own colour in that bin where its samples reach it (``over_theta``), else its mean colour.

    Where the sources' lobes differ in width and their colours differ, the light's colour changes
    with θ though each source's does not; where a source's own colour changes with θ, that counts
    too. The record has the fields of :func:`processing.colour.binned_colour`, ``bin_deg``, the
    ``flux`` per bin (the model's units × sr) and ``theta_max_deg``, the bins' end."""
    top = max(float(s.fit.theta_range[1]) for s in sources)
    edges = np.radians(np.arange(0.0, np.degrees(top) + bin_deg, bin_deg))
    edges = np.minimum(edges[edges < top + np.radians(bin_deg)], top)
    centres, totals, fluxes = [], [], []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        if hi <= lo:
            continue
        mixed, flux, moment = np.zeros(3), 0.0, 0.0
        index = int(np.floor(np.degrees(lo) / bin_deg + 1e-9))
        for s in sources:
            f, m = _band(s, float(lo), float(hi))
            over = s.chromaticity.get("over_theta") or {}
            own = {
                int(np.floor(t / bin_deg)): rgb
                for t, rgb in zip(over.get("theta_deg", []), over.get("camera_rgb", []), strict=False)
            }
            mixed += f * np.asarray(own.get(index, s.colour), dtype=float)
            flux, moment = flux + f, moment + m
        if flux > 0 and np.all(np.isfinite(mixed)) and mixed.sum() > 0:
            centres.append(float(np.degrees(moment / flux)))
            totals.append(mixed)
            fluxes.append(flux)
    out: dict = {"bin_deg": bin_deg, "theta_max_deg": float(np.degrees(top))}
    out.update(binned_colour(centres, np.reshape(totals, (-1, 3)), camera_colour))
    out["flux"] = fluxes
    out["weighting"] = "the sources' camera RGB in each bin weighed by their flux in it"
    return out


def light_chromaticity(sources: Sequence[SourceModel], camera_colour: dict) -> dict:
    """The whole light's colour record: the sources' camera RGB weighed by their flux; empty
    where no source has a colour measured through the channels. Each source's record gets its
    ``relative_luminance`` (:func:`processing.colour.relative_luminance`: its luminance per unit of
    intensity over the light's), which the TM-25 rays' luminous flux is shared by."""
    if not any(s.chromaticity for s in sources):
        return {}
    fluxes = [s.flux() for s in sources]
    mixed = sum((f * np.asarray(s.colour) for s, f in zip(sources, fluxes, strict=True)), np.zeros(3))
    section = colour_section(mixed, camera_colour)
    section["weighting"] = "the sources' camera RGB weighed by their flux"
    section["over_theta"] = light_over_theta(sources, camera_colour)
    if "XYZ" in section:
        shares = relative_luminance([s.colour for s in sources], fluxes, camera_colour)
        for s, share in zip(sources, shares, strict=True):
            if s.chromaticity:
                s.chromaticity["relative_luminance"] = share
    return section


def fit_light_model(
    run: RunFile,
    layout: Sequence[Source],
    samples: SourceSamples,
    *,
    method: str = "gaussian",
    units: str = "relative",
    estimator: str = "",
    footprint: float = float("nan"),
) -> LightModel:
    """Fit every source's samples and assemble the light model."""

    sources = []
    for k, source in enumerate(layout):
        ok = np.isfinite(samples.intensity[:, k]) & np.isfinite(samples.theta[:, k])
        sigma = samples.sigma[:, k][ok]
        if not np.all(np.isfinite(sigma) & (sigma > 0)):
            # Cell sums carry no uncertainty: weight by a constant fraction of the peak.
            sigma = np.full(ok.sum(), 0.01 * max(np.nanmax(samples.intensity[:, k]), 1e-30))
        data = Samples(samples.theta[:, k][ok], samples.phi[:, k][ok], samples.intensity[:, k][ok], sigma)
        try:
            fit, data = fit_with_model_error(data, method=method)
        except FitError as exc:
            raise ProcessingError(f"{run.path}: source {source.name}: {exc}") from None
        table = samples_table(data, samples.positions[ok], samples.cell_sum[:, k][ok])
        sources.append(
            SourceModel(
                source.name,
                source.centre,
                source.radius,
                fit,
                table,
                source_colour(samples.intensity_rgb[:, k]),
                source_chromaticity(samples.theta[:, k], samples.intensity_rgb[:, k], run.header.camera_colour),
                source.centre_sigma,
            )
        )
    provenance = {
        "run_id": run.header.run_id,
        "run_file": str(run.path),
        "rig": run.header.rig.name,
        "software_version": __version__,
        "method": estimator,
        "fit": method,
        "spatial_resolution_m": 2.0 * footprint,
        "gain_e_per_dn": radiometric_gain(run),
        "gain_source": "rig",  # DN/s -> e-/s, as the reflectance step
        # the whole rig, so an object run can check it is lit in the same light frame
        "rig_description": run.header.rig.model_dump(mode="json", exclude_none=True),
    }
    return LightModel(
        sources, units=units, provenance=provenance, chromaticity=light_chromaticity(sources, run.header.camera_colour)
    )
