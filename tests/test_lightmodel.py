"""processing.lightmodel: the light model's physics (intensity, far field, irradiance,
flux) against hand calculations, and its versioned JSON file."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from processing.fit import Samples, fit_intensity
from processing.lightmodel import (
    LIGHT_MODEL_FORMAT,
    LIGHT_MODEL_VERSION,
    LightModel,
    LightModelError,
    SourceModel,
    samples_table,
)

THETA = np.radians(np.linspace(3.0, 41.0, 66))


def source(name, centre, method="gaussian", seed=0, **truth):
    """A source fitted to noise-free-ish samples of a known lobe."""
    rng = np.random.default_rng(seed)
    phi = np.zeros_like(THETA)
    if method == "polynomial":  # flat: isotropic over the hemisphere
        values = np.full_like(THETA, truth["i0"])
    elif method == "cos-power":
        values = truth["a"] * np.cos(THETA) ** truth["mu"]
    elif method == "gaussian-2d":
        phi = rng.uniform(0, 2 * np.pi, 66)
        d = phi - truth["phi0"]
        q = np.cos(d) ** 2 / (2 * truth["s1"] ** 2) + np.sin(d) ** 2 / (2 * truth["s2"] ** 2)
        values = truth["a"] * np.exp(-(THETA**2) * q)
    else:
        values = truth["a"] * np.exp(-(THETA**2) / (2 * truth["s"] ** 2))
    sigma = 1e-3 * np.max(values) + 1e-3 * values
    samples = Samples(THETA, phi, values + rng.normal(0, sigma), sigma, name)
    options = {"degree": 0} if method == "polynomial" else {}
    fit = fit_intensity(samples, method, **options)
    cells = values * 0.075  # a fast-path estimate, for the table
    return SourceModel(name, centre, 0.0005, fit, samples_table(samples, np.arange(66) + 10, cells))


def five_gaussians() -> LightModel:
    """The reference truth: five Gaussian sources, 4 mm apart (docs/measurement.md)."""
    layout = [
        ("c", (0.0, 0.0), 2.0, 0.30),
        ("+u", (0.004, 0.0), 1.5, 0.35),
        ("-u", (-0.004, 0.0), 1.2, 0.25),
        ("+v", (0.0, 0.004), 1.0, 0.40),
        ("-v", (0.0, -0.004), 0.8, 0.28),
    ]
    sources = [source(n, c, a=a, s=s, seed=i) for i, (n, c, a, s) in enumerate(layout)]
    prov = {
        "run_id": "run-20261121-134501-3f2a",
        "run_file": "runs/run-20261121-134501-3f2a.h5",
        "rig": "default",
        "software_version": "0.1.0",
        "method": "template-unmixing",
        "spatial_resolution_m": 0.015,
    }
    return LightModel(sources, "W/sr", prov)


def test_irradiance_of_an_isotropic_source_by_hand():
    """One flat source of I0 = 5 W/sr at (u, v) = (10 mm, −20 mm): E = I0·cos/d²."""
    src = source("flat", (0.010, -0.020), "polynomial", i0=5.0)
    i0 = src.fit.params["c0"]
    assert i0 == pytest.approx(5.0, rel=1e-3)
    model = LightModel([src], "W/sr")
    # r = (0.04, 0.02, 0.3): d = r − p = (0.03, 0.04, 0.3), |d|² = 0.0925
    # normal straight back at the plane, n = (0, 0, −1): n·ω = 0.3/√0.0925
    # a tilted normal n = (−0.6, 0, −0.8): n·ω = (0.6·0.03 + 0.8·0.3)/√0.0925
    # a normal facing away gets nothing
    points = np.array([[0.04, 0.02, 0.3], [0.04, 0.02, 0.3], [0.04, 0.02, 0.3], [0.04, 0.02, -0.3], [0.0, 0.0, 0.0]])
    normals = np.array([[0, 0, -1.0], [-0.6, 0, -0.8], [0, 0, 1.0], [0, 0, 1.0], [0, 0, -1.0]])
    E = model.irradiance(points, normals)
    d2 = 0.0925
    expected = [i0 * 0.3 / math.sqrt(d2) / d2, i0 * (0.6 * 0.03 + 0.8 * 0.3) / math.sqrt(d2) / d2, 0.0, 0.0, 0.0]
    np.testing.assert_allclose(E, expected, rtol=1e-12, atol=0)
    # normals need not be unit vectors; one normal broadcasts to every point
    np.testing.assert_allclose(model.irradiance(points[:1], [0, 0, -7.0]), expected[:1], rtol=1e-12)


def test_irradiance_uses_each_sources_own_direction():
    """An elliptical lobe off the axis: E at r is I_s at the direction from p_s to r."""
    src = source("ell", (0.003, 0.001), "gaussian-2d", a=3.0, s1=0.4, s2=0.2, phi0=0.7)
    model = LightModel([src, source("g", (-0.002, 0.0), a=1.0, s=0.3)], "relative")
    rng = np.random.default_rng(1)
    points = np.column_stack([rng.uniform(-0.1, 0.1, 50), rng.uniform(-0.1, 0.1, 50), rng.uniform(0.05, 0.3, 50)])
    normals = rng.normal(size=(50, 3))
    expected = np.zeros(50)
    for s in model.sources:
        for k, (r, n) in enumerate(zip(points, normals, strict=True)):
            d = r - np.array([*s.centre_m, 0.0])
            dist = np.linalg.norm(d)
            theta, phi = math.acos(d[2] / dist), math.atan2(d[1], d[0])
            cos_in = max(0.0, float(np.dot(n / np.linalg.norm(n), -d / dist)))
            expected[k] += s.fit(theta, phi) * cos_in / dist**2
    np.testing.assert_allclose(model.irradiance(points, normals), expected, rtol=1e-12)


def test_irradiance_checks_its_arguments():
    model = five_gaussians()
    with pytest.raises(LightModelError, match=r"points must be \(N, 3\)"):
        model.irradiance(np.zeros((4, 2)), np.zeros((4, 2)))
    with pytest.raises(LightModelError, match="normals must be non-zero"):
        model.irradiance(np.ones((2, 3)), np.zeros((2, 3)))


def test_far_field_is_the_sum_of_the_sources():
    model = five_gaussians()
    theta = np.radians(np.linspace(0, 89, 40))[:, None]
    phi = np.radians(np.arange(0, 360, 30))[None, :]
    total = sum(model.intensity(i, theta, phi) for i in range(5))
    np.testing.assert_allclose(model.far_field(theta, phi), total, rtol=1e-14)
    assert model.far_field(theta, phi).shape == (40, 12)
    # by name as by index
    np.testing.assert_array_equal(model.intensity("+u", theta), model.intensity(1, theta))


def test_intensity_is_zero_behind_the_plane_and_never_negative():
    model = five_gaussians()
    assert np.all(model.far_field(np.radians([90.5, 120, 180])) == 0)
    # a polynomial extrapolated far beyond its data can dip below zero: the model clips it
    src = source("p", (0, 0), "polynomial", i0=1.0)
    src.fit.params = {"c0": 1.0, "c1": -10.0}
    assert src.fit(0.5) < 0 and LightModel([src]).intensity(0, 0.5) == 0.0
    with pytest.raises(LightModelError, match="no such source"):
        model.intensity("nope", 0.1)
    with pytest.raises(LightModelError, match="out of range"):
        model.intensity(5, 0.1)


def test_total_flux_against_closed_forms():
    # isotropic over the hemisphere: 2π·I0; cos^μ: 2π·a/(μ + 1)
    flat = source("flat", (0, 0), "polynomial", i0=5.0)
    assert LightModel([flat]).total_flux() == pytest.approx(2 * math.pi * flat.fit.params["c0"], rel=1e-12)
    cp = source("cp", (0, 0), "cos-power", a=3.0, mu=2.5)
    a, mu = cp.fit.params["a"], cp.fit.params["mu"]
    assert LightModel([cp]).total_flux() == pytest.approx(2 * math.pi * a / (mu + 1), rel=1e-10)
    # an elliptical lobe narrow enough to ignore the plane: 2π·a·σ₁σ₂ (small-angle Gaussian)
    el = source("el", (0, 0), "gaussian-2d", a=3.0, s1=0.12, s2=0.06, phi0=0.7)
    p = el.fit.params
    assert LightModel([el]).total_flux() == pytest.approx(2 * math.pi * p["a"] * p["sigma1"] * p["sigma2"], rel=5e-3)
    model = LightModel([flat, cp])
    assert model.total_flux() == pytest.approx(flat.flux() + cp.flux(), rel=1e-14)


def test_save_load_round_trip_is_exact(tmp_path):
    model = five_gaussians()
    model.sources[0].samples["cell_sum_intensity"][3] = float("nan")  # a position without a cell sum
    path = model.save(tmp_path / "light.json")
    text = path.read_text()
    json.loads(text)  # strict JSON: the NaN is written as null
    back = LightModel.load(path)
    assert back.sources[0].samples["cell_sum_intensity"][3] is None
    model.sources[0].samples["cell_sum_intensity"][3] = None
    assert back == model and back.to_dict() == model.to_dict()
    assert back.save(tmp_path / "again.json").read_text() == text
    t = np.linspace(0, 1.6, 33)
    np.testing.assert_array_equal(back.far_field(t), model.far_field(t))
    for a, b in zip(back.sources, model.sources, strict=True):
        np.testing.assert_array_equal(a.fit.covariance, b.fit.covariance)
        assert a.fit.theta_range == b.fit.theta_range and a.centre_m == b.centre_m
    assert back.provenance["method"] == "template-unmixing" and back.units == "W/sr"
    # small and human-readable: one key a line, number lists on one line
    assert text.startswith('{\n  "format": "mirrorgonio-light-model",\n  "format_version": 1,')
    assert len(text) < 60_000


def one_line(exc) -> str:
    msg = str(exc.value)
    assert "\n" not in msg
    return msg


def test_a_newer_format_version_is_refused_in_one_line(tmp_path):
    d = five_gaussians().to_dict()
    d["format_version"] = LIGHT_MODEL_VERSION + 1
    path = tmp_path / "future.json"
    path.write_text(json.dumps(d))
    with pytest.raises(LightModelError) as e:
        LightModel.load(path)
    msg = one_line(e)
    assert msg.startswith(str(path)) and "format_version 2 is newer" in msg and "update mirrorgonio" in msg


@pytest.mark.parametrize(
    "content, words",
    [
        ('{"type": "FeatureCollection", "features": []}', "not a mirrorgonio light model (format None"),
        ('{"format": "mirrorgonio-results", "format_version": 1}', "format 'mirrorgonio-results'"),
        ("[1, 2, 3]", "not a mirrorgonio light model (a JSON list"),
        ("format = 'toml'", "not JSON (Expecting value, line 1)"),
        (f'{{"format": "{LIGHT_MODEL_FORMAT}", "format_version": "1"}}', "format_version: '1' is not a version"),
    ],
)
def test_foreign_files_are_refused_in_one_line(tmp_path, content, words):
    path = tmp_path / "foreign.json"
    path.write_text(content)
    with pytest.raises(LightModelError) as e:
        LightModel.load(path)
    msg = one_line(e)
    assert msg.startswith(str(path)) and words in msg


def test_bad_fields_are_named(tmp_path):
    d = five_gaussians().to_dict()
    del d["sources"][2]["fit"]["params"]
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(d))
    with pytest.raises(LightModelError) as e:
        LightModel.load(path)
    assert one_line(e) == f"{path}: sources[2].fit: missing params"
    d = five_gaussians().to_dict()
    d["sources"][1]["name"] = d["sources"][0]["name"]
    path.write_text(json.dumps(d))
    with pytest.raises(LightModelError, match="duplicate name 'c'"):
        LightModel.load(path)
    with pytest.raises(LightModelError) as e:
        LightModel.load(tmp_path / "missing.json")
    assert one_line(e).endswith("missing.json: light-model file not found")


def test_model_validation():
    src = source("c", (0, 0), a=1.0, s=0.3)
    with pytest.raises(LightModelError, match="units: 'lm' is not one of W/sr, relative"):
        LightModel([src], "lm")
    with pytest.raises(LightModelError, match="at least one source"):
        LightModel([], "relative")
    with pytest.raises(LightModelError, match="radius_m must be finite and >= 0"):
        SourceModel("x", (0, 0), -1.0, src.fit)
    with pytest.raises(LightModelError, match="samples: columns differ in length"):
        samples_table(Samples(THETA, THETA, THETA, THETA + 1), positions=[1, 2])


def test_a_sources_colour_is_relative_saved_and_mixes_into_the_irradiance(tmp_path):
    """``colour`` is kept with a mean of 1 (only the channels' ratios are the colour), is
    written and read back, reads as grey from a file written before it existed, and each
    channel's irradiance mixes the sources' colours as they light the point; the channel
    mean is the grey irradiance."""
    model = five_gaussians()
    colours = [(2.6, 2.0, 1.4), (1.0, 1.0, 1.0), (0.8, 1.0, 1.2), (1.0, 1.0, 1.0), (1.0, 1.0, 1.0)]
    model = LightModel(
        [
            SourceModel(s.name, s.centre_m, s.radius_m, s.fit, s.samples, c)
            for s, c in zip(model.sources, colours, strict=True)
        ],
        model.units,
        model.provenance,
    )
    assert model.sources[0].colour == pytest.approx((1.3, 1.0, 0.7), rel=1e-12)
    back = LightModel.load(model.save(tmp_path / "tinted.json"))
    assert [s.colour for s in back.sources] == [s.colour for s in model.sources]
    old = json.loads((tmp_path / "tinted.json").read_text())
    for s in old["sources"]:
        del s["colour"]
    (tmp_path / "old.json").write_text(json.dumps(old))
    assert {s.colour for s in LightModel.load(tmp_path / "old.json").sources} == {(1.0, 1.0, 1.0)}

    rng = np.random.default_rng(3)
    points = np.column_stack([rng.uniform(-0.05, 0.05, (50, 2)), rng.uniform(0.02, 0.2, 50)])
    normals = np.tile([0.0, 0.0, -1.0], (50, 1)) + rng.normal(0, 0.2, (50, 3))
    rgb = model.irradiance_rgb(points, normals)
    np.testing.assert_allclose(rgb.mean(axis=1), model.irradiance(points, normals), rtol=1e-12)
    by_hand = np.zeros((50, 3))
    for s in model.sources:
        alone = LightModel([SourceModel(s.name, s.centre_m, s.radius_m, s.fit, s.samples)], model.units)
        by_hand += alone.irradiance(points, normals)[:, None] * np.asarray(s.colour)
    np.testing.assert_allclose(rgb, by_hand, rtol=1e-12)
    # The whole light's colour: weighted by each source's on-axis intensity.
    weights = np.array([s.intensity(0.0) for s in model.sources]).ravel()
    mixed = (weights[:, None] * np.array(colours) / np.array(colours).mean(axis=1, keepdims=True)).sum(axis=0)
    np.testing.assert_allclose(model.colour(), mixed / mixed.mean(), rtol=1e-12)


@pytest.mark.parametrize("colour", [(1.0, 2.0), (1.0, 0.0, 1.0), (1.0, float("nan"), 1.0), "red"])
def test_a_bad_colour_is_one_line_naming_the_source(colour):
    model = five_gaussians()
    s = model.sources[0]
    with pytest.raises(LightModelError) as exc:
        SourceModel(s.name, s.centre_m, s.radius_m, s.fit, s.samples, colour)
    assert one_line(exc).startswith(f"source {s.name!r}: colour must be")


def test_a_centres_1_sigma_reads_back_and_a_bad_one_is_one_line(tmp_path):
    """``centre_sigma_m`` (where the centre was found in the data) is saved and read back; a
    negative or malformed one is refused naming the source and the field."""
    model = five_gaussians()
    s = model.sources[0]
    found = SourceModel(s.name, s.centre_m, s.radius_m, s.fit, s.samples, centre_sigma_m=(2e-5, 3e-5))
    path = LightModel([found]).save(tmp_path / "m.light.json")
    assert LightModel.load(path).sources[0].centre_sigma_m == (2e-5, 3e-5)
    assert "centre_sigma_m" not in model.sources[1].to_dict()  # a layout given: none
    for bad, says in (((1e-5, -1e-5), "must be finite and >= 0"), ("x", "must be two numbers")):
        with pytest.raises(LightModelError) as exc:
            SourceModel(s.name, s.centre_m, s.radius_m, s.fit, centre_sigma_m=bad)
        assert one_line(exc).startswith(f"source {s.name!r}: centre_sigma_m {says}")
