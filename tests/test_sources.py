"""The processing's tracer, templates and unmixing against the simulated camera.

The two sides were written independently (sim_devices traces backwards from pixels with
sampled apertures; processing builds templates from exact specular paths), so agreement
is evidence, not an echo.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from acquisition.rig import load_rig
from conftest import REDUCED_RIG
from processing.pipeline import choose_estimator
from processing.sources import Source, SourcesError, TemplateBuilder, load_layout, unmix_position
from processing.trace import RigGeometry, ball_pixel_grid, trace_pixels
from sim_devices.lights import LIGHTS_DIR, TruthLight, load_truth
from sim_devices.optics import CameraOptics, LightPlane, Mirror, MirrorBallRenderer
from sim_devices.optics import trace as sim_trace
from sim_devices.sensor import mosaic_of
from test_render import _crop_rig, rig_with


def test_chief_rays_agree_with_the_simulators_independent_tracer():
    rig = load_rig(REDUCED_RIG)
    geometry = RigGeometry.from_rig(rig)
    for pose in (rig.light_poses()[0], rig.light_poses()[33], rig.light_poses()[65]):
        cols, rows = ball_pixel_grid(geometry)
        ours = trace_pixels(geometry, pose, cols, rows)
        theirs = sim_trace(CameraOptics.from_rig(rig), Mirror.from_rig(rig), LightPlane.at(rig, pose), cols, rows,
                           np.zeros_like(cols), np.zeros_like(cols))  # fmt: skip
        assert np.array_equal(ours.valid, theirs.valid)
        both = ours.valid & (np.hypot(ours.u, ours.v) < 0.2)
        np.testing.assert_allclose(ours.theta[both], theirs.theta[both], atol=1e-9)
        np.testing.assert_allclose(ours.u[both], theirs.u[both], atol=1e-9)
        np.testing.assert_allclose(ours.fresnel[both], theirs.fresnel[both], atol=1e-12)
        np.testing.assert_allclose(ours.cos4[both], theirs.cos4[both], atol=1e-12)


def _moments(image, row0=0, col0=0):
    rows, cols = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    total = image.sum()
    cy, cx = (image * rows).sum() / total + row0, (image * cols).sum() / total + col0
    spread = math.sqrt((image * ((rows + row0 - cy) ** 2 + (cols + col0 - cx) ** 2)).sum() / total / 2)
    return total, cx, cy, spread


@pytest.mark.parametrize("position", [5, 33])
def test_a_template_matches_the_simulated_image_of_its_source(position):
    rig = load_rig()
    pose = rig.light_poses()[position]
    emitter = load_truth("five-gaussians").emitters[3]  # +v
    builder = TemplateBuilder(RigGeometry.from_rig(rig), rig.camera.sensitivity_e_per_s, diffraction=False)
    template = builder.build(Source(emitter.name, tuple(emitter.centre_m), emitter.radius_m), pose)
    simulated = MirrorBallRenderer(rig, TruthLight(emitters=[emitter]), diffraction=False, seed=1).render(pose).rate[1]
    expected = template.image[1] * emitter.intensity_w_sr(template.theta)
    flux, cx, cy, spread = _moments(simulated)
    t_flux, t_cx, t_cy, t_spread = _moments(expected, template.row0, template.col0)
    assert t_flux == pytest.approx(flux, rel=3e-3)  # radiometry: k f² F Ω / (A_px A_ap)
    assert math.hypot(t_cx - cx, t_cy - cy) < 0.05  # pixels
    assert t_spread == pytest.approx(spread, rel=3e-3)
    assert template.blur_radius_px == pytest.approx(19.2, abs=0.4)  # measurement.md: ~38 px across


def test_unmixing_recovers_five_sources_4_mm_apart():
    rig = _crop_rig()  # full pitch, around the sources at the middle position
    truth = load_truth("five-gaussians")
    layout = [Source(e.name, tuple(e.centre_m), e.radius_m) for e in truth.emitters]
    pose = rig.light_poses()[33]
    rate = MirrorBallRenderer(rig, truth, diffraction=True, seed=2).render(pose).rate
    mosaic = mosaic_of(rate, "RGGB")
    variance = mosaic / 1e-3 + (3.0 / 1e-3) ** 2  # as an HDR merge of ~1 ms exposures would report
    builder = TemplateBuilder(RigGeometry.from_rig(rig), rig.camera.sensitivity_e_per_s)
    estimate = unmix_position(33, mosaic, variance, np.ones(mosaic.shape, bool), "RGGB", builder, layout, pose)
    truth_i = np.array([e.intensity_w_sr(t) for e, t in zip(truth.emitters, estimate.theta, strict=True)])
    error = np.abs(estimate.intensity.mean(axis=1) / truth_i - 1)
    assert error.max() < 0.01, error
    assert np.all(estimate.visible)
    # The sources image 7-12 px apart, as measurement.md says.
    centres = np.array([t.image_centre for t in estimate.templates])
    gaps = [math.dist(centres[0], c) for c in centres[1:]]
    assert 7 < min(gaps) and max(gaps) < 13


def test_the_estimator_follows_the_footprint():
    layout = load_layout(LIGHTS_DIR / "five-gaussians.toml")
    pinhole = load_rig()
    builder = TemplateBuilder(RigGeometry.from_rig(pinhole), 1.0)
    chosen, reason, footprint = choose_estimator(RigGeometry.from_rig(pinhole), builder, layout, pinhole.light_poses()[33], "auto")
    assert chosen == "templates" and "unmixing" in reason
    assert 12 <= 2e3 * footprint <= 23  # measurement.md: a pixel gathers rays from 12-23 mm
    lens = rig_with(camera__thin_lens={"focus_distance_m": 0.186, "f_number": 8.0})
    chosen, reason, footprint = choose_estimator(RigGeometry.from_rig(lens), TemplateBuilder(RigGeometry.from_rig(lens), 1.0),
                                                 layout, lens.light_poses()[33], "auto")  # fmt: skip
    assert chosen == "cell-sums" and "flux sums" in reason


def test_layout_errors_are_one_line(tmp_path):
    with pytest.raises(SourcesError, match=r"nope\.toml: layout file not found"):
        load_layout(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text('[[sources]]\nname = "a"\ncentre_m = [0.0]\n')
    with pytest.raises(SourcesError, match=r"bad\.toml: sources\[0\]\.centre_m: needs \[u, v\] in metres"):
        load_layout(bad)
    bad.write_text('[[sources]]\nname = "a"\ncentre_m = [0.0, nan]\n')  # inf and nan are TOML literals
    with pytest.raises(SourcesError, match=r"bad\.toml: sources\[0\]\.centre_m: must be finite \(got \[0\.0, nan\]\)"):
        load_layout(bad)
    bad.write_text('[[sources]]\nname = "a"\ncentre_m = [0.0, 0.0]\nradius_m = inf\n')
    with pytest.raises(SourcesError, match=r"bad\.toml: sources\[0\]\.radius_m: must be finite and > 0 \(got inf\)"):
        load_layout(bad)
    assert [s.name for s in load_layout(LIGHTS_DIR / "five-gaussians.toml")] == ["centre", "+u", "-u", "+v", "-v"]
