"""The simulated camera against analytic answers written here, not in the renderer.

Each check recomputes what the physics predicts with its own small formulas (its own
sphere intersection, the real-valued Born & Wolf form of the conductor's Fresnel
reflectance, the Coddington equations of a spherical mirror), so the renderer cannot
agree with itself by sharing a mistake.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import rig_with
from scipy.special import j1

from drivers.pose import Pose
from drivers.raw_decode import decode_raw
from sim_devices.camera import SimulatedCamera
from sim_devices.lights import Emitter, GaussianIntensity, TruthLight, load_truth
from sim_devices.optics import MirrorBallRenderer
from sim_devices.world import SimWorld

GREEN = 1


def fresnel_born_wolf(theta_i, n, k):
    """Unpolarised reflectance of a conductor, real-valued form (Born & Wolf §14.4)."""
    s2 = np.sin(theta_i) ** 2
    c = np.cos(theta_i)
    tan = np.tan(theta_i)
    root = np.sqrt((n * n - k * k - s2) ** 2 + 4 * n * n * k * k)
    a2 = 0.5 * (root + (n * n - k * k - s2))
    a = np.sqrt(a2)
    rs = (root - 2 * a * c + c * c) / (root + 2 * a * c + c * c)
    rp = (
        rs
        * (root - 2 * a * np.sin(theta_i) * tan + s2 * tan * tan)
        / (root + 2 * a * np.sin(theta_i) * tan + s2 * tan * tan)
    )
    return 0.5 * (rs + rp)


def chief_rays(rig, cols, rows):
    """Independent chief-ray trace: pixel -> ball -> reflected direction (rig frame)."""
    cam = rig.camera
    r, _ = cam.pose.extrinsics()
    cx, cy = cam.principal_point
    d = np.stack(
        [(cols - cx) * cam.pixel_pitch_m, (rows - cy) * cam.pixel_pitch_m, np.full(cols.shape, cam.sensor_distance_m)],
        axis=-1,
    )
    cos_beta = d[..., 2] / np.linalg.norm(d, axis=-1)
    d = d @ r  # camera -> rig (rows of r are the camera axes)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = cam.centre()
    centre, radius = np.array(rig.ball.centre_m), rig.ball.radius_m
    oc = o - centre
    b = d @ oc
    disc = b * b - (oc @ oc - radius * radius)
    hit = disc > 0
    t = -b - np.sqrt(np.where(hit, disc, 0))
    p = o + t[..., None] * d
    normal = (p - centre) / radius
    cos_i = -np.sum(d * normal, axis=-1)
    reflected = d + 2 * cos_i[..., None] * normal
    return hit, p, reflected, np.arccos(np.clip(cos_i, -1, 1)), cos_beta


def specular_point(source, camera_centre, centre, radius, iterations=200):
    """The point on a convex sphere where source light reflects into the camera."""
    p = centre + radius * (source + camera_centre - 2 * centre) / np.linalg.norm(source + camera_centre - 2 * centre)
    for _ in range(iterations):
        to_s = (source - p) / np.linalg.norm(source - p)
        to_c = (camera_centre - p) / np.linalg.norm(camera_centre - p)
        bis = to_s + to_c
        p = centre + radius * bis / np.linalg.norm(bis)
    return p


# --- (1) a uniform Lambertian plane --------------------------------------------------------
LAMBERTIAN_POSE = Pose(0.0, 0.0, 0.10, math.pi, 0.0, 0.0)  # the plane z = 0.1 faces the ball


@pytest.fixture(scope="module")
def lambertian_camera(tmp_path_factory):
    rig = rig_with(
        camera__width=500,
        camera__height=328,
        camera__pixel_pitch_m=23.6e-6,
        light__housing_radius_m=0.0,
        simulation__truth="lambertian-disc",
        simulation__diffraction=False,
    )  # Airy tails: tested on their own below
    world = SimWorld(lambda: LAMBERTIAN_POSE)
    return SimulatedCamera(rig, world, tmp_path_factory.mktemp("lambertian"), seed=7)


def _interior_expectation(camera):
    """Expected electron rate per photosite, and the pixels well inside the lit region."""
    rig = camera.rig
    h, w = rig.camera.height, rig.camera.width
    rows, cols = np.mgrid[0:h, 0:w].astype(float)
    hit, p, refl, alpha, cos_beta = chief_rays(rig, cols, rows)
    # The reflected ray reaches the plane z = 0.1 from below; emission angle from its normal.
    reaches = hit & (refl[..., 2] > 0)
    theta = np.arccos(np.clip(refl[..., 2], -1, 1))
    lit = reaches & (theta < math.radians(60))
    from scipy.ndimage import binary_erosion

    interior = binary_erosion(lit, iterations=14)  # blur radius ~10 px at this pitch
    radiance = camera.truth.emitters[0].intensity.radiance_w_sr_m2
    n, k = np.array(rig.ball.n), np.array(rig.ball.k)
    f_rgb = np.stack([fresnel_born_wolf(alpha, n[c], k[c]) for c in range(3)])
    expected = rig.camera.sensitivity_e_per_s * radiance * f_rgb * cos_beta**4
    return expected, interior


def test_uniform_lambertian_plane_gives_fresnel_times_radiance(lambertian_camera):
    expected, interior = _interior_expectation(lambertian_camera)
    rate = lambertian_camera.rendering().rate
    assert interior.sum() > 5000
    ratio = rate[:, interior] / expected[:, interior]
    # The renderer averages F and cos^4 over each pixel's footprint: within 0.3 % of the chief ray.
    assert np.median(np.abs(ratio - 1)) < 1e-3
    assert np.max(np.abs(ratio - 1)) < 3e-3
    # Not a constant field: cos^4 vignetting and F(alpha) shape it, and the renderer follows.
    assert expected[GREEN][interior].max() / expected[GREEN][interior].min() > 1.004


def test_uniform_plane_capture_is_within_the_noise(lambertian_camera):
    expected, interior = _interior_expectation(lambertian_camera)
    cam = lambertian_camera.rig.camera
    exposure = 0.02
    frame = lambertian_camera.capture(exposure)
    from sim_devices.sensor import cfa_channels

    channels = cfa_channels(cam.cfa_pattern, cam.height, cam.width)
    electrons = np.take_along_axis(expected, channels[None], 0)[0] * exposure
    gain = cam.gain_e_per_dn
    mean_dn = electrons / gain + cam.black_level_dn
    sigma_dn = np.sqrt((electrons + cam.read_noise_e**2) / gain**2 + 1 / 12)
    z = (frame.mosaic.astype(float) - mean_dn)[interior] / sigma_dn[interior]
    assert abs(z.mean()) < 5 / math.sqrt(z.size)
    assert z.std() == pytest.approx(1.0, abs=0.05)


# --- (2) linear in intensity, inverse square in distance -------------------------------------
def _crop_rig(size=320, diffraction=False):
    # A crop of the full-pitch sensor around the middle position's sources, its camera the
    # geometric⊗Airy one the renderer's and the unmixing's figures here were measured with.
    return rig_with(
        camera__point_spread="geometric-airy",
        camera__width=size,
        camera__height=size,
        camera__principal_point_px=[999.5 - 840, 655.5 - 400],
        light__housing_radius_m=0.012,
        simulation__diffraction=diffraction,
    )


def _single_source(peak=1.0, radius=0.2e-3, sigma_deg=60.0):
    return TruthLight(
        emitters=[Emitter(name="s", radius_m=radius, intensity=GaussianIntensity(peak_w_sr=peak, sigma_deg=sigma_deg))]
    )


def _predicted_total_rate(rig, light_pose, emitter):
    """Sum over all pixels of the green rate, from the Coddington equations."""
    source = light_pose.position
    cam_centre = rig.camera.centre()
    centre, radius = np.array(rig.ball.centre_m), rig.ball.radius_m
    p = specular_point(source, cam_centre, centre, radius)
    d, c = np.linalg.norm(source - p), np.linalg.norm(cam_centre - p)
    normal = (p - centre) / radius
    cos_a = float(np.dot(normal, (source - p) / d))
    power_t, power_s = 2 / (radius * cos_a), 2 * cos_a / radius
    emission = (p - source) / d
    theta = math.acos(float(np.dot(emission, light_pose.rotation[:, 2])))
    r, _ = rig.camera.pose.extrinsics()
    cos_beta = float(np.dot((cam_centre - p) / c, -r[2]))
    f_green = fresnel_born_wolf(math.acos(cos_a), rig.ball.n[GREEN], rig.ball.k[GREEN])
    spread = (d + c + d * c * power_t) * (d + c + d * c * power_s)
    cam = rig.camera
    intensity = float(emitter.intensity_w_sr(theta))
    total = (
        cam.sensitivity_e_per_s
        * cam.sensor_distance_m**2
        * f_green
        * intensity
        * abs(cos_beta)
        / (cam.pixel_pitch_m**2 * spread)
    )
    return total, (source - p) / d


def test_small_source_scales_with_intensity_and_inverse_square_of_distance():
    rig = _crop_rig()
    pose = rig.light_poses()[33]
    base = MirrorBallRenderer(rig, _single_source(1.0), diffraction=False, seed=1).render(pose).rate[GREEN].sum()
    doubled = MirrorBallRenderer(rig, _single_source(2.0), diffraction=False, seed=2).render(pose).rate[GREEN].sum()
    assert doubled / base == pytest.approx(2.0, rel=5e-3)

    predicted, outward = _predicted_total_rate(rig, pose, _single_source(1.0).emitters[0])
    assert base == pytest.approx(predicted, rel=0.005)
    # Move the light 3 cm farther along the ray that reflects into the camera.
    far = Pose(*(pose.position + 0.03 * outward), pose.rx, pose.ry, pose.rz)
    far_total = MirrorBallRenderer(rig, _single_source(1.0), diffraction=False, seed=3).render(far).rate[GREEN].sum()
    far_predicted, _ = _predicted_total_rate(rig, far, _single_source(1.0).emitters[0])
    assert far_total / base == pytest.approx(far_predicted / predicted, rel=0.005)
    assert far_total / base < 0.75  # and it is a real fall-off, not a flat response


# --- (3) the DNG path ---------------------------------------------------------------------------
def test_simulated_dng_decodes_to_exactly_the_mosaic_written(tmp_path):
    rig = _crop_rig()
    world = SimWorld(lambda: rig.tool_poses()[33])
    camera = SimulatedCamera(rig, world, tmp_path, seed=5)
    frame = camera.capture(0.004)
    again = decode_raw(frame.source)
    np.testing.assert_array_equal(again.mosaic, camera.last_mosaic)
    np.testing.assert_array_equal(frame.mosaic, camera.last_mosaic)
    assert frame.cfa_pattern == "RGGB"
    np.testing.assert_array_equal(frame.black_level, np.full((2, 2), 64.0))
    assert frame.white_level == 4095
    assert frame.exposure_s == pytest.approx(0.004, rel=1e-9)
    assert "SIM-0001" in frame.camera_id
    assert frame.mosaic.max() > 1000  # the sources are in view


# --- (4) noise: variance against mean ------------------------------------------------------------
def test_variance_against_mean_follows_shot_plus_read_noise(lambertian_camera):
    cam = lambertian_camera.rig.camera
    _, interior = _interior_expectation(lambertian_camera)
    means, variances = [], []
    for exposure in (0.0005, 0.003, 0.015):
        stack = np.stack([lambertian_camera.capture(exposure).mosaic.astype(float) for _ in range(8)])
        means.append(stack.mean(0)[interior] - cam.black_level_dn)
        variances.append(stack.var(0, ddof=1)[interior])
    mean, var = np.concatenate(means), np.concatenate(variances)
    keep = mean < 0.9 * (cam.white_level - cam.black_level_dn)
    gain = cam.gain_e_per_dn
    predicted = mean[keep] / gain + (cam.read_noise_e / gain) ** 2 + 1 / 12
    # Per-bin agreement within 4 % (each bin averages thousands of 7-dof variances).
    edges = np.quantile(mean[keep], np.linspace(0, 1, 11))
    bins = np.digitize(mean[keep], edges[1:-1])
    for b in range(10):
        sel = bins == b
        assert var[keep][sel].mean() / predicted[sel].mean() == pytest.approx(1.0, abs=0.04), b
    slope, intercept = np.polyfit(mean[keep], var[keep], 1)
    assert slope == pytest.approx(1 / gain, rel=0.03)


# --- (5) the blur spot of a tiny source ----------------------------------------------------------
def _blur_prediction(rig, pose):
    source = pose.position
    cam_centre = rig.camera.centre()
    centre, radius = np.array(rig.ball.centre_m), rig.ball.radius_m
    p = specular_point(source, cam_centre, centre, radius)
    d, c = np.linalg.norm(source - p), np.linalg.norm(cam_centre - p)
    cos_a = float(np.dot((p - centre) / radius, (source - p) / d))
    # Virtual image distance behind the mirror (mean of the tangential and sagittal foci).
    d_img = 0.5 * (1 / (1 / d + 2 / (radius * cos_a)) + 1 / (1 / d + 2 * cos_a / radius))
    z = c + d_img
    f, ra = rig.camera.sensor_distance_m, rig.camera.pinhole_diameter_m / 2
    return ra * (z + f) / z / rig.camera.pixel_pitch_m


def test_blur_spot_has_the_size_of_the_projected_aperture():
    rig = _crop_rig()
    pose = rig.light_poses()[33]
    tiny = _single_source(radius=0.02e-3)
    spot = MirrorBallRenderer(rig, tiny, diffraction=False, seed=4).render(pose).rate[GREEN]
    rows, cols = np.mgrid[0 : spot.shape[0], 0 : spot.shape[1]]
    total = spot.sum()
    cy, cx = (spot * rows).sum() / total, (spot * cols).sum() / total
    var = (spot * ((rows - cy) ** 2 + (cols - cx) ** 2)).sum() / total / 2  # per axis
    # A uniform disc of radius r has a per-axis variance r^2/4; the pixel box adds 1/12.
    measured_radius = 2 * math.sqrt(var - 1 / 12)
    predicted = _blur_prediction(rig, pose)
    assert predicted == pytest.approx(19.2, abs=0.5)  # docs/measurement.md: about 38 px across
    assert measured_radius == pytest.approx(predicted, rel=0.02)


def airy_kernel(wavelength, aperture, distance, pitch, half_size, oversample=5):
    """The Airy pattern integrated over pixels (direct from 2 J1(x)/x, not from an OTF)."""
    n = (2 * half_size + 1) * oversample
    coords = (np.arange(n) - (n - 1) / 2) / oversample * pitch
    x = math.pi * aperture * np.hypot(*np.meshgrid(coords, coords)) / (wavelength * distance)
    with np.errstate(invalid="ignore", divide="ignore"):
        psf = np.where(x > 0, (2 * j1(x) / x) ** 2, 1.0)
    psf = psf.reshape(2 * half_size + 1, oversample, 2 * half_size + 1, oversample).sum(axis=(1, 3))
    # Normalise with the analytic total power so the truncated tails count as lost.
    return psf * (math.pi * aperture**2 / (4 * wavelength**2 * distance**2)) * (pitch / oversample) ** 2


def test_diffraction_spreads_the_spot_as_the_airy_pattern_predicts():
    from scipy.signal import fftconvolve

    rig = _crop_rig()
    pose = rig.light_poses()[33]
    tiny = _single_source(radius=0.02e-3)
    geometric = MirrorBallRenderer(rig, tiny, diffraction=False, seed=4).render(pose).rate[GREEN]
    diffracted = (
        MirrorBallRenderer(rig, tiny, diffraction=True, point_spread="geometric-airy", seed=4).render(pose).rate[GREEN]
    )
    cam = rig.camera
    kernel = airy_kernel(
        cam.channel_wavelengths_m[GREEN], cam.pinhole_diameter_m, cam.sensor_distance_m, cam.pixel_pitch_m, 120
    )
    expected = fftconvolve(geometric, kernel, mode="same")
    peak = expected.max()
    assert np.max(np.abs(diffracted - expected)) < 0.01 * peak
    # First Airy zero at 1.22 lambda N = 14 px: the spot is visibly wider than the geometric disc.
    assert diffracted.max() < 0.92 * geometric.max()


# --- the thin-lens camera ---------------------------------------------------------------------
def _spot_radius(spot):
    rows, cols = np.mgrid[0 : spot.shape[0], 0 : spot.shape[1]]
    total = spot.sum()
    cy, cx = (spot * rows).sum() / total, (spot * cols).sum() / total
    var = (spot * ((rows - cy) ** 2 + (cols - cx) ** 2)).sum() / total / 2
    return 2 * math.sqrt(max(var - 1 / 12, 0.0))


def test_thin_lens_focused_on_the_virtual_image_is_sharp_and_defocus_blurs_as_predicted():
    pinhole = _crop_rig()
    pose = pinhole.light_poses()[33]
    source = pose.position
    cam_centre = pinhole.camera.centre()
    p = specular_point(source, cam_centre, np.zeros(3), pinhole.ball.radius_m)
    d, c = np.linalg.norm(source - p), np.linalg.norm(cam_centre - p)
    cos_a = float(np.dot(p / pinhole.ball.radius_m, (source - p) / d))
    radius = pinhole.ball.radius_m
    z = c + 0.5 * (1 / (1 / d + 2 / (radius * cos_a)) + 1 / (1 / d + 2 * cos_a / radius))
    tiny = _single_source(radius=0.02e-3)

    def lens_rig(focus):
        return rig_with(
            camera__width=320,
            camera__height=320,
            camera__principal_point_px=[999.5 - 840, 655.5 - 400],
            camera__thin_lens={"focus_distance_m": focus, "f_number": 8.0},
        )

    focused = lens_rig(z)
    spot = MirrorBallRenderer(focused, tiny, diffraction=False, seed=11).render(pose).rate[GREEN]
    assert _spot_radius(spot) < 1.5  # against ~19 px for the pinhole

    defocused = lens_rig(2 * z)
    spot = MirrorBallRenderer(defocused, tiny, diffraction=False, seed=12).render(pose).rate[GREEN]
    f = defocused.camera.sensor_distance_m
    aperture = defocused.camera.aperture_diameter_m
    predicted = 0.5 * aperture * f * abs(1 / z - 1 / (2 * z)) / defocused.camera.pixel_pitch_m
    assert predicted > 10
    assert _spot_radius(spot) == pytest.approx(predicted, rel=0.05)
    # The radiometry does not depend on the camera model: same total as the Coddington prediction.
    expected, _ = _predicted_total_rate(defocused, pose, tiny.emitters[0])
    assert spot.sum() == pytest.approx(expected, rel=0.01)


# --- truths -------------------------------------------------------------------------------------
def test_shipped_truths_load_and_match_their_definitions():
    five = load_truth("five-gaussians")
    assert len(five.emitters) == 5
    centres = sorted(tuple(e.centre_m) for e in five.emitters)
    assert centres == sorted([(0.0, 0.0), (0.004, 0.0), (-0.004, 0.0), (0.0, 0.004), (0.0, -0.004)])
    assert all(e.radius_m == 0.0005 for e in five.emitters)
    led = load_truth("cos-led").emitters[0]
    assert led.intensity_w_sr(math.radians(60)) == pytest.approx(0.5**3)
    lobe = load_truth("anisotropic").emitters[0]
    theta = math.radians(20)
    assert lobe.intensity_w_sr(theta, 0.0) > lobe.intensity_w_sr(theta, math.pi / 2)
    plane = load_truth("lambertian-disc").emitters[0]
    # Radiance of a disc is I / (cos(theta) * area): constant for a Lambertian emitter.
    assert plane.radiance(np.array([0.1, 1.0]), 0.0) == pytest.approx([1000.0, 1000.0])
    gauss = five.emitters[0]
    assert gauss.radiance(0.0, 0.0) * gauss.area_m2 == pytest.approx(gauss.intensity_w_sr(0.0))


def test_truth_errors_are_one_line(tmp_path):
    from sim_devices.lights import TruthError

    with pytest.raises(TruthError, match=r"^nonesuch: no such truth light \(shipped: .*five-gaussians"):
        load_truth("nonesuch")
    bad = tmp_path / "bad.toml"
    bad.write_text("[[emitters]]\nradius_m = -1\n")
    with pytest.raises(TruthError, match=r"bad\.toml: emitters\[0\]\.radius_m: must be > 0 \(got -1\)"):
        load_truth(bad)
    bad.write_text("[[emitters]]\nradius_m = nan\n")  # a TOML literal
    with pytest.raises(TruthError, match=r"bad\.toml: emitters\[0\]\.radius_m: Input should be a finite number"):
        load_truth(bad)


def test_light_housing_blocks_the_cameras_view_with_the_predicted_silhouette():
    # A 2 mm housing, 5 cm deep, on the camera axis between camera and ball: its back end,
    # 5 cm from the pinhole, hides a disc of radius f/p * 2 mm / 50 mm around the centre.
    pitch = 23.6e-6
    rig = rig_with(
        camera__width=500,
        camera__height=328,
        camera__pixel_pitch_m=pitch,
        light__housing_radius_m=0.002,
        light__housing_depth_m=0.05,
        simulation__truth="lambertian-disc",
        simulation__diffraction=False,
    )
    rate = (
        MirrorBallRenderer(rig, load_truth("lambertian-disc"), diffraction=False, seed=3)
        .render(LAMBERTIAN_POSE)
        .rate[GREEN]
    )
    cx, cy = rig.camera.principal_point
    rows, cols = np.mgrid[0 : rig.camera.height, 0 : rig.camera.width]
    r = np.hypot(cols - cx, rows - cy)
    shadow = 0.025 / pitch * 0.002 / 0.05  # 42.4 px
    blur = 0.1e-3 * (1 + 0.025 / 0.05) / pitch  # the pinhole's blur of an edge 5 cm away
    assert np.all(rate[r < shadow - blur - 1] == 0)
    assert np.all(rate[(r > shadow + blur + 1) & (r < shadow + 20)] > 0)
    # Without the housing the same pixels see the plane.
    clear = rig_with(camera__width=500, camera__height=328, camera__pixel_pitch_m=pitch, light__housing_radius_m=0.0)
    open_view = (
        MirrorBallRenderer(clear, load_truth("lambertian-disc"), diffraction=False, seed=3)
        .render(LAMBERTIAN_POSE)
        .rate[GREEN]
    )
    assert np.all(open_view[r < shadow - blur - 1] > 0)


def test_sources_imaged_off_a_cropped_sensor_render_as_dark_not_as_an_error():
    rig = _crop_rig()
    renderer = MirrorBallRenderer(rig, load_truth("five-gaussians"), diffraction=False, seed=1)
    rendering = renderer.render(rig.light_poses()[0])  # the sweep's first position images off this crop
    assert rendering.rate.shape == (3, 320, 320)
    assert np.isfinite(rendering.rate).all()
