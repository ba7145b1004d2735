"""What the simulated camera sees of the mirrored ball: backward ray tracing.

Written from the physics of ``docs/measurement.md`` and deliberately independent of
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

The Fresnel point spread (``point_spread = "fresnel"``, opt-in): the geometric shadow ⊗ Airy
picture above is the far field's, but the reference pinhole works at a Fresnel number
``N_F = a²/λ · (1/z₁ + 1/z₂)`` of 0.74–0.98 (a = 0.1 mm, z₁ ≈ 187 mm the light's virtual image
in front of the pinhole, z₂ = 25 mm), where neither holds: the scalar Fresnel integral of the
aperture lit by the point's spherical wave (Goodman, *Introduction to Fourier Optics*, §4.2;
Born & Wolf, *Principles of Optics*, §8.8 for the circle's Lommel functions) is centre-peaked,
3.4–3.9 times the shadow's level, 10.5–13.5 px wide at half height against the model's 38 px.
With it the renderer traces only the chief rays (an aperture shrunk to 1e-4 of the pinhole) for
each emitter's sharp image, sub-pixel sampled, and convolves it with the point spread of that
emitter's own path: the second derivatives of the optical path about its chief ray, measured by
tracing neighbouring rays (astigmatism from the ball's curvature and the sensor's obliquity
included; the image distances are Coddington's foci, 186–189 mm over the default sweep), through
the rig's actual aperture (circle, ellipse, mask image, rough edge), averaged over each
channel's spectral band and normalised to unit flux. The point spreads are cached by the path
rounded (the Fresnel number to 0.002): the default sweep needs 9 paths.

The package's modules, in the order a ray meets them: :mod:`~sim_devices.optics.geometry`
(the camera, the ball, the light's plane and housing, and the exact trace through them),
:mod:`~sim_devices.optics.sampling` (the stratified sample patterns),
:mod:`~sim_devices.optics.renderer` (:class:`MirrorBallRenderer`: the emitters and the
environment, pixel by pixel), :mod:`~sim_devices.optics.diffraction` (the Airy pattern),
:mod:`~sim_devices.optics.aperture` (the pinhole's shape), :mod:`~sim_devices.optics.fresnel`
(the Fresnel point spread and the bands) and :mod:`~sim_devices.optics.point_spread` (its
kernels, cached, convolved with a frame).
"""

from sim_devices.optics.aperture import ApertureShape
from sim_devices.optics.diffraction import apply_diffraction, circular_otf
from sim_devices.optics.fresnel import PathCurvature, channel_band, channel_psf, fresnel_psf
from sim_devices.optics.geometry import CameraOptics, LightPlane, Mirror, Trace, fresnel_conductor, trace
from sim_devices.optics.point_spread import FresnelBlur
from sim_devices.optics.renderer import MirrorBallRenderer, Rendering, RenderStats, environment_rgb
from sim_devices.optics.sampling import GOLDEN_ANGLE, subpixel_pattern, unit_disc_samples

__all__ = [
    "GOLDEN_ANGLE",
    "ApertureShape",
    "CameraOptics",
    "FresnelBlur",
    "LightPlane",
    "Mirror",
    "MirrorBallRenderer",
    "PathCurvature",
    "RenderStats",
    "Rendering",
    "Trace",
    "apply_diffraction",
    "channel_band",
    "channel_psf",
    "circular_otf",
    "environment_rgb",
    "fresnel_conductor",
    "fresnel_psf",
    "subpixel_pattern",
    "trace",
    "unit_disc_samples",
]
