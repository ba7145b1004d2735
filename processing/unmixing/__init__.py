"""From merged radiance to per-source samples of radiant intensity I_s(θ).

The camera's point spread is large (``docs/measurement.md``: a 0.2 mm pinhole blurs a point
into a 38 px disc while five sources 4 mm apart image 7–12 px apart), so a pixel's chief
ray does not say which source its light came from. The estimate that counts unmixes: for
every source and position a *template* — the image that source alone would make at unit
intensity — and a variance-weighted non-negative least-squares solve for all sources'
intensities at once.

A template is built from exact specular paths, not from the chief-ray map: from the
source's centre, the path reflecting off the sphere into each point of the pinhole's rim
gives the blur's outline on the sensor (the aperture projected through the mirror, with
its astigmatism), and the set of those paths gives the solid angle the aperture subtends
at the source through the mirror. The blur is uniform inside the outline, convolved with
the source disc's own small image and with the Airy pattern of the aperture at the
channel's wavelength (its exact transfer function, band-limited below the pixel Nyquist
frequency). Its scale follows from radiometry alone::

    Σ_pixels rate = k f² / (A_pixel A_aperture) · F(α) · Ω · I

with ``k`` the camera's sensitivity (e⁻/s per unit radiance), ``f`` the sensor distance,
``F`` the ball's reflectance and ``Ω`` that solid angle.

The flux-conserving chief-ray cell sums of ``docs/measurement.md`` (estimator 4) are here too, as the
fast path for sources farther apart than the footprint of a pixel on the light plane.

Modules, in the order the data flow through them: :mod:`~processing.unmixing.sources` (the
sources' layout), :mod:`~processing.unmixing.psf` (the point spread),
:mod:`~processing.unmixing.templates`, :mod:`~processing.unmixing.unmix` (one position's
intensities), :mod:`~processing.unmixing.cell_flux` (the fast path),
:mod:`~processing.unmixing.problem` (the templates' χ² over a few positions),
:mod:`~processing.unmixing.search` (the sources found in the data) and
:mod:`~processing.unmixing.camera_fit` (the camera's numbers fitted to the data).
"""

from processing.unmixing.camera_fit import ApertureFit, SensorDistanceFit, fit_aperture, fit_sensor_distance
from processing.unmixing.cell_flux import cell_pixel_boxes, cell_sums
from processing.unmixing.problem import LayoutData, LayoutProblem
from processing.unmixing.search import (
    LayoutFit,
    candidate_grid,
    candidate_strength,
    lit_box,
    refine_layout,
    seeds_from_strength,
    sources_from_strength,
)
from processing.unmixing.sources import Source, SourcesError, load_layout
from processing.unmixing.templates import Template, TemplateBuilder
from processing.unmixing.unmix import PositionEstimate, unmix_position

__all__ = [
    "candidate_grid",
    "candidate_strength",
    "cell_pixel_boxes",
    "cell_sums",
    "fit_aperture",
    "fit_sensor_distance",
    "lit_box",
    "load_layout",
    "refine_layout",
    "seeds_from_strength",
    "sources_from_strength",
    "unmix_position",
    "ApertureFit",
    "LayoutData",
    "LayoutFit",
    "LayoutProblem",
    "PositionEstimate",
    "SensorDistanceFit",
    "Source",
    "SourcesError",
    "Template",
    "TemplateBuilder",
]
