"""The point spread refined from the sweep (processing.unmixing.point_spread_fit) against the
simulator's Fresnel camera, whose pinhole has a rough edge or none (written apart from the
processing's templates)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_render import rig_with

from processing import ProcessingError
from processing.light_run.plan import plan_processing
from processing.options import ProcessingOptions
from processing.trace import RigGeometry
from processing.unmixing.fresnel import FresnelPupil
from processing.unmixing.point_spread_fit import refine_point_spread
from processing.unmixing.problem import LayoutData, LayoutProblem
from processing.unmixing.sources import Source
from processing.unmixing.templates import TemplateBuilder
from sim_devices.lights import LIGHTS_DIR, load_truth
from sim_devices.optics import MirrorBallRenderer
from sim_devices.sensor import mosaic_of


def _crop_sweep(roughness_m: float):
    """Seven positions of the middle of the sweep on a 320 px crop of the demo camera (5.9 µm
    pixels, Fresnel), its pinhole's edge ``roughness_m`` RMS over 5 µm, with seeded noise at
    about a 10 ms merge's: (training positions, held-out positions, builder, truth sources)."""
    rig = rig_with(
        camera__point_spread="fresnel",
        camera__width=320,
        camera__height=320,
        camera__principal_point_px=[999.5 - 840, 655.5 - 400],
        camera__aperture__edge_roughness_rms_m=roughness_m,
        light__housing_radius_m=0.012,
    )
    truth = load_truth("five-gaussians")
    renderer = MirrorBallRenderer(rig, truth, diffraction=True, seed=4)
    rng = np.random.default_rng(1)
    data = []
    for index in range(30, 37):
        pose = rig.light_poses()[index]
        mosaic = mosaic_of(renderer.render(pose).rate, "RGGB")
        variance = mosaic / 10e-3 + (3.0 / 10e-3) ** 2
        noisy = mosaic + rng.normal(size=mosaic.shape) * np.sqrt(variance)
        data.append(LayoutData(noisy, variance, np.ones(mosaic.shape, bool), pose))
    pupil = FresnelPupil.from_camera(rig.camera)
    builder = TemplateBuilder(RigGeometry.from_rig(rig), rig.camera.sensitivity_e_per_s, pupil=pupil)
    sources = [Source(e.name, tuple(e.centre_m), e.radius_m) for e in truth.emitters]
    return data[1::2], data[0::2], builder, sources


def _chi2_per_pixel(data, builder, sources) -> float:
    problem = LayoutProblem(data, builder, "RGGB", sources, 48, 8)
    return problem.chi2(np.array([s.centre for s in sources]), sources[0].radius) / problem.pixels


def test_a_rough_edges_halo_is_taken_from_the_sweep_and_a_smooth_hole_is_left_alone():
    """A rough edge (2 µm RMS): the smooth circle's templates leave χ²/pixel 7.8 on the positions
    the estimate does not see; the templates built with the correction 1.13 (measured), where a
    smooth hole's are 1.18. A smooth hole: not refined at all (χ²/pixel 1.18 is under 1.5)."""
    train, held, builder, sources = _crop_sweep(2e-6)
    refinement = refine_point_spread(train, held, builder, "RGGB", sources)
    assert refinement.needed and refinement.correction is not None, refinement.message
    assert refinement.held_out_before > 5.0 and refinement.held_out_after < 1.3, refinement.record()
    # The builder with the correction (what the estimate of every position uses) gives what was judged.
    corrected = _chi2_per_pixel(held, replace(builder, correction=refinement.correction), sources)
    assert corrected == pytest.approx(refinement.held_out_after, rel=0.02)
    assert "kept" in refinement.record()["message"] and refinement.record()["refined"] is True

    train, held, builder, sources = _crop_sweep(0.0)
    smooth = refine_point_spread(train, held, builder, "RGGB", sources)
    assert not smooth.needed and smooth.correction is None, smooth.message
    assert smooth.chi2_per_pixel_before < 1.3 and smooth.message.startswith("not needed")


def test_the_plan_refines_the_point_spread_where_the_sources_are_searched_for(tmp_path):
    """auto: where the sources are searched for; a given layout is not refined (and its run is
    merged and estimated in one pass), unless asked always; never with a measured point spread."""
    layout = LIGHTS_DIR / "five-gaussians.toml"
    assert plan_processing(ProcessingOptions.checked(steps="hdr,sources")).point_spread == "needed"
    given = plan_processing(ProcessingOptions.checked(steps="hdr,sources", layout=layout, calibrate_rig="never"))
    assert given.point_spread == "never" and given.fused
    asked = ProcessingOptions.checked(
        steps="hdr,sources", layout=layout, calibrate_rig="never", refine_point_spread="always"
    )
    assert plan_processing(asked).point_spread == "always" and not plan_processing(asked).fused
    auto = ProcessingOptions.checked(steps="hdr,sources")
    assert plan_processing(auto, point_spread_measured=True).point_spread == "never"
    always = ProcessingOptions.checked(steps="hdr,sources", refine_point_spread="always")
    with pytest.raises(ProcessingError, match="--refine-point-spread always: the rig's camera has a measured"):
        plan_processing(always, point_spread_measured=True)


def test_the_reports_quality_line_says_what_the_refinement_changed():
    """Where the sweep asked for the point spread to be refined, the report's first words say so."""
    from processing.fit import IntensityFit
    from processing.lightmodel import LightModel, SourceModel
    from processing.report.trust import quality_banner

    fit = IntensityFit(
        "gaussian", {"a": 2.0, "sigma": 0.5}, {"a": 0.002, "sigma": 0.001}, np.diag([4e-6, 1e-6]),
        np.zeros(9), 1.0, 9, (0.0, 0.6), (0.0, 0.0),
    )  # fmt: skip
    quality = {"status": "ok", "model_error": 0.015, "model_error_allowance": 0.03, "chi2_per_pixel": 2.25}
    quality |= {"positions": 66, "unexplained_positions": []}
    refined = "kept: the held-out positions' χ²/pixel 6.61 → 1.12 (+83 %)"
    model = LightModel([SourceModel("s", (0.0, 0.0), 0.0005, fit)], quality=quality | {"point_spread_refined": refined})
    assert "the point spread refined from the sweep, kept: the held-out positions" in quality_banner(model)
    assert "refined" not in quality_banner(LightModel([SourceModel("s", (0.0, 0.0), 0.0005, fit)], quality=quality))
