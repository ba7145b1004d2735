"""The fast paths of the source estimate against the direct computations they replace.

Templates and cell sums are computed per position of every run, so they take shortcuts
(compiled loops, smaller FFT grids, tracing only the pixels near the cells); each must give
the numbers of the direct computation, which is written out here once more to compare.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import REDUCED_RIG
from scipy import fft as sfft
from scipy.signal import fftconvolve

import processing.unmixing.cell_flux as cell_sums_module
import processing.unmixing.psf as psf
from drivers.contracts.rig import load_rig
from drivers.pose import Pose
from processing.trace import RigGeometry, ball_pixel_grid, specular_points, trace_pixels
from processing.unmixing.cell_flux import cell_pixel_boxes, cell_sums
from processing.unmixing.sources import Source, load_layout
from sim_devices.lights import LIGHTS_DIR


def _reference_specular(s, t, centre, radius, iterations=60):
    """The law-of-reflection iteration as plain NumPy (the form the compiled one replaced)."""

    def unit(v):
        return v / np.sqrt(np.einsum("...i,...i->...", v, v))[..., None]

    s, t = s - centre, t - centre
    p = radius * unit(unit(s) + unit(t))
    for _ in range(iterations):
        p = radius * unit(unit(s - p) + unit(t - p))
    return p + centre


@pytest.mark.parametrize("iterations", [0, 1, 2, 7, 60, 61])
def test_specular_points_are_the_iteration_they_stand_for(iterations):
    rng = np.random.default_rng(iterations)
    centre, radius = np.array([0.001, -0.002, 0.0]), 0.0254
    s = np.array([0.0, 0.04, 0.1]) + rng.normal(0.0, 0.01, (300, 3))
    t = np.array([0.0, 0.0, 0.2]) + rng.normal(0.0, 1e-4, (300, 3))
    found = specular_points(s, t, centre, radius, iterations)
    np.testing.assert_allclose(found, _reference_specular(s, t, centre, radius, iterations), rtol=0, atol=1e-15)
    if iterations >= 60:  # converged: the normal bisects the directions to source and target
        normal = (found - centre) / radius
        to_s, to_t = s - found, t - found
        to_s /= np.linalg.norm(to_s, axis=1, keepdims=True)
        to_t /= np.linalg.norm(to_t, axis=1, keepdims=True)
        bisector = (to_s + to_t) / np.linalg.norm(to_s + to_t, axis=1, keepdims=True)
        assert np.max(np.abs(bisector - normal)) < 1e-12
    # Broadcasting, as the template builder uses it.
    one = specular_points(s[0], t[0], centre, radius, iterations)
    assert one.shape == (3,)
    np.testing.assert_array_equal(one, found[0])


def test_convex_coverage_is_the_clipped_distance_ramp():
    angles = np.linspace(0.0, 2.0 * math.pi, 96, endpoint=False)
    outline = np.stack([12.3 + 9.7 * np.cos(angles), -4.1 + 7.2 * np.sin(angles + 0.3 * np.sin(angles))], -1)
    sample = 0.25
    xs = np.arange(-2.0, 26.0, sample) + 0.125
    ys = np.arange(-16.0, 8.0, sample) + 0.125
    for polygon in (outline, outline[::-1]):  # either orientation
        got = psf.convex_coverage(polygon, xs, ys, sample)
        ccw = polygon if psf._shoelace(polygon) > 0 else polygon[::-1]
        edges = np.roll(ccw, -1, axis=0) - ccw
        normals = np.stack([edges[:, 1], -edges[:, 0]], -1)
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        offsets = np.sum(normals * ccw, axis=1)
        gx, gy = np.meshgrid(xs, ys)
        distance = np.max(gx[..., None] * normals[:, 0] + gy[..., None] * normals[:, 1] - offsets, axis=-1)
        expected = np.clip(0.5 - distance / sample, 0.0, 1.0)
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)
        assert 0 < np.count_nonzero((got > 0) & (got < 1)) < got.size // 4  # a ramp along the edge
    assert psf.polygon_area(outline) == pytest.approx(
        0.5
        * abs(np.dot(outline[:, 0], np.roll(outline[:, 1], -1)) - np.dot(outline[:, 1], np.roll(outline[:, 0], -1))),
        rel=1e-14,
    )


@pytest.mark.parametrize("n", [9, 47, 61])
def test_diffraction_is_the_padded_otf_product(n):
    rng = np.random.default_rng(n)
    geometric = rng.random((n, n))
    margin, pitch, aperture, distance = 32, 5.9e-6, 2e-4, 0.025
    wavelengths = [610e-9, 540e-9, 465e-9]
    size = n + 2 * margin
    padded = sfft.next_fast_len(4 * size, real=True)
    got = psf.diffract(geometric, size, margin, padded, pitch, aperture, distance, wavelengths)
    image = np.zeros((padded, padded))
    image[margin : margin + n, margin : margin + n] = geometric
    for c, wavelength in enumerate(wavelengths):
        otf = psf._airy_otf((padded, padded), pitch, aperture, distance, wavelength)
        expected = sfft.irfft2(sfft.rfft2(image) * otf, s=(padded, padded))[:size, :size]
        np.testing.assert_allclose(got[c], expected, rtol=0, atol=1e-13 * expected.max())


def test_same_convolution_is_scipys():
    rng = np.random.default_rng(0)
    for n, k in ((188, 15), (60, 3), (101, 21)):
        image, kernel = rng.random((n, n)), rng.random((k, k))
        expected = fftconvolve(image, kernel, mode="same")
        np.testing.assert_allclose(psf.convolve_same(image, kernel), expected, rtol=0, atol=1e-13 * expected.max())


@pytest.mark.parametrize("rig_path", [REDUCED_RIG, None])
def test_cell_boxes_hold_every_pixel_that_lands_in_a_cell(rig_path):
    rig = load_rig(rig_path) if rig_path else load_rig()
    geometry = RigGeometry.from_rig(rig)
    layout = load_layout(LIGHTS_DIR / "five-gaussians.toml") + [Source("far", (0.03, -0.02), 0.5e-3)]
    cols, rows = ball_pixel_grid(geometry)
    poses = rig.light_poses()
    for pose in (poses[0], poses[33], poses[65]) if rig_path else (poses[33],):
        rays = trace_pixels(geometry, pose, cols, rows)
        for radius in (0.3e-3, 2e-3, 6e-3, 20e-3):
            boxes = cell_pixel_boxes(geometry, pose, layout, radius, (geometry.height, geometry.width))
            assert boxes is not None
            boxed = np.zeros((geometry.height, geometry.width), bool)
            for r0, r1, c0, c1 in boxes:
                boxed[r0:r1, c0:c1] = True
            for s in layout:
                lands = rays.valid & (np.hypot(rays.u - s.centre[0], rays.v - s.centre[1]) <= radius)
                assert np.all(boxed[rows[lands].astype(int), cols[lands].astype(int)]), (s.name, radius)
            # The boxes are a few pixels wider than the cells, not the frame.
            assert boxed.sum() < 0.1 * geometry.height * geometry.width


def test_cell_sums_over_the_boxes_are_the_sums_over_every_pixel(monkeypatch):
    rig = load_rig(REDUCED_RIG)
    geometry = RigGeometry.from_rig(rig)
    layout = load_layout(LIGHTS_DIR / "five-gaussians.toml")
    rng = np.random.default_rng(3)
    shape = (geometry.height, geometry.width)
    rate = rng.gamma(2.0, 50.0, shape) * (rng.random(shape) > 0.05)
    usable = rng.random(shape) > 0.02
    for pose in rig.light_poses()[::22]:
        for radius in (0.5e-3, 2e-3, 8e-3):
            fast = cell_sums(rate, usable, geometry, 1000.0, layout, pose, radius)
            with monkeypatch.context() as m:
                m.setattr(cell_sums_module, "cell_pixel_boxes", lambda *args, **kwargs: None)
                every = cell_sums(rate, usable, geometry, 1000.0, layout, pose, radius)
            assert np.any(every > 0)
            np.testing.assert_array_equal(fast, every)


def test_cell_boxes_decline_a_ball_behind_the_light_plane():
    rig = load_rig(REDUCED_RIG)
    geometry = RigGeometry.from_rig(rig)
    pose = rig.light_poses()[33]
    flipped = pose.compose(Pose(0.0, 0.0, 0.0, math.pi, 0.0, 0.0))  # facing away from the ball
    layout = [Source("a", (0.0, 0.0), 0.5e-3)]
    assert cell_pixel_boxes(geometry, flipped, layout, 2e-3, (geometry.height, geometry.width)) is None
    assert cell_pixel_boxes(geometry, pose, layout, math.inf, (geometry.height, geometry.width)) is None


@pytest.mark.parametrize("max_pixels", [None, 10**9, 250_000, 60_000, 40_000, 1_000, 1])
def test_a_strided_ball_grid_is_the_whole_box_thinned(max_pixels):
    geometry = RigGeometry.from_rig(load_rig())
    cols, rows = ball_pixel_grid(geometry)
    stride = 1 if max_pixels is None else max(1, math.ceil(math.sqrt(cols.size / max_pixels)))
    keep = (cols % stride == 0) & (rows % stride == 0)
    thin_cols, thin_rows = ball_pixel_grid(geometry, max_pixels)
    np.testing.assert_array_equal(thin_cols, cols[keep])
    np.testing.assert_array_equal(thin_rows, rows[keep])
    if max_pixels is not None:  # about max_pixels: the box's whole rows and columns, one more of each at most
        width, height = np.ptp(cols) + 1, np.ptp(rows) + 1
        assert (
            thin_cols.size <= (width / stride + 1) * (height / stride + 1)
            and thin_cols.size >= min(cols.size, max_pixels) / 4
        )
