"""What the simulated camera sees of the mirrored ball: backward ray tracing.

Written from the physics of ``measurement.md`` and deliberately independent of
:mod:`processing` (which has its own tracer), so that the two cannot share a mistake.

A pixel's value is the average, over the pixel's area and the whole aperture, of the
radiance each ray brings back, times the ball's Fresnel reflectance and the ``cos⁴``
fall-off of a flat sensor behind a pinhole (or thin lens)::

    rate = k · ⟨ L(u, v, θ, φ) · F(α) · cos⁴β ⟩_pixel × aperture

with ``k`` the camera's ``sensitivity_e_per_s``. Diffraction is applied afterwards as
the exact optical transfer function of a circular aperture at each channel's
wavelength (the Airy pattern), which is band-limited well below the pixel Nyquist
frequency at the default f/125, so the FFT product is exact.

The blur is large (the aperture's projection is ~38 px across at the defaults) while a
0.5 mm source's pre-image in the aperture is tiny, so sampling the aperture blindly would
need thousands of rays per pixel. Instead, for each pixel and emitter the renderer finds,
by Newton's method on the exact trace, the aperture point whose ray lands on the
emitter's centre, linearises the map around it, and samples only an ellipse 1.5 times
the emitter's pre-image; every sample is then traced exactly, so the estimate stays
unbiased as long as the ellipse covers the true pre-image (the renderer reports the
fraction of hits in the ellipse's outer rim to check it). Emitters larger than the
aperture's footprint are sampled over the whole aperture instead.

An optional uniform *environment* (``environment_radiance``, for calibration images) is
the ball reflecting a radiance ``L_env`` from every direction that meets neither the light's
housing (its face included) nor an emitter; the housing also hides the ball where it
stands between camera and ball. It adds ``k · L_env · F(α) · cos⁴β`` per ray. Pixels whose
whole ray bundle (pixel area × aperture) can straddle an edge of that (the silhouette, the
housing's reflection or shadow) are those within the largest blur radius of a pixel whose
chief ray is classified differently; they are sampled over the whole aperture, the others
with one aperture point per sub-pixel sample (their integrand is smooth). Emitters outside
the housing's face hide the environment behind them: their rays subtract ``L_env``.

The package's modules, in the order a ray meets them: :mod:`~sim_devices.optics.geometry`
(the camera, the ball, the light's plane and housing, and the exact trace through them),
:mod:`~sim_devices.optics.sampling` (the stratified sample patterns),
:mod:`~sim_devices.optics.renderer` (:class:`MirrorBallRenderer`: the emitters and the
environment, pixel by pixel) and :mod:`~sim_devices.optics.diffraction` (the Airy pattern).
"""

from sim_devices.optics.diffraction import apply_diffraction, circular_otf
from sim_devices.optics.geometry import CameraOptics, LightPlane, Mirror, Trace, fresnel_conductor, trace
from sim_devices.optics.renderer import MirrorBallRenderer, Rendering, RenderStats, environment_rgb
from sim_devices.optics.sampling import GOLDEN_ANGLE, subpixel_pattern, unit_disc_samples

__all__ = [
    "GOLDEN_ANGLE",
    "CameraOptics",
    "LightPlane",
    "Mirror",
    "MirrorBallRenderer",
    "RenderStats",
    "Rendering",
    "Trace",
    "apply_diffraction",
    "circular_otf",
    "environment_rgb",
    "fresnel_conductor",
    "subpixel_pattern",
    "trace",
    "unit_disc_samples",
]
