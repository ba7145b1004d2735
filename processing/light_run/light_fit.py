"""Every source's samples fitted, and the light model assembled with its provenance."""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np

from drivers.contracts.runfile import RunFile
from drivers.contracts.version import __version__
from processing.colour import colour_section, over_theta, relative_luminance
from processing.fit import FitError, Samples, fit_with_model_error
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
