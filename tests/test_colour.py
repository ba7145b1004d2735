"""Colour: the camera's colour matrices from the raw file to the run file, camera RGB to XYZ,
chromaticity, CCT and Duv against colour-science's reference values, and the light files'
colour fields."""

from __future__ import annotations

import json
import math
import struct
from dataclasses import replace

import colour
import h5py
import numpy as np
import pytest
from conftest import REDUCED_RIG
from scipy.integrate import trapezoid

from drivers.camera import RawFrame
from drivers.contracts.camera_colour import CameraColourError, checked_camera_colour
from drivers.contracts.rig import Camera, load_rig
from drivers.contracts.runfile import PositionTimes, RunFile, RunFileWriter, RunHeader
from drivers.raw_decode import decode_raw
from processing.colour import camera_to_xyz, chromaticity, colour_section, over_theta
from processing.exports import read_tm25, write_ies, write_ldt, write_tm25
from processing.fit import Samples, fit_intensity
from processing.light_run.light_fit import light_chromaticity
from processing.lightmodel import LightModel, SourceModel
from processing.report.colour import colour_section as report_colour_section
from sim_devices.colour import WAVELENGTHS_NM, camera_rgb, colour_matrices, planck, spectrum_xyz
from sim_devices.dng import write_dng
from sim_devices.lights import Emitter, TruthError, TruthLight, load_truth

OBSERVER = "CIE 1931 2 Degree Standard Observer"
SHAPE = colour.SpectralShape(360, 830, 1)


def illuminant_xyz(name: str) -> np.ndarray:
    """colour-science's XYZ of a CIE illuminant (Y = 1), from its spectrum."""
    sd = colour.SDS_ILLUMINANTS[name].copy().align(SHAPE)
    xyz = colour.sd_to_XYZ(sd, colour.MSDS_CMFS[OBSERVER])
    return xyz / xyz[1]


@pytest.mark.parametrize(("name", "cct_k"), [("A", 2856.0), ("D65", 6504.0), ("D50", 5003.0)])
def test_cct_of_the_cie_illuminants_is_their_reference_value(name, cct_k):
    got = chromaticity(illuminant_xyz(name))
    # colour-science's own chromaticity of the illuminant (its reference table), and the CCT the CIE gives.
    x, y = colour.CCS_ILLUMINANTS[OBSERVER][name]
    assert got["x"] == pytest.approx(x, abs=2e-4) and got["y"] == pytest.approx(y, abs=2e-4)
    assert got["cct_k"] == pytest.approx(cct_k, abs=min(20.0, 0.005 * cct_k))
    u, v = colour.xy_to_Luv_uv([got["x"], got["y"]])
    assert (got["u_prime"], got["v_prime"]) == pytest.approx((u, v), abs=1e-12)
    if name == "A":  # a blackbody: on the Planckian locus
        assert abs(got["duv"]) < 2e-4


def test_a_light_far_from_white_has_no_cct():
    got = chromaticity(colour.xy_to_XYZ([0.15, 0.06]))  # a saturated blue
    assert got["cct_k"] is None and abs(got["duv"]) > 0.05
    assert chromaticity([0.0, 0.0, 0.0])["x"] is None


def test_the_simulated_cameras_matrices_map_its_rgb_back_to_the_spectrums_xyz():
    """The simulated camera's DNG matrices (fitted to its Gaussian bands against the CIE 1931
    observer) take the camera RGB of a light back to the light's own XYZ: exactly for its two
    calibration illuminants; for blackbodies between them within 0.0015 in xy (a just
    noticeable difference is about 0.003) and 1.5 % in CCT (Gaussian bands are not a linear
    mix of the observer's functions, so no 3×3 matrix is exact for every spectrum)."""
    camera = Camera()
    matrices = colour_matrices(camera)
    assert matrices["calibration_illuminant_1"] == 17 and matrices["calibration_illuminant_2"] == 21
    assert not np.allclose(matrices["color_matrix_2"], np.eye(3), atol=0.1)  # not an identity
    for name in ("A", "D65"):
        spd = colour.SDS_ILLUMINANTS[name].copy().align(SHAPE).values
        got = camera_to_xyz(camera_rgb(spd, camera), matrices)
        np.testing.assert_allclose(got, illuminant_xyz(name), atol=1e-4, err_msg=name)
    # The neutral is the camera's RGB of D65, largest channel 1.
    d65 = camera_rgb(colour.SDS_ILLUMINANTS["D65"].copy().align(SHAPE).values, camera)
    np.testing.assert_allclose(matrices["as_shot_neutral"], d65 / d65.max(), rtol=1e-12)
    worst = 0.0
    for cct_k in (2700.0, 3000.0, 3500.0, 4000.0, 5000.0, 6500.0):
        true = spectrum_xyz(planck(cct_k))
        got = camera_to_xyz(camera_rgb(planck(cct_k), camera), matrices)
        xy_true, xy_got = true[:2] / true.sum(), got[:2] / got.sum()
        worst = max(worst, float(np.hypot(*(xy_got - xy_true))))
        assert chromaticity(got)["cct_k"] == pytest.approx(cct_k, rel=0.015)  # measured: 1.2 % at 6500 K
    assert worst < 0.0015  # measured: 0.0014 at 6500 K, 0.0007 at 4000 K, 0.0001 at 3000 K
    assert WAVELENGTHS_NM[0] == 360 and WAVELENGTHS_NM[-1] == 830


def test_the_dng_carries_the_matrices_and_the_decode_reads_them(tmp_path):
    matrices = colour_matrices(Camera())
    mosaic = np.full((24, 30), 200, np.uint16)
    frame = decode_raw(write_dng(tmp_path / "a.dng", mosaic, exposure_s=0.01, colour=matrices))
    got = frame.extra["colour"]
    assert got["source"] == "DNG tags"
    for key in ("color_matrix_1", "color_matrix_2", "as_shot_neutral"):
        np.testing.assert_allclose(got[key], matrices[key], atol=5e-5, err_msg=key)  # rationals over 10 000
    assert (got["calibration_illuminant_1"], got["calibration_illuminant_2"]) == (17, 21)
    plain = decode_raw(write_dng(tmp_path / "b.dng", mosaic, exposure_s=0.01))  # without: the identity
    assert plain.extra["colour"]["color_matrix_1"] == np.eye(3).tolist()


@pytest.mark.parametrize(
    ("description", "message"),
    [
        ({"color_matrix_2": np.eye(3).tolist()}, "color_matrix_1: missing"),
        ({"color_matrix_1": [[1, 0], [0, 1]]}, "color_matrix_1: must be a 3x3 matrix"),
        ({"color_matrix_1": np.zeros((3, 3)).tolist()}, "color_matrix_1: singular"),
        ({"color_matrix_1": np.eye(3).tolist(), "calibration_illuminant_1": 99}, "calibration_illuminant_1: 99"),
        ({"color_matrix_1": np.eye(3).tolist(), "as_shot_neutral": [1, 0, 1]}, "as_shot_neutral"),
        ([1, 2], "must be an object"),
    ],
)
def test_a_bad_colour_description_is_one_line_naming_the_field(description, message):
    with pytest.raises(CameraColourError, match=message) as caught:
        checked_camera_colour(description, "x.h5")
    assert "\n" not in str(caught.value) and str(caught.value).startswith("x.h5")


def _header(rig, run_id="run-colour"):
    return RunHeader(
        run_id=run_id,
        rig=rig,
        tool_poses=rig.tool_poses()[:2],
        light_poses=rig.light_poses()[:2],
        max_exposures=1,
        frame_shape=(24, 30),
        bracket={"mode": "fixed", "exposures_s": [0.01]},
        metadata={},
        devices={},
        software_version="test",
        created_utc="2026-11-26T00:00:00+00:00",
    )


def _frame(extra):
    mosaic = np.full((24, 30), 100, np.uint16)
    return RawFrame(mosaic, np.zeros((2, 2)), 4095, "RGGB", 0.01, 0.0, "cam", extra=extra)


def test_the_run_file_keeps_the_first_frames_matrices_and_an_older_file_reads_without(tmp_path):
    rig = load_rig(REDUCED_RIG)
    matrices = checked_camera_colour(colour_matrices(rig.camera))
    path = tmp_path / "run.h5"
    pose = rig.tool_poses()[0]
    with RunFileWriter.create(path, _header(rig)) as writer:
        writer.write_position(0, pose, PositionTimes(0, 0, 0), [_frame({})])  # a frame without: nothing yet
        with RunFile.open(path) as run:
            assert run.header.camera_colour == {}
        writer.write_position(1, pose, PositionTimes(0, 0, 0), [_frame({"colour": matrices})])
        writer.set_status("complete")
    with RunFile.open(path) as run:
        assert run.header.camera_colour == matrices
    with h5py.File(path, "a") as f:  # as a file written before the run file kept the matrices
        del f["header/camera_colour_json"]
    with RunFile.open(path) as run:
        assert run.header.camera_colour == {}
    with h5py.File(path, "a") as f:
        f["header"].create_dataset("camera_colour_json", data=np.bytes_(json.dumps({"color_matrix_1": [1]})))
    with pytest.raises(ValueError, match=r"run.h5: /header/camera_colour_json: color_matrix_1"):
        RunFile.open(path)


def test_without_matrices_the_colour_is_camera_rgb_and_says_so():
    section = colour_section([1.2, 1.0, 0.8], {})
    assert section["basis"].startswith("camera RGB only")
    assert "x" not in section and "cct_k" not in section
    assert section["camera_rgb"] == pytest.approx([1.2, 1.0, 0.8])


def test_colour_over_theta_bins_the_samples_and_says_whether_it_varies():
    camera = Camera()
    matrices = colour_matrices(camera)
    theta = np.radians([1.0, 2.0, 12.0, 13.0, 31.0])
    warm, cool = camera_rgb(planck(3000.0), camera), camera_rgb(planck(4000.0), camera)
    rgb = np.array([warm, warm, warm, warm, cool]) * np.array([[2.0], [1.0], [1.0], [1.0], [0.5]])
    got = over_theta(theta, rgb, matrices)
    assert got["samples"] == [2, 2, 1]
    assert got["theta_deg"][0] == pytest.approx((1.0 * 2 + 2.0 * 1) / 3)  # weighted by the signal
    assert got["cct_k"][0] == pytest.approx(3000.0, rel=0.005) and got["cct_k"][2] == pytest.approx(4000.0, rel=0.005)
    assert got["varies"] is True
    same = over_theta(theta, np.array([warm] * 5), matrices)
    assert same["varies"] is False and same["max_delta_uv"] < 1e-9


def _model_with_colour(matrices, far=(2700.0, 5000.0), sigmas=(0.4, 0.4)):
    """Two sources of 2700 and 5000 K seen at 0° and 10°; at 10° of the colour ``far`` gives; lobes
    of ``sigmas`` (radians)."""
    camera = Camera()
    sources = []
    for k, (cct_k, far_k) in enumerate(zip((2700.0, 5000.0), far, strict=True)):
        theta = np.linspace(0.0, 0.8, 20)
        values = np.exp(-(theta**2) / (2 * sigmas[k] ** 2))
        fit = fit_intensity(Samples(theta, np.zeros(20), values, np.full(20, 1e-3), f"s{k}"), "gaussian")
        rgb = camera_rgb(planck(cct_k), camera)
        chroma = colour_section(rgb, matrices)
        rgb_far = camera_rgb(planck(far_k), camera)
        chroma["over_theta"] = over_theta(np.radians([0.0, 10.0]), np.array([rgb, rgb_far]), matrices)
        sources.append(SourceModel(f"s{k}", (0.004 * k, 0.0), 5e-4, fit, {}, tuple(rgb), chroma))
    return LightModel(sources, provenance={"run_id": "run-colour"}, chromaticity=light_chromaticity(sources, matrices))


def test_the_light_model_file_and_the_light_files_carry_the_colour(tmp_path):
    model = _model_with_colour(colour_matrices(Camera()))
    back = LightModel.load(model.save(tmp_path / "light.json"))
    assert back.chromaticity == model.chromaticity and back.sources[1].chromaticity == model.sources[1].chromaticity
    assert back.sources[0].chromaticity["cct_k"] == pytest.approx(2700.0, rel=0.005)
    cct = model.chromaticity["cct_k"]
    assert 2700.0 < cct < 5000.0
    ies = write_ies(model, tmp_path / "light.ies").read_text()
    assert f"[_CCT] {cct:.0f}\n" in ies and "[_DUV] " in ies and "[_CRI] not measured" in ies
    assert f"CCT {cct:.0f} K" in ies.split("[_CHROMATICITY]")[1].splitlines()[0]
    ldt = write_ldt(model, tmp_path / "light.ldt").read_bytes().decode("ascii").split("\r\n")
    assert ldt[29:31] == [f"{cct:.0f}K", "n/a"]  # lines 26d and 26e: colour appearance, colour rendering
    header, _ = read_tm25(write_tm25(model, tmp_path / "light.tm25ray", 200, seed=1))
    info = header["texts"]["additional_info"]
    assert f"Colour of the whole light: x {model.chromaticity['x']:.4f}" in info and "s1: x" in info
    assert header["spectrum_type"] == 0  # no spectrum: a three-channel camera measures none
    html = report_colour_section(model)
    assert "whole light" in html and f"{cct:.0f} K" in html and "no plot over θ" in html


def test_the_report_plots_the_colour_over_theta_where_it_varies():
    model = _model_with_colour(colour_matrices(Camera()), far=(3000.0, 5000.0))
    html = report_colour_section(model)
    assert "<img " in html and "Varying by more than 0.002 in u′v′: s0, the whole light." in html


def test_a_model_without_matrices_writes_no_cct():
    model = _model_with_colour({})
    assert "cct_k" not in model.chromaticity
    assert "camera RGB only" in report_colour_section(model)


def test_a_truth_emitter_of_a_colour_temperature_is_seen_through_the_cameras_channels():
    camera = Camera()
    light = load_truth("cct-five-gaussians")
    seen = light.seen_by(camera)
    for emitter, shown in zip(light.emitters, seen.emitters, strict=True):
        rgb = camera_rgb(planck(emitter.cct_k), camera)
        np.testing.assert_allclose(shown.spectrum, rgb / rgb.mean(), rtol=1e-12)
    assert seen.emitters[0].spectrum[0] > seen.emitters[0].spectrum[2]  # 2700 K: warm
    assert load_truth("five-gaussians").seen_by(camera) == load_truth("five-gaussians")
    with pytest.raises(ValueError, match="not both"):
        Emitter(spectrum=(1.0, 1.0, 1.0), cct_k=3000.0)
    with pytest.raises(ValueError, match="cct_k"):
        TruthLight(emitters=[Emitter(cct_k=100.0)])
    assert issubclass(TruthError, ValueError) and math.isfinite(seen.emitters[0].spectrum[1])


def _read_tm25_independently(path):
    """The TM-25-13 file read from its bytes without processing.exports: the flags (4.7.2), the
    fluxes and spectrum type (4.7.1), and the rays, whose columns follow the flags in the order
    x y z kx ky kz phi lambda Tri_Y S1..PolEllipseZ Tri_X Tri_Z spectrumIdx (TM-25-13 4.7.6)."""
    data = path.read_bytes()
    assert data[:4] == b"TM25" and struct.unpack_from("<i", data, 4)[0] == 2013
    luminous, radiant = struct.unpack_from("<ff", data, 12)
    (n_rays,) = struct.unpack_from("<Q", data, 20)
    (spectrum_type,) = struct.unpack_from("<i", data, 60)
    n_spectra, n_additional, text_bytes = struct.unpack_from("<3i", data, 76)
    flags = struct.unpack_from("<8i", data, 256)
    assert (n_spectra, n_additional, text_bytes) == (0, 0, 0)
    names = [["x", "y", "z", "kx", "ky", "kz"], ["phi"], ["lambda"], ["Tri_Y"], ["S1", "S2", "S3", "Px", "Py", "Pz"]]
    names += [["Tri_X", "Tri_Z"], ["spectrumIdx"]]
    columns = names[0] + [c for flag, group in zip(flags[2:], names[1:], strict=True) if flag for c in group]
    rays = np.frombuffer(data, "<f4", offset=36288).reshape(n_rays, len(columns))
    return {"luminous": luminous, "radiant": radiant, "spectrum_type": spectrum_type, "flags": flags}, {
        c: rays[:, k].astype(np.float64) for k, c in enumerate(columns)
    }


def test_the_tm25_rays_carry_their_sources_colour(tmp_path):
    """Each ray carries its source's CIE XYZ at its luminous flux (its flux weighed by the source's
    luminance per unit of intensity); the rays' sum is the whole light's colour (mixed in camera
    RGB through one matrix, the rays' sources each through its own: within 1e-3 in xy)."""
    model = _model_with_colour(colour_matrices(Camera()))
    path = write_tm25(model, tmp_path / "light.tm25ray", 20_000, seed=2)
    head, rays = _read_tm25_independently(path)
    assert head["flags"] == (1, 1, 1, 0, 1, 0, 1, 0) and head["spectrum_type"] == 0
    assert math.isnan(head["luminous"])  # relative: no lumens given
    assert rays["Tri_Y"].sum() == pytest.approx(rays["phi"].sum(), rel=1e-5)  # relative: the light's flux
    header, same = read_tm25(path)
    assert header["columns"] == ["x", "y", "z", "kx", "ky", "kz", "phi", "Tri_Y", "Tri_X", "Tri_Z"]
    assert "Tri_Y in relative units" in header["texts"]["additional_info"]
    np.testing.assert_array_equal(same[:, 8], rays["Tri_X"])
    which = np.round(rays["x"] / 4.0).astype(int)  # the sources sit at x = 0 and 4 mm
    luminance = [s.chromaticity["relative_luminance"] for s in model.sources]
    assert sum(s.flux() * w for s, w in zip(model.sources, luminance, strict=True)) == pytest.approx(model.total_flux())
    assert luminance[0] != pytest.approx(1.0, abs=0.01)  # a warm and a cool source of equal intensity
    for k, source in enumerate(model.sources):
        xyz = np.array(source.chromaticity["XYZ"])
        mine = which == k
        assert mine.sum() > 5000
        np.testing.assert_allclose(rays["Tri_X"][mine] / rays["Tri_Y"][mine], xyz[0] / xyz[1], rtol=1e-6)
        np.testing.assert_allclose(rays["Tri_Z"][mine] / rays["Tri_Y"][mine], xyz[2] / xyz[1], rtol=1e-6)
        np.testing.assert_allclose(rays["Tri_Y"][mine] / rays["phi"][mine], luminance[k], rtol=1e-6)
    total = np.array([rays["Tri_X"].sum(), rays["Tri_Y"].sum(), rays["Tri_Z"].sum()])
    x, y = total[:2] / total.sum()
    assert (x, y) == pytest.approx((model.chromaticity["x"], model.chromaticity["y"]), abs=1e-3)  # measured 8e-4

    lumens = write_tm25(model, tmp_path / "lm.tm25ray", 2000, seed=2, lamp_lumens=800.0)
    head, rays = _read_tm25_independently(lumens)
    assert head["luminous"] == pytest.approx(800.0, rel=1e-6) and rays["Tri_Y"].sum() == pytest.approx(800.0, rel=1e-5)
    calibrated = write_tm25(model, tmp_path / "cd.tm25ray", 2000, seed=2, calibration=50.0)
    head, rays = _read_tm25_independently(calibrated)
    assert head["luminous"] == pytest.approx(50.0 * model.total_flux(), rel=1e-5)
    assert "Tri_Y in lm" in read_tm25(calibrated)[0]["texts"]["additional_info"]
    grey = LightModel([replace(s, chromaticity={}) for s in model.sources], provenance=model.provenance)
    head, rays = _read_tm25_independently(write_tm25(grey, tmp_path / "grey.tm25ray", 2000, seed=2))
    assert head["flags"] == (1, 1, 1, 0, 0, 0, 0, 0) and "Tri_Y" not in rays


def test_the_whole_lights_colour_over_theta_weighs_the_sources_by_their_flux(tmp_path):
    """A narrow warm lobe and a wide cool one, each of one colour: the light cools with θ. Each
    bin's colour is the sources' camera RGB weighed by their flux in the bin (checked against the
    trapezoid rule), and the TM-25 rays leaving in that band carry the same colour."""
    matrices = colour_matrices(Camera())
    model = _model_with_colour(matrices, sigmas=(0.2, 0.6))
    over = model.chromaticity["over_theta"]
    assert over["varies"] is True and over["bin_deg"] == 5.0 and over["theta_max_deg"] == pytest.approx(45.8, abs=0.1)
    assert len(over["cct_k"]) == 10 and np.all(np.diff(over["cct_k"]) > 0)  # cooler outwards
    assert over["cct_k"][0] < 3600.0 and over["cct_k"][-1] > 4700.0
    k = 4  # 20°-25°
    t = np.radians(np.linspace(20.0, 25.0, 2001))
    flux = [2 * np.pi * trapezoid(s.intensity(t) * np.sin(t), t) for s in model.sources]
    rgb = sum(f * np.asarray(s.colour) for f, s in zip(flux, model.sources, strict=True))
    expected = chromaticity(camera_to_xyz(rgb, matrices))
    assert (over["x"][k], over["y"][k]) == pytest.approx((expected["x"], expected["y"]), abs=1e-6)
    assert over["flux"][k] == pytest.approx(sum(flux), rel=1e-6)
    back = LightModel.load(model.save(tmp_path / "light.json"))
    assert back.chromaticity["over_theta"] == over  # in the light model JSON

    _, rays = read_tm25(write_tm25(model, tmp_path / "light.tm25ray", 60_000, seed=3))
    theta = np.degrees(np.arccos(np.clip(rays[:, 5].astype(np.float64), -1, 1)))
    band = (theta >= 20.0) & (theta < 25.0)
    total = rays[band][:, [8, 7, 9]].astype(np.float64).sum(axis=0)  # Tri_X, Tri_Y, Tri_Z
    xy = (total[0] / total.sum(), total[1] / total.sum())
    assert xy == pytest.approx((expected["x"], expected["y"]), abs=1.5e-3)  # measured: 4e-4 (5344 rays)

    html = report_colour_section(model)
    assert "<img " in html and "Varying by more than 0.002 in u′v′: the whole light." in html
