"""Measured geometry: the ball's centre from a calibration image, against the simulator.

The calibration frames are rendered by the simulated camera with a uniform environment
(the room the ball reflects), the light's emitters off, photon and read noise, the Bayer
mosaic and a DNG round trip, on a reduced sensor (500 x 400 pixels of 23.6 µm: the
default optics, 4x coarser). Measured on such frames (seeds 5-7): the tangent-cone solve
with the Fresnel rim correction finds the centre within 0.014 mm (0.004 mm laterally);
without the rim correction it comes out 0.80-0.82 mm too close to the camera; the ellipse
centre's perspective offset is 3.66 px against 3.61 px from the closed form.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import rig_with

from drivers.contracts.rig import load_rig
from drivers.pose import Pose
from processing.calibration import (
    CalibrationError,
    angle_sensitivity,
    calibrate_ball,
    compare_with_rig,
    detect_silhouette,
    mosaic_luminance,
    solve_ball_centre,
)
from sim_devices.camera import SimulatedCamera
from sim_devices.lights import Emitter, LambertianRadiance, TruthLight
from sim_devices.optics import MirrorBallRenderer
from sim_devices.world import SimWorld

GREEN = 1
REDUCED = dict(camera__width=500, camera__height=400, camera__pixel_pitch_m=23.6e-6)


def calibration_frame(rig, tmp_path, seed):
    """A noisy calibration capture: room lit, light off, exposed to 60 % of full well."""
    pose = rig.light_poses()[33]
    camera = SimulatedCamera(rig, SimWorld(lambda: pose), tmp_path, seed=seed, environment_radiance=50.0)
    camera.light_on = False
    exposure = 0.6 * rig.camera.full_well_e / camera.rendering().rate.max()
    frame = camera.capture(exposure)
    assert frame.mosaic.max() < rig.camera.white_level  # nothing clipped
    return mosaic_luminance(frame.mosaic, frame.black_level)


@pytest.fixture(scope="module")
def on_axis(tmp_path_factory):
    rig = rig_with(**REDUCED)
    image = calibration_frame(rig, tmp_path_factory.mktemp("calibration"), seed=5)
    return rig, image, detect_silhouette(image)


def true_centre_camera(rig):
    rot, t = rig.camera.pose.extrinsics()
    return rot @ np.asarray(rig.ball.centre_m) + t


# --- the centre --------------------------------------------------------------------------------
def test_tangent_solve_finds_the_ball_centre_within_0_2_mm(on_axis):
    rig, image, silhouette = on_axis
    assert silhouette.rejected < 0.05 * (len(silhouette.points) + silhouette.rejected)
    # The ball's image: radius f/p * R / sqrt(D² - R²) = 136.2 px (plus the rim's half pixel).
    assert np.mean(silhouette.ellipse.semi_axes) == pytest.approx(136.2, abs=1.0)
    truth = true_centre_camera(rig)
    fit = solve_ball_centre(
        silhouette,
        rig.camera.camera_matrix(),
        rig.ball.radius_m,
        extrinsics=rig.camera.pose.extrinsics(),
        ball_index=(rig.ball.n, rig.ball.k),
    )
    error_mm = (fit.centre_camera - truth) * 1e3
    assert np.linalg.norm(error_mm) < 0.2  # measured: 0.011 mm
    assert np.all(np.abs(error_mm[:2]) < 0.02)  # laterally the edge bias cancels
    # The statistical uncertainty is of the edge noise only: microns here.
    assert np.all(fit.sigma_camera < 0.05e-3)
    assert fit.rms_m < 0.05e-3
    np.testing.assert_allclose(fit.centre_rig, rig.ball.centre_m, atol=0.2e-3)
    # The Fresnel rim puts the flux-balanced edge ~0.56 px outside the tangent: uncorrected,
    # the ball looks bigger and so closer (z is the depth in camera coordinates).
    assert 0.45 < fit.rim_shift_px < 0.7
    plain = solve_ball_centre(silhouette, rig.camera.camera_matrix(), rig.ball.radius_m)
    assert -1.1e-3 < plain.centre_camera[2] - truth[2] < -0.5e-3  # measured: -0.81 mm
    # The one-call form gives the same answer.
    again = calibrate_ball(image, rig)
    np.testing.assert_allclose(again.centre_camera, fit.centre_camera, atol=1e-9)


def test_the_contour_method_is_the_coarse_one(on_axis):
    rig, image, _ = on_axis
    coarse = detect_silhouette(image, method="contour")
    fit = solve_ball_centre(coarse, rig.camera.camera_matrix(), rig.ball.radius_m)
    assert np.linalg.norm(fit.centre_camera - true_centre_camera(rig)) < 2e-3


def test_compare_with_rig_reports_a_wrong_ball_position(on_axis):
    rig, image, silhouette = on_axis
    fit = solve_ball_centre(
        silhouette, rig.camera.camera_matrix(), rig.ball.radius_m, ball_index=(rig.ball.n, rig.ball.k)
    )
    right = compare_with_rig(fit, rig)
    assert right["distance_mm"] < 0.2
    # The description puts the ball 1 mm to the side (+x), or 1 mm towards the camera (+z):
    # the measurement says it is 1 mm the other way.
    sideways = compare_with_rig(fit, rig_with(**REDUCED, ball__centre_m=[0.001, 0.0, 0.0]))
    np.testing.assert_allclose(sideways["discrepancy_mm"], [-1.0, 0.0, 0.0], atol=0.05)
    assert sideways["distance_mm"] == pytest.approx(1.0, abs=0.05)
    assert sideways["significance"] > 10
    nearer = compare_with_rig(fit, rig_with(**REDUCED, ball__centre_m=[0.0, 0.0, 0.001]))
    np.testing.assert_allclose(nearer["discrepancy_mm"], [0.0, 0.0, -1.0], atol=0.2)
    # In camera coordinates that is the depth: the ball is 1 mm farther than described.
    assert nearer["discrepancy_camera_mm"][2] == pytest.approx(1.0, abs=0.2)


# --- perspective -------------------------------------------------------------------------------
def test_perspective_moves_the_ellipse_centre_off_the_ball_centre(tmp_path):
    # The camera looks 4 cm beside the ball: the ball is 11.3° off the axis; the principal
    # point near the sensor's left edge keeps it in this small frame.
    rig = rig_with(**REDUCED, camera__principal_point_px=[40.0, 199.5], camera__pose__look_at_m=[-0.04, 0.0, 0.0])
    silhouette = detect_silhouette(calibration_frame(rig, tmp_path, seed=3))
    k = rig.camera.camera_matrix()
    truth = true_centre_camera(rig)
    projected = (k @ truth)[:2] / (k @ truth)[2]
    # Closed form: the cone of half-angle β about an axis at γ from the optical axis cuts
    # the image plane in an ellipse whose major axis runs from f tan(γ-β) to f tan(γ+β).
    distance = np.linalg.norm(truth)
    beta = math.asin(rig.ball.radius_m / distance)
    gamma = math.acos(truth[2] / distance)
    predicted = k[0, 0] * (0.5 * (math.tan(gamma + beta) + math.tan(gamma - beta)) - math.tan(gamma))
    assert predicted == pytest.approx(3.61, abs=0.01)
    outward = (projected - k[:2, 2]) / np.linalg.norm(projected - k[:2, 2])
    offset = np.asarray(silhouette.ellipse.centre) - projected
    assert offset @ outward == pytest.approx(predicted, abs=0.15)  # measured: 3.66 px
    assert abs(offset @ np.array([-outward[1], outward[0]])) < 0.15
    # The tangent solve is not fooled; taking the ellipse's centre for the ball's is.
    fit = solve_ball_centre(silhouette, k, rig.ball.radius_m, ball_index=(rig.ball.n, rig.ball.k))
    tangent_error = np.linalg.norm(fit.centre_camera - truth)
    naive_error = np.linalg.norm(fit.naive_centre_camera - truth)
    assert tangent_error < 0.2e-3  # measured: 0.003 mm
    assert naive_error > 0.5e-3  # measured: 0.67 mm, mostly sideways
    assert naive_error > 20 * tangent_error


# --- what a wrong position costs ----------------------------------------------------------------
def test_angle_sensitivity_of_a_1_mm_error():
    rig = load_rig()
    result = angle_sensitivity(rig, rig.light_poses()[33])
    assert result["shift_mm"] == 1.0
    assert result["pixels"] > 100
    # Sideways, the ball's normal at a fixed pixel turns by s / R and the reflected ray by
    # twice that: 2 * 1 mm / 25.4 mm = 4.5°. Measured: 4.40° (x) and 4.61° (y) median.
    lateral = math.degrees(2 * 1e-3 / rig.ball.radius_m)
    for axis in "xy":
        assert result[axis]["direction_median_deg"] == pytest.approx(lateral, rel=0.1)
        assert result[axis]["theta_max_deg"] <= result[axis]["direction_max_deg"] + 1e-9
        assert 1.0 < result[axis]["theta_median_deg"] < lateral * 1.1  # measured: 2.5°, 2.9°
        assert 3.0 < result[axis]["uv_median_mm"] < 15.0
    # Along the camera's axis the ray meets the ball earlier, nearly along the normal:
    # a tenth of a degree.
    assert result["z"]["direction_median_deg"] < 0.3  # measured: 0.14°
    assert result["z"]["theta_max_deg"] < 0.3
    assert result["theta_max_deg"] == max(result[a]["theta_max_deg"] for a in "xyz")
    # Linear in the shift.
    half = angle_sensitivity(rig, rig.light_poses()[33], shift_m=0.5e-3)
    assert half["x"]["direction_median_deg"] == pytest.approx(result["x"]["direction_median_deg"] / 2, rel=0.05)


# --- bad input ----------------------------------------------------------------------------------
def _one_line(excinfo):
    assert "\n" not in str(excinfo.value)
    return str(excinfo.value)


def test_blank_and_ballless_images_are_refused_in_one_line(tmp_path):
    with pytest.raises(CalibrationError, match="blank") as excinfo:
        detect_silhouette(np.zeros((328, 500)))
    _one_line(excinfo)
    # A dark room: the ball reflects nothing, the frame is read noise around black.
    rig = rig_with(**REDUCED)
    pose = rig.light_poses()[33]
    dark = SimulatedCamera(rig, SimWorld(lambda: pose), tmp_path, seed=2)
    dark.light_on = False
    frame = dark.capture(0.1)
    with pytest.raises(CalibrationError, match="no ball") as excinfo:
        detect_silhouette(mosaic_luminance(frame.mosaic, frame.black_level))
    _one_line(excinfo)

    rng = np.random.default_rng(0)
    rows, cols = np.mgrid[0:328, 0:500]
    noise = rng.normal(0.0, 3.0, (328, 500))
    square = np.where((np.abs(cols - 250) < 100) & (np.abs(rows - 164) < 100), 500.0, 0.0) + noise
    with pytest.raises(CalibrationError, match="not an ellipse|not disc-like") as excinfo:
        detect_silhouette(square)
    _one_line(excinfo)
    cut = np.where(np.hypot(cols - 480, rows - 164) < 130, 500.0, 0.0) + noise
    with pytest.raises(CalibrationError, match="cut off by the image border") as excinfo:
        detect_silhouette(cut)
    _one_line(excinfo)
    with pytest.raises(CalibrationError, match="2-D"):
        detect_silhouette(np.zeros(100))
    with pytest.raises(CalibrationError, match="unknown silhouette method"):
        detect_silhouette(square, method="hough")
    # A sharp synthetic disc is found where it is drawn.
    disc = np.where(np.hypot(cols - 250.3, rows - 164.6) < 120, 500.0, 0.0) + noise
    found = detect_silhouette(disc)
    np.testing.assert_allclose(found.ellipse.centre, (250.3, 164.6), atol=0.05)
    np.testing.assert_allclose(found.ellipse.semi_axes, (120.0, 120.0), atol=0.15)


# --- the simulated room ---------------------------------------------------------------------------
def test_environment_light_is_fresnel_times_radiance_and_hidden_by_emitters():
    rig = rig_with(camera__width=320, camera__height=320, camera__pixel_pitch_m=23.6e-6, light__housing_radius_m=0.0)
    pose = Pose(0.0, 0.0, 0.10, math.pi, 0.0, 0.0)  # the plane z = 0.1 faces the ball
    room = 1000.0
    env_only = MirrorBallRenderer(rig, None, environment_radiance=room, diffraction=False, seed=9).render(pose).rate
    # The pixel on the axis sees the ball at normal incidence: k · L · F(0), with the
    # normal-incidence reflectance ((n-1)² + k²) / ((n+1)² + k²) of each channel.
    cx, cy = rig.camera.principal_point
    n, k = np.array(rig.ball.n), np.array(rig.ball.k)
    f0 = ((n - 1) ** 2 + k**2) / ((n + 1) ** 2 + k**2)
    centre = env_only[:, int(cy), int(cx)]
    np.testing.assert_allclose(centre, rig.camera.sensitivity_e_per_s * room * f0, rtol=2e-3)
    # Outside the ball's blurred outline: nothing.
    assert np.all(env_only[:, :, :5] == 0.0)
    # An emitter of the room's own radiance hides exactly the room behind it: the image is
    # the same with a Lambertian disc of that radiance switched on (bare, no housing).
    patch = TruthLight(
        emitters=[Emitter(name="patch", radius_m=0.02, intensity=LambertianRadiance(radiance_w_sr_m2=room))]
    )
    renderer = MirrorBallRenderer(rig, patch, environment_radiance=room, diffraction=False, seed=9)
    with_patch = renderer.render(pose)
    assert with_patch.stats.per_emitter_pixels["patch"] > 1000
    np.testing.assert_allclose(with_patch.rate, env_only, rtol=1e-9, atol=1e-6)
    # ... while a brighter one shows at its own radiance (Monte-Carlo sampled: a 5 x 5 mean).
    patch2 = TruthLight(
        emitters=[Emitter(name="patch", radius_m=0.02, intensity=LambertianRadiance(radiance_w_sr_m2=2 * room))]
    )
    brighter = MirrorBallRenderer(rig, patch2, environment_radiance=room, diffraction=False, seed=9).render(pose).rate
    block = (slice(None), slice(int(cy) - 2, int(cy) + 3), slice(int(cx) - 2, int(cx) + 3))
    np.testing.assert_allclose(brighter[block].mean(axis=(1, 2)), 2 * env_only[block].mean(axis=(1, 2)), rtol=0.01)
