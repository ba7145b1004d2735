"""The object chain end to end: daemon run engine → simulated object → reflectance.

The light model is the simulated truth itself (fitted to noise-free samples of each
emitter), so this checks that the simulator's object rendering (written from
docs/measurement.md alone) and the processing's estimator (likewise) agree, through a real run
file, DNG decoding and the HDR merge. The light run's own accuracy is the business of
``bench accuracy``; the whole chain with a measured light is ``bench reflectance``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import TRUTH, truth_light_model

from acquisition.benchmarks.accuracy import acquire_simulated
from acquisition.benchmarks.reflectance import OBJECT_RIGS, score
from drivers.contracts.rig import load_rig, rig_from_dict, rig_to_toml_dict
from drivers.contracts.runfile import RunFile, file_sha256
from processing.reflectance.codes import ReflectanceError
from processing.reflectance.run import reflectance_from_run
from sim_devices.lights import load_truth
from sim_devices.objects import surface_truth_at


def reduced(name: str, **changes):
    data = rig_to_toml_dict(load_rig(OBJECT_RIGS / f"{name}.toml"))
    data["camera"].update(width=500, height=328, pixel_pitch_m=23.6e-6)
    for key, value in changes.items():
        data[key] = {**data.get(key, {}), **value}
    return rig_from_dict(data, f"{name} (reduced)")


@pytest.fixture(scope="module")
def vase_run(tmp_path_factory):
    base = tmp_path_factory.mktemp("vase")
    rig = reduced("object-vase")
    light = truth_light_model(load_rig(None)).save(base / "truth.light.json")
    run = acquire_simulated(
        rig, TRUTH, True, (1.0, 4.0, 16.0), None, base, preset="object-arc", light_results=str(light)
    )
    return rig, run, light, base


def test_the_run_file_names_its_object_and_light(vase_run):
    rig, run, light, _ = vase_run
    with RunFile.open(run) as f:
        refs = f.header.references
        assert f.header.preset == "object-arc" and f.n_positions == 5
    assert refs["light_model"]["sha256"] == file_sha256(light) and refs["light_model"]["run_id"] == "truth"
    assert refs["object_mesh"]["sha256"] == file_sha256(rig.object.mesh)


def test_measured_light_recovers_the_albedo_and_the_others_do_not(vase_run):
    rig, run, light, base = vase_run
    result = reflectance_from_run(run, light, None, base / "out")
    valid = np.all(np.isfinite(result.rho_points["measured"]), axis=1)
    assert valid.sum() > 5000
    truth, uniform = surface_truth_at(rig, result.points[valid], faces=result.faces[valid])
    scores = {m: score(result.rho_points[m][valid], truth, uniform) for m in result.methods}
    # Photon noise at these exposures is ~0.5 % per superpixel; the light is exact here.
    assert scores["measured"]["median_abs_rel_error"] < 0.01, scores
    # Superpixels 4× larger than the default straddle facets more often (flat normals).
    assert scores["measured"]["uniform_cv"] < 0.03, scores
    assert abs(scores["measured"]["median_rel_bias"]) < 0.005
    # One direction and one irradiance for a 5 cm object at 30 cm: ±8 % in 1/d² alone.
    assert scores["collimated"]["median_abs_rel_error"] > 3 * scores["measured"]["median_abs_rel_error"]
    assert scores["collimated"]["uniform_cv"] > 0.05
    for name in ("albedo-measured.exr", "albedo-collimated.png", "profiles.png", "report.html"):
        assert (base / "out" / name).is_file(), name


def test_light_from_a_rig_with_another_light_frame_is_refused(vase_run, tmp_path):
    rig, run, _, _ = vase_run
    other = rig_to_toml_dict(load_rig(None))
    other["light"]["light_to_tool"]["position_m"] = [0.0, 0.0, 0.01]
    foreign = truth_light_model(rig_from_dict(other)).save(tmp_path / "foreign.light.json")
    with pytest.raises(ReflectanceError) as info:
        reflectance_from_run(run, foreign, None, tmp_path / "out")
    message = str(info.value)
    assert "\n" not in message and "light_to_tool" in message


def test_a_mesh_outside_the_view_is_refused(vase_run, tmp_path):
    import trimesh

    _, run, light, _ = vase_run
    far = trimesh.creation.box(extents=(0.01, 0.01, 0.01))
    far.apply_translation((0.5, 0.5, 0.0))
    far.export(tmp_path / "far.stl")
    with pytest.raises(ReflectanceError) as info:
        reflectance_from_run(run, light, tmp_path / "far.stl", tmp_path / "out")
    assert "far.stl" in str(info.value) and "\n" not in str(info.value)


def test_truth_light_model_is_the_truth():
    rig = load_rig(None)
    model = truth_light_model(rig)
    for k, emitter in enumerate(load_truth(TRUTH).emitters):
        for theta in (0.0, 0.1, 0.5):
            assert model.sources[k].fit(theta) == pytest.approx(
                float(emitter.intensity_w_sr(np.array([theta]))[0]), rel=1e-3
            )
    assert math.isclose(model.sources[0].centre_m[0], 0.0)
