"""The simulated camera's Fresnel point spread (sim_devices/optics/fresnel.py): its analytic limits,
the band, the aperture's shapes, the rig's fields, and a rendered frame of the reference rig.

Every number here is computed, deterministic (seeded where random), and checked against a formula
written in this file: the on-axis Lommel value sin²(πN_F/2), the Airy pattern, the geometric
shadow, Coddington's astigmatic image distances of a convex mirror.
"""

import math

import cv2
import numpy as np
import pytest
from conftest import rig_with
from scipy.special import j1

from drivers.contracts.rig import RigError, load_rig
from sim_devices.camera import ROOM_RADIANCE, SimulatedCamera
from sim_devices.lights import Emitter, GaussianIntensity, TruthLight
from sim_devices.optics import LightPlane, MirrorBallRenderer, trace
from sim_devices.optics.aperture import ApertureShape
from sim_devices.optics.fresnel import (
    PathCurvature,
    channel_band,
    channel_psf,
    fresnel_intensity,
    fresnel_psf,
    psf_grid,
    to_pixels,
)
from sim_devices.optics.point_spread import MAX_KERNELS, FresnelBlur
from sim_devices.world import SimWorld

PITCH, Z2, RADIUS, LAM = 5.9e-6, 0.025, 1e-4, 540e-9  # the reference camera, green
Z1 = 0.187  # the light's virtual image in front of the pinhole (issue 23)
CIRCLE = ApertureShape.circle(2 * RADIUS)


def _path(fresnel_number, radius=RADIUS, wavelength=LAM):
    """On the axis, with 1/z1 + 1/z2 chosen for the Fresnel number (z1 < 0: a converging wave)."""
    return PathCurvature.on_axis(1.0 / (fresnel_number * wavelength / radius**2 - 1.0 / Z2), Z2, PITCH)


def _radius_grid(psf):
    c = psf.shape[0] // 2
    rows, cols = np.indices(psf.shape)
    return np.hypot(rows - c, cols - c)


def _fwhm(psf):
    """Full width at half maximum along the row through the centre (linear interpolation)."""
    c = psf.shape[0] // 2
    row, half = psf[c], psf[c, c] / 2
    k = c
    while row[k] > half:
        k += 1
    return 2 * (k - 1 + (row[k - 1] - half) / (row[k - 1] - row[k]) - c)


# --- flux --------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "aperture",
    [
        CIRCLE,
        ApertureShape.ellipse((2.05e-4, 1.95e-4), math.radians(20)),
        ApertureShape.circle(2e-4, roughness_rms=1e-6, roughness_correlation=5e-6, roughness_seed=1),
    ],
    ids=["circle", "ellipse", "rough"],
)
def test_the_point_spread_holds_the_whole_flux(aperture):
    path = PathCurvature.on_axis(Z1, Z2, PITCH)
    for integrated in (True, False):
        psf = fresnel_psf(aperture, LAM, path, pixel_integrated=integrated)
        assert psf.sum() == pytest.approx(1.0, abs=1e-9)
        assert psf.min() > -1e-9
    # Before the uniform floor is added back, the grid holds all but the grey edge cells' share:
    # Σ T² / Σ T of the hole, a fraction ~2/(3 n) with n cells across it (0.5 % at 128).
    grid = psf_grid(aperture, np.array([LAM]), path)
    fine = fresnel_intensity(aperture, LAM, path, grid)
    floor = fine[0, 0]  # the far corner: nothing but the floor (the pattern there is ~1e-12)
    assert 0 < floor * grid.n**2 < 0.01


def test_a_rendered_frame_keeps_the_flux_of_the_geometric_image(monkeypatch):
    """The whole chain at the demo rig's pitch, on a sensor large enough to hold the tails: the
    convolution keeps the sharp image's flux to rounding, and the sharp image (the chief rays) has
    the flux of the geometric one (rays through the whole aperture) within the two samplings' noise
    (0.2 % between seeds)."""
    rig = rig_with(camera__pixel_pitch_m=11.8e-6, camera__width=1400, camera__height=1400)
    pose = rig.light_poses()[33]
    truth = TruthLight(
        emitters=[Emitter(name="s", radius_m=0.3e-3, intensity=GaussianIntensity(peak_w_sr=1.0, sigma_deg=40.0))]
    )
    geometric = MirrorBallRenderer(rig, truth, diffraction=False, seed=2).render(pose).rate
    fresnel = MirrorBallRenderer(rig, truth, point_spread="fresnel", seed=2).render(pose).rate
    sharp_renderer = MirrorBallRenderer(rig, truth, point_spread="fresnel", seed=2)
    monkeypatch.setattr(sharp_renderer.fresnel, "blur", lambda layer, path: layer)
    sharp = sharp_renderer.render(pose).rate
    for ch in range(3):
        assert fresnel[ch].sum() == pytest.approx(sharp[ch].sum(), rel=1e-6)  # single-precision kernels
        assert sharp[ch].sum() == pytest.approx(geometric[ch].sum(), rel=6e-3)


# --- the analytic limits ---------------------------------------------------------------------------
@pytest.mark.parametrize("fresnel_number", [0.25, 0.5, 0.84, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0])
def test_on_axis_intensity_of_a_circle_follows_sin_squared(fresnel_number):
    """|U(0)|² = (2λ/Q)² sin²(πN_F/2) over the flux πa² (λz₂)²: 4 sin²(πN_F/2) times the geometric
    shadow's level, 1/(π (a z₂ Q)²) per m² (Born & Wolf §8.8.1; Q = 1/z₁ + 1/z₂, N_F = a²Q/λ).
    Maxima of four times the shadow at odd N_F, zeros at even N_F."""
    path = _path(fresnel_number)
    assert path.fresnel_number(RADIUS, LAM) == pytest.approx(fresnel_number, rel=1e-12)
    psf = fresnel_psf(CIRCLE, LAM, path, pixel_integrated=False)
    c = psf.shape[0] // 2
    q = fresnel_number * LAM / RADIUS**2
    shadow_level = PITCH**2 / (math.pi * (RADIUS * Z2 * q) ** 2)
    expected = 4 * math.sin(math.pi * fresnel_number / 2) ** 2
    assert psf[c, c] / shadow_level == pytest.approx(expected, abs=0.02)  # 0.5 % of the maxima
    if fresnel_number < 1:
        assert psf[c, c] / shadow_level == pytest.approx(expected, rel=2e-3)


@pytest.mark.parametrize("fresnel_number", [0.0, 0.01])
def test_far_field_is_the_airy_pattern(fresnel_number):
    """N_F ≪ 1 (here a converging wave, z₁ ≈ −z₂): the Airy pattern (2 J₁(x)/x)² with
    x = π D r / (λ z₂), peak πa²/(λz₂)² per m² of unit flux, first zero at 1.22 λ z₂ / D."""
    psf = fresnel_psf(CIRCLE, LAM, _path(fresnel_number), pixel_integrated=False)
    r = _radius_grid(psf)
    x = 2 * math.pi * RADIUS * r * PITCH / (LAM * Z2)
    safe = np.where(x > 0, x, 1.0)
    airy = np.where(x > 0, (2 * j1(safe) / safe) ** 2, 1.0) * math.pi * RADIUS**2 / (LAM * Z2) ** 2 * PITCH**2
    assert np.abs(psf - airy).max() < 5e-4 * airy.max()
    c = psf.shape[0] // 2
    zero = 1.22 * LAM * Z2 / (2 * RADIUS) / PITCH  # 13.96 px
    profile = psf[c, c : c + 30]
    assert np.argmin(profile[:20]) == round(zero)
    assert profile[round(zero)] < 2e-3 * profile[0]


def test_near_field_is_the_geometric_shadow():
    """N_F ≫ 1: a uniform disc of the aperture projected from the point, radius a z₂ Q, edges and
    Fresnel ripples aside; the ripples shrink as N_F grows (a 2 mm hole: N_F = 84)."""
    ripples = []
    for diameter in (1e-3, 2e-3):
        path = PathCurvature.on_axis(Z1, Z2, PITCH)
        psf = fresnel_psf(ApertureShape.circle(diameter), LAM, path)
        disc = diameter / 2 * Z2 * (1 / Z1 + 1 / Z2) / PITCH  # 96 and 192 px
        r = _radius_grid(psf)
        level = psf[r < 0.8 * disc] * math.pi * disc**2
        ripples.append(level.std())
        if diameter == 2e-3:
            assert path.fresnel_number(diameter / 2, LAM) == pytest.approx(84.0, abs=0.1)
            assert level.mean() == pytest.approx(1.0, abs=0.01)
            assert psf[r < 1.1 * disc].sum() > 0.99
            assert psf[r > 1.2 * disc].max() * math.pi * disc**2 < 0.01
    assert ripples[1] < 0.6 * ripples[0]


def test_pixel_integration_is_the_average_over_the_pixel():
    """The exact band-limited integration on the pixel grid equals the mean of a grid five times
    finer over each pixel (the midpoint rule, with sensor-plane samples 1/5 px apart)."""
    path = PathCurvature.on_axis(Z1, Z2, PITCH)
    exact = fresnel_psf(CIRCLE, LAM, path)
    grid = psf_grid(CIRCLE, np.array([LAM]), path, oversample=5)
    fine = fresnel_intensity(CIRCLE, LAM, path, grid)
    # Pixel (i, j) holds the fine samples within ±2 of 5i, 5j from the centre.
    m = grid.pixels
    blocks = np.roll(fine, (2, 2), axis=(0, 1)).reshape(m, 5, m, 5).sum(axis=(1, 3))

    def centre(image, h=60):
        c = image.shape[0] // 2
        return image[c - h : c + h, c - h : c + h]

    assert np.abs(centre(blocks) - centre(exact)).max() < 2e-3 * exact.max()
    # And the same computed 3 times finer, then integrated exactly, agrees to rounding.
    grid = psf_grid(CIRCLE, np.array([LAM]), path, oversample=3)
    finer = to_pixels(fresnel_intensity(CIRCLE, LAM, path, grid), grid)
    assert np.abs(centre(finer) - centre(exact)).max() < 1e-3 * exact.max()


# --- the band ----------------------------------------------------------------------------------------
def test_the_band_is_converged_with_the_default_wavelengths():
    """Each channel's band-averaged point spread with 1, 3 and 7 Gauss–Hermite wavelengths against
    15: the default (7) is within 2e-4 of the peak and 0.01 px of FWHM (the rest is the grid's
    size, which follows the longest wavelength); a single wavelength is off by up to 1.2 % of the
    peak (the band smooths the rings)."""
    cam = load_rig().camera
    path = PathCurvature.on_axis(Z1, Z2, PITCH)
    h = 150
    for ch in range(3):
        reference = channel_psf(cam, CIRCLE, ch, path, samples=15)
        rc = reference.shape[0] // 2
        ref = reference[rc - h : rc + h + 1, rc - h : rc + h + 1]
        errors = {}
        for n in (1, 3, 7):
            psf = channel_psf(cam, CIRCLE, ch, path, samples=n)
            c = psf.shape[0] // 2
            errors[n] = np.abs(psf[c - h : c + h + 1, c - h : c + h + 1] - ref).max() / ref.max()
            if n == 7:
                assert _fwhm(psf) == pytest.approx(_fwhm(reference), abs=0.01)
        assert errors[7] < 2e-4 and errors[3] < 5e-4, errors
        assert errors[1] > 3e-3, errors  # the band does matter


def test_channel_bands_default_and_tabulated():
    cam = load_rig().camera
    for ch, centre in enumerate((610e-9, 540e-9, 465e-9)):
        wavelengths, weights = channel_band(cam, ch, 7)
        assert weights.sum() == pytest.approx(1.0)
        assert (weights * wavelengths).sum() == pytest.approx(centre, rel=1e-12)
        # A Gaussian of 80 nm FWHM: sigma 34 nm.
        sigma = math.sqrt((weights * (wavelengths - centre) ** 2).sum())
        assert sigma == pytest.approx(80e-9 / (2 * math.sqrt(2 * math.log(2))), rel=1e-9)
    table = rig_with(
        camera__spectral_response={
            "wavelengths_m": [400e-9, 500e-9, 600e-9, 700e-9],
            "r": [0, 0, 1, 0],
            "g": [0, 1, 0, 0],
            "b": [1, 0, 0, 0],
        }
    ).camera
    wavelengths, weights = channel_band(table, 1, 41)
    assert (weights * wavelengths).sum() == pytest.approx(500e-9, rel=1e-6)  # a symmetric triangle
    assert wavelengths.min() >= 400e-9 and wavelengths.max() <= 600e-9
    single = rig_with(camera__channel_bandwidths_m=[0.0, 0.0, 0.0]).camera
    assert channel_band(single, 2)[0].tolist() == [465e-9]


# --- the aperture's shapes ------------------------------------------------------------------------------
def _orientation(psf, radius=50):
    """The angle (degrees) of the pattern's long axis from its second moments in a disc."""
    c = psf.shape[0] // 2
    y, x = np.indices(psf.shape) - c
    w = psf * (np.hypot(x, y) <= radius)
    return 0.5 * math.degrees(math.atan2(2 * (w * x * y).sum(), (w * x * x).sum() - (w * y * y).sum()))


def test_an_ellipses_pattern_turns_with_its_angle():
    """The issue's ellipse (0.205 × 0.195 mm) at the reference camera: the pattern's long axis
    follows the hole's angle. A longer ellipse shows the two limits: the geometric shadow is long
    along the hole's long axis, the far field (Fraunhofer) across it."""
    path = PathCurvature.on_axis(Z1, Z2, PITCH)
    for angle in (0.0, 30.0, 75.0, 120.0):
        psf = fresnel_psf(ApertureShape.ellipse((2.05e-4, 1.95e-4), math.radians(angle)), LAM, path)
        turned = (_orientation(psf) - angle + 90.0) % 180.0 - 90.0
        assert abs(turned) < 0.5, (angle, _orientation(psf))
    long = ApertureShape.ellipse((1.6e-3, 0.8e-3), math.radians(30))  # N_F = 38 along the long axis
    assert _orientation(fresnel_psf(long, LAM, path), radius=160) == pytest.approx(30.0, abs=0.5)
    far = ApertureShape.ellipse((3e-4, 1.5e-4), math.radians(30))
    assert _orientation(fresnel_psf(far, LAM, _path(0.0, radius=1.5e-4))) == pytest.approx(-60.0, abs=0.5)


def test_a_mask_image_of_a_circle_gives_the_circles_pattern(tmp_path):
    """A 16-bit PNG of the 0.2 mm hole, 0.5 µm a pixel, off-centre in its image, named by the rig
    (relative to the rig file): the same point spread as the circle, within 0.3 % of its peak."""
    pixel = 0.5e-6
    rows, cols = np.indices((500, 520))
    # Antialiased: the circle's area fraction in each pixel, its centre (260.3, 240.6) px.
    grey = CIRCLE.transmission((cols + 0.5 - 260.3) * pixel, (rows + 0.5 - 240.6) * pixel, pixel)
    cv2.imwrite(str(tmp_path / "pinhole.png"), np.round(grey * 65535).astype(np.uint16))
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(
        'schema_version = 2\n[camera.aperture]\nshape = "mask"\nmask = "pinhole.png"\nmask_pixel_m = 5e-7\n'
    )
    camera = load_rig(rig_file).camera
    mask = ApertureShape.from_rig(camera)
    assert mask.area() == pytest.approx(math.pi * RADIUS**2, rel=1e-4)
    path = PathCurvature.on_axis(Z1, Z2, PITCH)
    for ch in range(3):
        circle, masked = channel_psf(camera, CIRCLE, ch, path, 3), channel_psf(camera, mask, ch, path, 3)
        c, cm = circle.shape[0] // 2, masked.shape[0] // 2
        h = 100
        diff = masked[cm - h : cm + h + 1, cm - h : cm + h + 1] - circle[c - h : c + h + 1, c - h : c + h + 1]
        assert np.abs(diff).max() < 3e-3 * circle.max()


def test_a_masks_shadow_on_the_image_is_the_hole_turned_half_a_turn():
    """The mask is the aperture seen from the sensor (x along the image's columns): a 1 mm hole
    with a notch cut on its +x side (N_F = 21) throws its shadow on the image with the notch on
    the −x side, and the shadow is centred on the chief ray (the mask is centred on its centroid,
    which the notch moves 10 mask pixels)."""
    pixel = 2e-6
    rows, cols = np.indices((600, 600))
    x, y = (cols + 0.5 - 300) * pixel, (rows + 0.5 - 300) * pixel
    hole = (np.hypot(x, y) < 5e-4) & ~((x > 3e-4) & (np.abs(y) < 1e-4))
    mask = ApertureShape.from_mask(hole.astype(float), pixel)
    assert mask.mask_centre[0] - 300 == pytest.approx(-10.5, abs=0.1)
    psf = fresnel_psf(mask, LAM, PathCurvature.on_axis(Z1, Z2, PITCH))
    c = psf.shape[0] // 2
    disc = 5e-4 * Z2 * (1 / Z1 + 1 / Z2) / PITCH  # 96 px
    level = 1 / (math.pi * disc**2)
    yy, xx = np.indices(psf.shape) - c
    assert abs((psf * xx).sum()) < 0.05 and abs((psf * yy).sum()) < 0.05
    notch, opposite = psf[c, c - round(0.9 * disc)] / level, psf[c, c + round(0.9 * disc)] / level
    assert notch < 0.2 and opposite > 0.4


def test_a_rough_edge_is_seeded_and_has_the_rms_asked():
    rough = ApertureShape.circle(2e-4, roughness_rms=1e-6, roughness_correlation=5e-6, roughness_seed=7)
    phi = np.linspace(0, 2 * math.pi, 5000, endpoint=False)
    edge, _ = rough._edge(phi)
    assert np.sqrt(np.mean((edge - RADIUS) ** 2)) == pytest.approx(1e-6, rel=0.01)
    # Its correlation along the edge: about exp(-1/2) one correlation length (5 µm) apart.
    delta = edge - RADIUS
    shift = round(5e-6 / RADIUS / (2 * math.pi) * phi.size)
    assert np.mean(delta * np.roll(delta, shift)) / np.mean(delta**2) == pytest.approx(math.exp(-0.5), abs=0.15)
    again = ApertureShape.circle(2e-4, roughness_rms=1e-6, roughness_correlation=5e-6, roughness_seed=7)
    np.testing.assert_array_equal(again._edge(phi)[0], edge)
    other = ApertureShape.circle(2e-4, roughness_rms=1e-6, roughness_correlation=5e-6, roughness_seed=8)
    assert not np.allclose(other._edge(phi)[0], edge)
    path = PathCurvature.on_axis(Z1, Z2, PITCH)
    smooth, bumpy = fresnel_psf(CIRCLE, LAM, path), fresnel_psf(rough, LAM, path)
    c, cb, h = smooth.shape[0] // 2, bumpy.shape[0] // 2, 100
    change = np.abs(bumpy[cb - h : cb + h, cb - h : cb + h] - smooth[c - h : c + h, c - h : c + h]).max()
    assert 1e-4 < change / smooth.max() < 0.03


# --- the path through the ball ------------------------------------------------------------------------
def _specular_point(source, camera_centre, centre, radius, iterations=200):
    """The point of the ball that reflects ``source`` into the camera (bisector iteration)."""
    p = centre + radius * (source + camera_centre - 2 * centre) / np.linalg.norm(source + camera_centre - 2 * centre)
    for _ in range(iterations):
        a = (source - p) / np.linalg.norm(source - p)
        b = (camera_centre - p) / np.linalg.norm(camera_centre - p)
        n = (a + b) / np.linalg.norm(a + b)
        p = centre + radius * n
    return p


def test_image_distances_through_the_ball_follow_coddington():
    """The path the renderer measures by tracing neighbouring rays: a symmetric Q (a Hessian),
    and image distances that are Coddington's tangential and sagittal foci of the convex mirror,
    1/d′ = 1/d + 2/(R cos α) and 1/d + 2 cos α / R, seen from the pinhole (186–189 mm)."""
    rig = load_rig()
    renderer = MirrorBallRenderer(rig, None, point_spread="fresnel")
    cam_centre, centre, radius = rig.camera.centre(), np.zeros(3), rig.ball.radius_m
    emitter = Emitter(name="c", radius_m=0.5e-3, intensity=GaussianIntensity(peak_w_sr=1.0, sigma_deg=20.0))
    for position in (0, 33, 65):
        pose = rig.light_poses()[position]
        plane = LightPlane.at(rig, pose)
        col, row = renderer._ball_pixels()
        zero = np.zeros_like(col)
        chief = trace(renderer.camera, renderer.mirror, plane, col, row, zero, zero, fresnel=False)
        uv0 = np.column_stack([chief.u[chief.valid], chief.v[chief.valid]])
        path = renderer._emitter_path(plane, emitter, col[chief.valid], row[chief.valid], uv0)
        q = path.quadratic
        # Q = -G M from the rays is symmetric only with the right G (the sensor's obliquity).
        raw = -path.conjugate @ path.magnification()
        assert abs(raw[0, 1] - raw[1, 0]) < 1e-6 * np.trace(q)
        p = _specular_point(pose.position, cam_centre, centre, radius)
        d, c = np.linalg.norm(pose.position - p), np.linalg.norm(cam_centre - p)
        cos_a = float(np.dot((p - centre) / radius, (pose.position - p) / d))
        foci = sorted(c + 1 / (1 / d + 2 * k / radius) for k in (1 / cos_a, cos_a))
        measured = sorted(path.image_distances()[:2])
        np.testing.assert_allclose(measured, foci, atol=1e-5)  # measured: 1 µm
        assert 0.1855 < measured[0] and measured[1] < 0.1895


# --- the renderer ----------------------------------------------------------------------------------------
def _crop_rig(**edits):
    """The reference rig's sensor cropped to 320 px around the middle position's sources."""
    return rig_with(
        camera__width=320, camera__height=320, camera__principal_point_px=[999.5 - 840, 655.5 - 400], **edits
    )


@pytest.fixture(scope="module")
def point_source_frames():
    """A 0.02 mm source at the middle position, rendered three ways (seeded)."""
    rig = _crop_rig()
    pose = rig.light_poses()[33]
    intensity = GaussianIntensity(peak_w_sr=1.0, sigma_deg=60.0)
    tiny = TruthLight(emitters=[Emitter(name="s", radius_m=0.02e-3, intensity=intensity)])
    fresnel = MirrorBallRenderer(rig, tiny, point_spread="fresnel", seed=4)
    return {
        "rig": rig,
        "fresnel": fresnel.render(pose),
        "renderer": fresnel,
        "airy": MirrorBallRenderer(rig, tiny, point_spread="geometric-airy", seed=4).render(pose).rate,
        "geometric": MirrorBallRenderer(rig, tiny, diffraction=False, seed=4).render(pose).rate,
    }


def test_a_point_source_on_the_reference_rig_has_the_issues_point_spread(point_source_frames, capsys):
    """Issue 23's table, from a rendered frame: FWHM 13.5 / 12.0 / 10.5 px (R, G, B) against the
    geometric⊗Airy model's 37.7, and peaks 3.4 / 3.7 / 3.9 times the geometric shadow's level
    against 0.85–0.90."""
    frames = point_source_frames
    geometric = frames["geometric"]
    rows = []
    for ch, (fwhm, peak) in enumerate(((13.5, 3.39), (12.0, 3.74), (10.5, 3.95))):
        fresnel, airy = frames["fresnel"].rate[ch], frames["airy"][ch]
        # The shadow's level: the geometric image's flux over the projected disc (radius 19.2 px).
        level = geometric[ch].sum() / (math.pi * 19.2**2)
        widths = [2 * math.sqrt(np.count_nonzero(img >= img.max() / 2) / math.pi) for img in (fresnel, airy)]
        rows.append((ch, *widths, fresnel.max() / level, airy.max() / level))
        assert widths[0] == pytest.approx(fwhm, abs=0.6)
        assert widths[1] == pytest.approx(37.7, abs=1.0)
        assert fresnel.max() / level == pytest.approx(peak, rel=0.04)
        assert airy.max() / level == pytest.approx(0.87, abs=0.04)
    with capsys.disabled():
        for ch, wf, wa, pf, pa in rows:
            print(f"\nchannel {'RGB'[ch]}: FWHM {wf:.2f} px (geometric⊗Airy {wa:.2f}), peak/shadow {pf:.3f} ({pa:.3f})")


def test_the_renderer_caches_its_kernels(point_source_frames):
    renderer = point_source_frames["renderer"]
    rig = point_source_frames["rig"]
    stats = renderer.fresnel.stats
    assert stats.computed == 3  # one path, three channels
    (z_a, z_b) = point_source_frames["fresnel"].stats.per_emitter_image_distance["s"]
    assert 0.1855 < min(z_a, z_b) and max(z_a, z_b) < 0.1895
    renderer.render(rig.light_poses()[34])  # the light 2.5 mm on: the same rounded path
    assert stats.computed == 3 and stats.reused >= 3


def test_the_kernel_cache_keeps_the_most_recent_paths():
    camera = rig_with(camera__pixel_pitch_m=23.6e-6, camera__width=500, camera__height=328).camera
    blur = FresnelBlur(camera, CIRCLE, band_samples=3)
    paths = [PathCurvature.on_axis(0.160 + 0.005 * k, Z2, 23.6e-6) for k in range(MAX_KERNELS // 3 + 1)]
    assert len({blur.rounded(path).key for path in paths}) == len(paths)
    for path in paths:
        for ch in range(3):
            kernel = blur.kernel(ch, path)
            assert kernel.dtype == np.float32 and kernel.sum(dtype=float) == pytest.approx(1.0, abs=1e-6)
    assert blur.stats.computed == 3 * len(paths) and len(blur._kernels) == MAX_KERNELS
    blur.kernel(0, paths[-1])  # kept
    assert blur.stats.computed == 3 * len(paths) and blur.stats.reused == 1
    blur.kernel(0, paths[0])  # the oldest: dropped, computed again
    assert blur.stats.computed == 3 * len(paths) + 1


def test_the_simulated_camera_takes_the_rigs_point_spread_and_blurs_the_lit_room(tmp_path):
    """``camera.point_spread = "fresnel"`` reaches the renderer; a calibration frame (the room
    lit, the light off: the whole ball) keeps the geometric frame's flux and shows a sharper
    silhouette (the Fresnel pattern is a third as wide at half height as the geometric⊗Airy one)."""
    rig = rig_with(camera__width=500, camera__height=328, camera__pixel_pitch_m=23.6e-6, camera__point_spread="fresnel")
    world = SimWorld(lambda: rig.tool_poses()[33], rig.light.light_to_tool.to_pose(), light_on=False, room_lit=True)
    camera = SimulatedCamera(rig, world, tmp_path, seed=1, environment_radiance=ROOM_RADIANCE)
    assert camera.renderer.fresnel is not None
    fresnel = camera.rendering().rate
    room = {"seed": 1, "environment_radiance": ROOM_RADIANCE}
    old = SimulatedCamera(rig, world, tmp_path, point_spread="geometric-airy", **room)
    assert old.renderer.fresnel is None
    airy = old.rendering().rate
    assert fresnel.sum() == pytest.approx(airy.sum(), rel=2e-3)
    # The silhouette's steepest step along the middle row, over the ball's brightness there.
    row = fresnel.shape[1] // 2
    steepness = [np.abs(np.diff(rate[1, row])).max() / rate[1, row].max() for rate in (fresnel, airy)]
    assert steepness[0] > 1.5 * steepness[1], steepness  # measured: 1.73 times as steep


def test_an_astigmatic_wave_throws_an_elliptical_shadow():
    """Image distances of 50 and 187 mm along axes turned 30°: in the geometric regime (a 1 mm
    hole) the shadow is an ellipse of radii a z₂ (1/z₁ + 1/z₂) along each axis (127 and 96 px),
    whose second moments are r²/4."""
    path = PathCurvature.on_axis((0.05, Z1), Z2, PITCH, math.radians(30))
    z_a, z_b, angle = path.image_distances()
    assert sorted((z_a, z_b)) == pytest.approx([0.05, Z1], rel=1e-12)
    psf = fresnel_psf(ApertureShape.circle(1e-3), LAM, path)
    assert _orientation(psf, radius=200) == pytest.approx(30.0, abs=0.5)
    c = psf.shape[0] // 2
    yy, xx = np.indices(psf.shape) - c
    inside = np.hypot(xx, yy) < 200
    turn = math.radians(30)
    u, v = xx * math.cos(turn) + yy * math.sin(turn), -xx * math.sin(turn) + yy * math.cos(turn)
    for axis, z1 in ((u, 0.05), (v, Z1)):
        radius = 5e-4 * Z2 * (1 / z1 + 1 / Z2) / PITCH
        assert math.sqrt(4 * (psf * axis**2 * inside).sum()) == pytest.approx(radius, rel=0.02)


def test_without_diffraction_the_fresnel_camera_is_the_geometric_one():
    rig = _crop_rig(camera__point_spread="fresnel", simulation__diffraction=False)
    renderer = MirrorBallRenderer(rig, None, diffraction=False, point_spread="fresnel")
    assert renderer.fresnel is None and renderer.camera.aperture_radius == pytest.approx(1e-4)


# --- the rig --------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("edits", "message"),
    [
        ({"camera__aperture": {"shape": "ellipse"}}, "camera.aperture: axes_m: required for an ellipse"),
        ({"camera__aperture": {"angle_deg": 10.0}}, "camera.aperture: angle_deg: only for an ellipse"),
        ({"camera__aperture": {"shape": "mask", "mask": "a.png"}}, "camera.aperture: mask_pixel_m: required"),
        (
            {"camera__aperture": {"shape": "mask", "mask": "a", "mask_pixel_m": 1e-7, "edge_roughness_rms_m": 1e-8}},
            "edge_roughness_rms_m: a mask already has its own edge",
        ),
        ({"camera__aperture": {"edge_roughness_rms_m": 2e-5}}, "aperture.edge_roughness_rms_m: must be below 10 %"),
        ({"camera__aperture": {"shape": "square"}}, "camera.aperture.shape: Input should be"),
        ({"camera__channel_bandwidths_m": [80e-9, 600e-9, 80e-9]}, "channel_bandwidths_m: each band"),
        ({"camera__channel_bandwidths_m": [80e-9, -1e-9, 80e-9]}, "camera.channel_bandwidths_m[1]: must be >= 0"),
        (
            {"camera__spectral_response": {"wavelengths_m": [5e-7, 4e-7], "r": [1, 1], "g": [1, 1], "b": [1, 1]}},
            "camera.spectral_response: wavelengths_m: must be strictly ascending",
        ),
        (
            {"camera__spectral_response": {"wavelengths_m": [4e-7, 5e-7], "r": [1], "g": [1, 1], "b": [1, 1]}},
            "camera.spectral_response: r: 1 values for 2 wavelengths",
        ),
        ({"camera__point_spread": "wave"}, "camera.point_spread: Input should be"),
    ],
)
def test_the_rigs_new_fields_are_refused_in_one_line(edits, message):
    with pytest.raises(RigError) as error:
        rig_with(**edits)
    text = str(error.value)
    assert message in text and "\n" not in text


def test_an_unreadable_mask_names_the_field(tmp_path):
    (tmp_path / "rig.toml").write_text(
        'schema_version = 2\n[camera.aperture]\nshape = "mask"\nmask = "missing.png"\nmask_pixel_m = 5e-7\n'
    )
    camera = load_rig(tmp_path / "rig.toml").camera
    assert camera.aperture.mask == str(tmp_path / "missing.png")
    with pytest.raises(RigError, match=r"^camera\.aperture\.mask: .*missing\.png: aperture mask not found$"):
        ApertureShape.from_rig(camera)
    cv2.imwrite(str(tmp_path / "missing.png"), np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(RigError, match="not an 8- or 16-bit greyscale image"):
        ApertureShape.from_rig(camera)
