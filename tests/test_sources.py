"""The processing's tracer, templates and unmixing against the simulated camera.

The two sides were written independently (sim_devices traces backwards from pixels with
sampled apertures; processing builds templates from exact specular paths), so agreement
is evidence, not an echo.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from conftest import REDUCED_RIG
from test_render import _crop_rig, rig_with

from drivers.contracts.rig import load_rig
from processing.light_run.samples import choose_estimator
from processing.trace import RigGeometry, ball_pixel_grid, trace_pixels
from processing.unmixing.problem import LayoutData
from processing.unmixing.search import refine_layout
from processing.unmixing.sources import Source, SourcesError, load_layout
from processing.unmixing.templates import TemplateBuilder
from processing.unmixing.unmix import unmix_position
from sim_devices.lights import LIGHTS_DIR, TruthLight, load_truth
from sim_devices.optics import CameraOptics, LightPlane, Mirror, MirrorBallRenderer
from sim_devices.optics import trace as sim_trace
from sim_devices.sensor import mosaic_of


def test_chief_rays_agree_with_the_simulators_independent_tracer():
    rig = load_rig(REDUCED_RIG)
    geometry = RigGeometry.from_rig(rig)
    for pose in (rig.light_poses()[0], rig.light_poses()[33], rig.light_poses()[65]):
        cols, rows = ball_pixel_grid(geometry)
        ours = trace_pixels(geometry, pose, cols, rows)
        theirs = sim_trace(
            CameraOptics.from_rig(rig),
            Mirror.from_rig(rig),
            LightPlane.at(rig, pose),
            cols,
            rows,
            np.zeros_like(cols),
            np.zeros_like(cols),
        )
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
    assert template.blur_radius_px == pytest.approx(19.2, abs=0.4)  # docs/measurement.md: ~38 px across


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
    # The sources image 7-12 px apart, as docs/measurement.md says.
    centres = np.array([t.image_centre for t in estimate.templates])
    gaps = [math.dist(centres[0], c) for c in centres[1:]]
    assert 7 < min(gaps) and max(gaps) < 13


def test_the_layout_search_moves_a_poor_guess_onto_the_sources_and_adds_the_one_it_missed():
    """The candidate grid's guess, as it came out at full resolution: the outer sources
    0.2-0.75 mm too close to the middle, the middle one missing, discs too large. The
    refinement must put five sources within 30 µm of the truth, with their radius, from
    the simulator's images (written independently of the templates)."""
    rig = _crop_rig()
    truth = load_truth("five-gaussians")
    renderer = MirrorBallRenderer(rig, truth, diffraction=True, seed=4)
    data = []
    for index in (31, 33, 35):
        pose = rig.light_poses()[index]
        mosaic = mosaic_of(renderer.render(pose).rate, "RGGB")
        data.append(LayoutData(mosaic, mosaic / 1e-3 + (3.0 / 1e-3) ** 2, np.ones(mosaic.shape, bool), pose))
    builder = TemplateBuilder(RigGeometry.from_rig(rig), rig.camera.sensitivity_e_per_s)
    guess = [
        Source(f"g{k}", centre, 0.75e-3)
        for k, centre in enumerate([(-3.25e-3, -0.1e-3), (0.0, -3.78e-3), (3.78e-3, 0.0), (0.0, 3.66e-3)])
    ]
    seeds = [(u * 1.5e-3, v * 1.5e-3) for u in range(-3, 4) for v in range(-3, 4)]
    fit = refine_layout(data, builder, "RGGB", guess, seeds)
    assert fit.refined, fit.message
    assert len(fit.sources) == 5, fit.message
    distance = _distances_to_truth(fit, truth)
    assert np.all(distance < 30e-6), distance
    assert abs(fit.sources[0].radius - 0.5e-3) < 0.05e-3, fit.message
    # The fifth source explained most of what the four left: χ² fell by more than half.
    assert [n for n, _ in fit.steps] == [4, 5] and fit.steps[1][1] < 0.5 * fit.steps[0][1], fit.steps
    assert fit.chi2 / fit.pixels < 1.5, fit.message  # the templates explain the data to about its noise

    # Started from the truth, nothing is added: no seed explains 2 % of what is left.
    again = refine_layout(data, builder, "RGGB", [Source(s.name, s.centre, 0.5e-3) for s in fit.sources], seeds)
    assert len(again.sources) == 5 and [n for n, _ in again.steps] == [5]
    # Two guesses of one source meet when fitted: one goes.
    twice = refine_layout(data, builder, "RGGB", again.sources + [Source("+u again", (4.3e-3, 0.1e-3), 0.5e-3)], seeds)
    assert [n for n, _ in twice.steps] == [6, 5], twice.steps
    assert np.all(_distances_to_truth(twice, truth) < 30e-6)


@functools.lru_cache(maxsize=1)
def _reduced_rig_images():
    """The demo's reduced rig's noiseless mosaics at five of the sweep's first ten positions,
    their poses, the builder and the truth."""
    rig = load_rig(REDUCED_RIG)
    truth = load_truth("five-gaussians")
    renderer = MirrorBallRenderer(rig, truth, diffraction=True, seed=4)
    poses = [rig.light_poses()[index] for index in (1, 3, 5, 7, 9)]
    mosaics = [mosaic_of(renderer.render(pose).rate, "RGGB") for pose in poses]
    return mosaics, poses, TemplateBuilder(RigGeometry.from_rig(rig), rig.camera.sensitivity_e_per_s), truth


def _reduced_rig_positions(noise_seed: int = 1):
    """The demo's reduced rig (23.6 µm pixels: the five sources image 2-3 px apart) at five of
    the sweep's first ten positions, as a partial run has them, with seeded noise at about an
    HDR merge's variance for 10 ms (χ² per pixel near 1); the builder and the truth."""
    mosaics, poses, builder, truth = _reduced_rig_images()
    rng = np.random.default_rng(noise_seed)
    exposure = 10e-3
    data = []
    for mosaic, pose in zip(mosaics, poses, strict=True):
        variance = mosaic / exposure + (3.0 / exposure) ** 2
        noisy = mosaic + rng.normal(size=mosaic.shape) * np.sqrt(variance)
        data.append(LayoutData(noisy, variance, np.ones(mosaic.shape, bool), pose))
    return data, builder, truth


def test_the_centres_quoted_sigma_covers_their_error_over_noise_realisations():
    """Each centre found carries a 1σ (the larger of the least-squares one and the sandwich
    clustered by position). Over six noise realisations of the reduced rig, started from the
    truth: 50-85 % of the 60 coordinates lie within 1σ of it (a true 1σ holds 68 %) and at
    least 80 % within 2σ. Measured: 70 % and 90 %. The tail is one bias the sandwich cannot
    see: the +u source comes out 116 µm along u in every realisation (spread 31 µm, quoted
    1σ 41 µm), where its 2-3 px image on this coarse sensor meets the centre's."""
    z = []
    for noise_seed in range(10, 16):
        data, builder, truth = _reduced_rig_positions(noise_seed)
        start = [Source(e.name, tuple(e.centre_m), 0.5e-3) for e in truth.emitters]
        fit = refine_layout(data, builder, "RGGB", start)
        assert len(fit.sources) == 5, fit.message
        for found, emitter in zip(fit.sources, truth.emitters, strict=True):
            assert found.centre_sigma is not None and min(found.centre_sigma) > 0
            z.extend((np.array(found.centre) - np.array(emitter.centre_m)) / np.array(found.centre_sigma))
    z = np.abs(np.array(z))
    assert 0.5 <= np.mean(z < 1.0) <= 0.85, np.round(z, 2)
    assert np.mean(z < 2.0) >= 0.8, np.round(z, 2)


def _distances_to_truth(fit, truth) -> np.ndarray:
    """Each emitter's distance to the nearest source found (m)."""
    found = np.array([s.centre for s in fit.sources])
    expected = np.array([e.centre_m for e in truth.emitters])
    return np.min(np.hypot(*(found[:, None, :] - expected[None, :, :]).transpose(2, 0, 1)), axis=0)


def test_a_source_hidden_by_grown_discs_is_still_found():
    """At a quarter of the pitch four guesses widen their discs to 1.3 mm and share out the
    missed centre source's light. At that radius one more source barely lowers χ²; it needs
    the discs to shrink back. Before the candidate was screened by a short fit of every
    centre and the radius (not judged at the grown radius), the search stopped at four (the
    demo's reduced rig: 65 % errors)."""
    data, builder, truth = _reduced_rig_positions()
    guess = [Source(e.name, tuple(e.centre_m), 0.75e-3) for e in truth.emitters if e.name != "centre"]
    seeds = [(u * 1.5e-3, v * 1.5e-3) for u in range(-3, 4) for v in range(-3, 4)]
    fit = refine_layout(data, builder, "RGGB", guess, seeds)
    assert [n for n, _ in fit.steps] == [4, 5], fit.message
    assert fit.steps[1][1] < 0.98 * fit.steps[0][1]
    distance = _distances_to_truth(fit, truth)
    assert np.all(distance < 150e-6), distance  # about a tenth of a pixel: the sources image 2-3 px apart here


def test_the_search_screens_more_seeds_than_the_best_where_it_stands():
    """The demo's own case: the grid's first guess (four sources, 0.15-0.72 mm off) and the
    grid points that took light, which do not include the centre. With the discs grown, the
    seeds' χ² where they stand differ by 0.01-0.1 %: the best there, (-4.5, 0) mm, gains 1.2 %
    after its short fit, short of the 2 % asked; the second, (-1.5, 0) mm, gains 3.4 % and
    moves to the centre. Screening only the best stopped at four sources, the centre one
    3.3 mm from any."""
    data, builder, truth = _reduced_rig_positions()
    first = [(0.01, -3.848), (3.555, -0.015), (-3.279, -0.003), (-0.048, 3.791)]  # mm, as the demo's grid gave them
    guess = [Source(f"guess-{k}", (u * 1e-3, v * 1e-3), 0.75e-3) for k, (u, v) in enumerate(first)]
    lit = [
        (0.0, -4.5),
        (3.0, 0.0),
        (-3.0, 0.0),
        (0.0, -3.0),
        (4.5, 0.0),
        (-4.5, 0.0),
        (-1.5, 0.0),
        (0.0, 1.5),
        (0.0, 4.5),
        (0.0, 3.0),
        (-4.5, -1.5),
    ]
    seeds = [(u * 1e-3, v * 1e-3) for u, v in lit]
    only_best = refine_layout(data, builder, "RGGB", guess, seeds, screen_seeds=1)
    assert len(only_best.sources) == 4 and _distances_to_truth(only_best, truth)[0] > 3e-3, only_best.message
    fit = refine_layout(data, builder, "RGGB", guess, seeds)
    assert [n for n, _ in fit.steps] == [4, 5] and fit.steps[1][1] < 0.98 * fit.steps[0][1], fit.steps
    distance = _distances_to_truth(fit, truth)
    assert np.all(distance < 150e-6), distance


def test_the_layout_search_says_when_it_cannot_refine():
    rig = _crop_rig()
    builder = TemplateBuilder(RigGeometry.from_rig(rig), rig.camera.sensitivity_e_per_s)
    nothing = refine_layout([], builder, "RGGB", [])
    assert not nothing.refined and nothing.message == "no first guess to refine" and nothing.sources == []
    guess = [Source("far", (0.5, 0.5), 0.5e-3)]  # half a metre off the axis: the ball never shows it
    dark = np.zeros((rig.camera.height, rig.camera.width))
    fit = refine_layout(
        [LayoutData(dark, dark + 1.0, np.ones(dark.shape, bool), rig.light_poses()[33])], builder, "RGGB", guess
    )
    assert not fit.refined and fit.sources == guess
    assert fit.message == "no position has a window where every template is whole"


def test_the_estimator_follows_the_footprint():
    layout = load_layout(LIGHTS_DIR / "five-gaussians.toml")
    pinhole = load_rig()
    builder = TemplateBuilder(RigGeometry.from_rig(pinhole), 1.0)
    chosen, reason, footprint = choose_estimator(
        RigGeometry.from_rig(pinhole), builder, layout, pinhole.light_poses()[33], "auto"
    )
    assert chosen == "templates" and "unmixing" in reason
    assert 12 <= 2e3 * footprint <= 23  # docs/measurement.md: a pixel gathers rays from 12-23 mm
    lens = rig_with(camera__thin_lens={"focus_distance_m": 0.186, "f_number": 8.0})
    chosen, reason, footprint = choose_estimator(
        RigGeometry.from_rig(lens),
        TemplateBuilder(RigGeometry.from_rig(lens), 1.0),
        layout,
        lens.light_poses()[33],
        "auto",
    )
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
    bad.write_text('[[sources]]\nname = "a"\ncentre_m = [1e300, 0.0]\n')  # finite, but squares to inf
    with pytest.raises(
        SourcesError, match=r"bad\.toml: sources\[0\]\.centre_m: 1e\+300 m is beyond the ±1000 m allowed$"
    ):
        load_layout(bad)
    assert [s.name for s in load_layout(LIGHTS_DIR / "five-gaussians.toml")] == ["centre", "+u", "-u", "+v", "-v"]


def test_the_aperture_fit_finds_the_pinhole_the_data_were_taken_through():
    """`fit_aperture` at the true layout, on the reduced rig's five noisy positions: from the
    rig's own description and from one 10 % too narrow, the simulated camera's 0.2 mm comes back
    within 1 %, with χ² no higher than at the described diameter. Bounds that leave the truth
    outside give a clear failure, not a diameter at the bound."""
    from dataclasses import replace

    from processing.unmixing.camera_fit import fit_aperture

    data, builder, truth = _reduced_rig_positions()
    layout = [Source(e.name, tuple(e.centre_m), e.radius_m) for e in truth.emitters]
    true_diameter = 2 * builder.geometry.aperture_radius
    narrow = replace(builder, geometry=replace(builder.geometry, aperture_radius=0.45 * true_diameter))
    for described in (builder, narrow):
        fit = fit_aperture(data, described, "RGGB", layout)
        assert fit.described_m == pytest.approx(2 * described.geometry.aperture_radius)
        assert fit.diameter_m == pytest.approx(true_diameter, rel=0.01), fit
        assert fit.chi2 <= fit.chi2_described and fit.pixels > 1000 and 5 <= fit.evaluations <= 30
    with pytest.raises(SourcesError, match="the best aperture lies at the search's bound"):
        fit_aperture(data, builder, "RGGB", layout, bounds=(1.05, 1.25))
    with pytest.raises(SourcesError, match="no sources"):
        fit_aperture(data, builder, "RGGB", [])


def test_the_sensor_distance_fit_finds_the_distance_the_data_were_taken_at():
    """`fit_sensor_distance` on the reduced rig's five noisy positions, the rig described 0.5 %
    long: with the sources held at the truth's places, and with them refitted at each trial
    from places 100 µm off (as a search leaves them), the simulated camera's distance comes back
    within 0.1 % (measured: 0.99983 and 1.00034 of it, 9 evaluations each), χ² no higher than as
    described. A search whose bounds leave the truth outside fails clearly."""
    from dataclasses import replace

    from processing.unmixing.camera_fit import fit_sensor_distance

    data, builder, truth = _reduced_rig_positions()
    true_distance = builder.geometry.sensor_distance
    long = replace(builder, geometry=builder.geometry.with_sensor_distance(1.005 * true_distance))
    layout = [Source(e.name, tuple(e.centre_m), e.radius_m) for e in truth.emitters]
    shifted = [Source(s.name, (s.centre[0] + 1e-4, s.centre[1]), s.radius) for s in layout]
    for sources, refit in ((layout, False), (shifted, True)):
        fit = fit_sensor_distance(data, long, "RGGB", sources, refit=refit)
        assert fit.described_m == pytest.approx(1.005 * true_distance) and fit.sources_refitted == refit
        assert fit.sensor_distance_m == pytest.approx(true_distance, rel=1e-3), (
            refit,
            fit.sensor_distance_m / true_distance,
        )
        assert fit.chi2 <= fit.chi2_described and fit.pixels > 1000 and 5 <= fit.evaluations <= 30
    with pytest.raises(SourcesError, match="the best sensor distance lies at the search's bound"):
        fit_sensor_distance(data, long, "RGGB", layout, refit=False, bounds=(1.0, 1.02))
    with pytest.raises(SourcesError, match="no sources"):
        fit_sensor_distance(data, long, "RGGB", [])
