"""Measured geometry: where the mirrored ball really is, from a calibration image.

The reference work found that the relative position of camera, ball and light must be
known precisely; this package measures the ball's position, so that the processing need not
trust the rig description's.

A *calibration image* shows the ball lit by its surroundings: a bright disc-like region
(the room reflected in the mirror) against a darker background. Its outline is the
silhouette of the sphere: the cone of rays from the camera's centre of projection that
graze the ball. From the outline and the ball's known radius R the centre C follows,
because every silhouette ray is tangent to the sphere: for each edge point's unit ray d_i
(back-projected through the camera matrix), the distance from C to the ray is R,
``|C - (C·d_i) d_i| = R``.

Under perspective the silhouette is an ellipse (the cone cut by the image plane) whose
centre is **not** the projection of the ball's centre: for a ball whose centre lies at an
angle γ from the optical axis and subtends a half-angle β, the ellipse's major axis runs
from ``f tan(γ - β)`` to ``f tan(γ + β)`` from the principal point, so its centre lies
``f [(tan(γ + β) + tan(γ - β)) / 2 - tan γ]`` farther out than the centre's projection
``f tan γ`` (several pixels for a ball 10-15° off the axis). :func:`solve_ball_centre`
therefore fits the tangent cone, not the ellipse's centre.

The edge. Along profiles normal to a first outline (OpenCV contour + ``cv2.fitEllipse``),
the edge is placed by flux conservation: where a sharp step between the straight lines
fitted to the profile inside and outside would hold the same light as the measured
profile over a window symmetric about the edge. The camera's blur (the aperture's disc,
the Airy pattern and its slow tails, the pixel) conserves light and is symmetric, so the
estimate is unbiased by it. What it does see is the ball's own reflectance: a metal's
Fresnel reflectance rises to 1 at grazing incidence, so the outermost sliver of the
disc is brighter than the interior's trend, and the flux-balanced edge lands outside the
true tangent — about half a pixel for chrome at the defaults' resolution reduced to
23.6 µm pixels, 0.8 mm in the ball's distance. Given the ball's complex refractive index,
:func:`solve_ball_centre` predicts that shift for each edge point (the same estimator
applied to the Fresnel profile of a sharp silhouette, at the fitted geometry) and
removes it.

The uncertainty reported is statistical (the scatter of the edge points about the fitted
cone, through the fit's Jacobian). Systematic errors are not in it: the intrinsics, and
the radius (the solution scales with R: a 10 µm error in R moves the centre by
10 µm × |C| / R, 80 µm at 20 cm).

:func:`angle_sensitivity` says what an error in the ball's position costs: how far the
recovered outgoing angles move when the ball is 1 mm from where the processing thinks.

Modules: :mod:`~processing.calibration.silhouette` (the outline, sub-pixel edges by flux
balance), :mod:`~processing.calibration.ball` (the centre, the Fresnel rim's correction,
the comparison with the rig) and :mod:`~processing.calibration.sensitivity` (what a wrong
ball position costs).
"""

from processing.calibration.ball import (
    BallFit,
    calibrate_ball,
    compare_with_rig,
    fresnel_rim_shift_px,
    solve_ball_centre,
)
from processing.calibration.errors import CalibrationError
from processing.calibration.sensitivity import angle_sensitivity
from processing.calibration.silhouette import Ellipse, Silhouette, detect_silhouette, mosaic_luminance

__all__ = [
    "CalibrationError",
    "Ellipse",
    "Silhouette",
    "BallFit",
    "mosaic_luminance",
    "detect_silhouette",
    "fresnel_rim_shift_px",
    "solve_ball_centre",
    "calibrate_ball",
    "compare_with_rig",
    "angle_sensitivity",
]
