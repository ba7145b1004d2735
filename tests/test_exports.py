"""processing.exports: IES LM-63-2019 and EULUMDAT read back by an independent parser
(photompy), and TM-25-13 ray files read from real files of other software and written
from a light model."""

from __future__ import annotations

import math
import struct
import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import pbrt_irradiance_rgb, read_pbrt_lights
from scipy.integrate import trapezoid

from processing.exports.far_field import ExportError
from processing.exports.ies import FILE_GENERATION_TYPES, write_ies
from processing.exports.ldt import write_ldt
from processing.exports.tm25 import TM25Error, read_tm25, write_tm25
from processing.fit import Samples, fit_intensity
from processing.lightmodel import LightModel, SourceModel, samples_table

try:  # the independent parser of the far-field files (the `test` extra)
    import photompy
except ImportError:  # pragma: no cover
    photompy = None
needs_photompy = pytest.mark.skipif(photompy is None, reason="photompy (the test extra) is not installed")

SHARED_TM25 = Path(__file__).resolve().parents[2] / "shared/data/tm25"
THETA = np.radians(np.linspace(3.0, 41.0, 66))


def gaussian_source(name, centre, a, s, seed=0):
    rng = np.random.default_rng(seed)
    values = a * np.exp(-(THETA**2) / (2 * s * s))
    sigma = 1e-3 * a + 1e-3 * values
    samples = Samples(THETA, np.zeros(66), values + rng.normal(0, sigma), sigma, name)
    return SourceModel(name, centre, 0.0005, fit_intensity(samples, "gaussian"), samples_table(samples))


def elliptic_source(name, centre, seed=0):
    rng = np.random.default_rng(seed)
    theta, phi = np.radians(rng.uniform(2, 40, 120)), rng.uniform(0, 2 * np.pi, 120)
    d = phi - 0.7  # 40°: the lobe is not symmetric about C0–C180 or C90–C270
    values = 2.0 * np.exp(-(theta**2) * (np.cos(d) ** 2 / (2 * 0.45**2) + np.sin(d) ** 2 / (2 * 0.2**2)))
    sigma = 2e-3 + 1e-3 * values
    samples = Samples(theta, phi, values + rng.normal(0, sigma), sigma, name)
    return SourceModel(name, centre, 0.001, fit_intensity(samples, "gaussian-2d"), samples_table(samples))


PROVENANCE = {
    "run_id": "run-20261121-134501-3f2a",
    "run_file": "run-20261121-134501-3f2a.h5",
    "rig": "default",
    "software_version": "0.1.0",
    "method": "template-unmixing",
    "spatial_resolution_m": 0.015,
}


@pytest.fixture(scope="module")
def symmetric_model() -> LightModel:
    sources = [
        gaussian_source("c", (0.0, 0.0), 2.0, 0.30, 0),
        gaussian_source("+u", (0.004, 0.0), 1.5, 0.45, 1),
        gaussian_source("-v", (0.0, -0.004), 1.0, 0.15, 2),
    ]
    return LightModel(sources, "W/sr", PROVENANCE)


@pytest.fixture(scope="module")
def asymmetric_model() -> LightModel:
    sources = [gaussian_source("c", (0.0, 0.0), 1.0, 0.3, 3), elliptic_source("e", (0.004, 0.002), 4)]
    return LightModel(sources, "relative", PROVENANCE)


def read_ies(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return photompy.IESFile.read(path)


def ies_numbers(path) -> tuple[list[str], list[str]]:
    """The two numeric lines after TILT=NONE, as tokens (our own reading of the standard's layout)."""
    lines = Path(path).read_bytes().decode("ascii").split("\r\n")
    i = lines.index("TILT=NONE")
    return lines[i + 1].split(), lines[i + 2].split()


def relative(a):
    a = np.asarray(a, dtype=float)
    return a / np.max(a)


# --------------------------------------------------------------------------- IES


@needs_photompy
def test_ies_relative_table_matches_the_far_field(tmp_path, asymmetric_model):
    path = write_ies(asymmetric_model, tmp_path / "light.ies")
    ies = read_ies(path)
    phot = ies.photometry
    np.testing.assert_allclose(phot.thetas, np.arange(0, 91, 1.0))
    np.testing.assert_allclose(phot.phis, np.arange(0, 361, 5.0))
    # C is counter-clockwise seen from above the light hanging down: φ = −C
    expected = asymmetric_model.far_field(np.radians(phot.thetas)[None, :], np.radians(-phot.phis)[:, None])
    np.testing.assert_allclose(relative(phot.values), relative(expected), atol=2e-6)
    mirrored = asymmetric_model.far_field(np.radians(phot.thetas)[None, :], np.radians(phot.phis)[:, None])
    assert np.max(np.abs(relative(phot.values) - relative(mirrored))) > 0.05  # the test sees the convention
    assert float(np.max(phot.values)) == pytest.approx(1000.0, rel=1e-6)
    h = ies.header
    assert h.version.value == "LM-63-2019" and h.photometric_type.value == 1 and h.units.value == 2
    assert h.keywords["_UNITS"] == "relative intensity"
    assert "Relative intensity, not candela" in h.keywords["OTHER"]
    assert "run-20261121-134501-3f2a" in h.keywords["TEST"] and h.keywords["MANUFAC"] == "unknown"
    assert {"TESTLAB", "ISSUEDATE", "LUMCAT", "LUMINAIRE", "FILEGENINFO"} <= set(h.keywords)
    lo = min(math.degrees(s.fit.theta_range[0]) for s in asymmetric_model.sources)
    assert f"covered vertical angles {lo:.1f} to 41.0 degrees" in h.keywords["FILEGENINFO"]  # [MORE] lines joined
    # relative photometry: lumens per lamp is the flux of the table itself
    assert h.lumens_per_lamp == pytest.approx(asymmetric_model.total_flux() * 1000 / np.max(expected), rel=1e-5)


@needs_photompy
def test_ies_layout_and_file_generation_type(tmp_path, symmetric_model):
    path = write_ies(
        symmetric_model, tmp_path / "light.ies", vertical_step_deg=2.5, vertical_max_deg=180, horizontal_step_deg=15
    )
    raw = path.read_bytes()
    assert raw.startswith(b"IES:LM-63-2019\r\n") and b"\nTILT=NONE\r\n" in raw
    lines = raw.decode("ascii").split("\r\n")
    assert max(len(x) for x in lines) <= 132 and b"\n" not in raw.replace(b"\r\n", b"")
    first, second = ies_numbers(path)
    # lamps, lumens, multiplier, #vertical, #horizontal, type C, metres, width (y), length (x), height
    assert first[0] == "1" and first[2:7] == ["1", "73", "25", "1", "2"]
    assert float(first[7]) == pytest.approx(0.005) and float(first[8]) == pytest.approx(0.005) and first[9] == "0"
    assert second[:2] == ["1.0", "1.01000"]  # LM-63-2019 Table 2: unaccredited lab, interpolated angle set
    phot = read_ies(path).photometry
    assert np.all(phot.values[:, phot.thetas > 90] == 0)  # nothing behind the light plane
    write_ies(symmetric_model, path, lamp_lumens=1200.0)
    assert ies_numbers(path)[1][1] == "1.01100"  # … that has been lumen scaled
    write_ies(symmetric_model, path, file_generation_type="1.00010")
    assert ies_numbers(path)[1][1] == "1.00010"
    assert FILE_GENERATION_TYPES["1.00010"] == "Computer Simulation"


@needs_photompy
def test_ies_lumen_scaled_and_calibrated(tmp_path, symmetric_model):
    path = write_ies(symmetric_model, tmp_path / "scaled.ies", lamp_lumens=1200.0)
    ies = read_ies(path)
    assert ies.header.lumens_per_lamp == pytest.approx(1200.0)
    phot = ies.photometry
    # the table carries the lamp's flux: ∫ I dΩ over the sphere (trapezoid on the 1° × 5° grid)
    t = np.radians(phot.thetas)
    per_plane = trapezoid(phot.values * np.sin(t)[None, :], t, axis=1)
    flux = trapezoid(per_plane, np.radians(phot.phis))
    assert flux == pytest.approx(1200.0, rel=2e-3)

    path = write_ies(symmetric_model, tmp_path / "absolute.ies", calibration=250.0)
    ies = read_ies(path)
    assert ies.header.lumens_per_lamp == -1  # absolute photometry
    assert ies.header.keywords["_UNITS"] == "candela"
    assert "250 cd per model unit" in ies.header.keywords["OTHER"]
    phot = ies.photometry
    expected = 250.0 * symmetric_model.far_field(np.radians(phot.thetas)[None, :], np.radians(-phot.phis)[:, None])
    np.testing.assert_allclose(phot.values, expected, rtol=1e-5, atol=1e-9)


def one_line(exc) -> str:
    msg = str(exc.value)
    assert "\n" not in msg
    return msg


def test_ies_errors_name_the_file_and_field(tmp_path, symmetric_model):
    path = tmp_path / "x.ies"
    with pytest.raises(ExportError) as e:
        write_ies(symmetric_model, path, vertical_step_deg=7)
    assert one_line(e) == f"{path}: vertical_step_deg: 7° does not divide 90°"
    with pytest.raises(ExportError) as e:
        write_ies(symmetric_model, path, calibration=2.0, lamp_lumens=100)
    assert one_line(e).startswith(f"{path}: give calibration")
    with pytest.raises(ExportError) as e:
        write_ies(symmetric_model, path, file_generation_type="1.2")
    assert one_line(e).startswith(f"{path}: file_generation_type: '1.2' is not a token of LM-63-2019 Table 2")
    with pytest.raises(ExportError, match="vertical_max_deg: must be 90 or 180"):
        write_ies(symmetric_model, path, vertical_max_deg=120)
    assert not path.exists()


# --------------------------------------------------------------------------- EULUMDAT


@needs_photompy
@pytest.mark.parametrize("which", ["symmetric", "asymmetric"])
def test_ldt_matches_the_far_field(tmp_path, which, request):
    model = request.getfixturevalue(f"{which}_model")
    path = write_ldt(model, tmp_path / "light.ldt")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ldt = photompy.LDTFile.read(path)
    phot = ldt.photometry
    np.testing.assert_allclose(phot.thetas, np.arange(0, 181, 5.0))
    np.testing.assert_allclose(phot.phis, np.arange(0, 360, 15.0))
    expected = model.far_field(np.radians(phot.thetas)[None, :], np.radians(-phot.phis)[:, None])
    np.testing.assert_allclose(relative(phot.values), relative(expected), atol=1e-5)  # 6 digits, twice rounded
    lines = path.read_text().split("\n")
    assert lines[1].strip() == ("1" if which == "symmetric" else "3") and lines[2].strip() == "0"
    # cd/klm of the lamp flux: the file's numbers times flux/1000 are the relative candela
    assert ldt.header.lamps[0].total_flux == pytest.approx(model.total_flux() * 1000 / np.max(expected), rel=1e-5)


# --------------------------------------------------------------------------- TM-25

needs_shared = pytest.mark.skipif(not SHARED_TM25.exists(), reason=f"{SHARED_TM25} is absent")


@needs_shared
def test_read_real_tm25_files():
    h, rays = read_tm25(SHARED_TM25 / "cyl10k.tm25ray")
    assert h["n_rays"] == 10000 and rays.shape == (10000, 7) and rays.dtype == np.float32
    assert h["columns"] == ["x", "y", "z", "kx", "ky", "kz", "Tri_Y"]  # luminous flux only
    assert h["luminous_flux"] == 1.0 and h["radiant_flux"] == 0.0
    assert float(rays[:, 6].sum(dtype=np.float64)) == pytest.approx(10000.0, rel=1e-6)  # not the header's 1 lm
    assert h["texts"]["rayfile_creator"].strip() == "LightTools 8.7.0"

    h, rays = read_tm25(SHARED_TM25 / "farfield.tm25ray")
    assert h["n_rays"] == 100000 and h["columns"][6] == "phi" and h["spectrum_type"] == 1 and h["wavelength"] == 500.0
    assert math.isnan(h["luminous_flux"]) and h["radiant_flux"] == 1.0
    assert float(rays[:, 6].sum(dtype=np.float64)) == pytest.approx(31350.1376, rel=1e-6)
    assert np.all(rays[:, :3] == 0)  # a point source
    np.testing.assert_allclose(np.linalg.norm(rays[:, 3:6], axis=1), 1.0, atol=1e-6)

    h, rays = read_tm25(SHARED_TM25 / "osram_blue_100k.TM25RAY")
    assert h["n_rays"] == 100000 and h["creation_method"] == 1 and h["ray_offset"] == 36928
    assert len(h["spectra"]) == 1 and len(h["spectra"][0]["wavelength"]) == 76
    assert h["spectra"][0]["wavelength"][0] == pytest.approx(390.0)
    assert h["texts"]["name"] == "LERTDUW_S2WP" and h["texts"]["manufacturer"] == "OSRAM Opto Semiconductors GmbH"
    assert float(rays[:, 6].sum(dtype=np.float64)) == pytest.approx(h["radiant_flux"], rel=1e-6)
    assert h["trailing_bytes"] == 0


def theta_bin_flux(model, edges):
    out = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        t = np.linspace(lo, hi, 201)
        out.append(2 * np.pi * trapezoid(model.far_field(t) * np.sin(t), t))
    return np.array(out)


def test_tm25_write_read_round_trip(tmp_path, symmetric_model):
    model = symmetric_model
    path = write_tm25(model, tmp_path / "light.tm25ray", 200_000, seed=7, name="test light")
    h, rays = read_tm25(path)
    assert h["n_rays"] == 200_000 and h["columns"] == ["x", "y", "z", "kx", "ky", "kz", "phi"]
    assert h["version"] == 2013 and h["creation_method"] == 1 and h["spectrum_type"] == 0
    assert h["texts"]["name"] == "test light" and "relative" not in h["texts"]["additional_info"]
    assert "run-20261121-134501-3f2a" in h["texts"]["data_reference"]
    assert path.stat().st_size == 36288 + 200_000 * 7 * 4
    flux = rays[:, 6].astype(np.float64)
    assert h["radiant_flux"] == pytest.approx(flux.sum(), rel=1e-6)
    assert flux.sum() == pytest.approx(model.total_flux(), rel=1e-6)
    # each ray starts on its source's disc, on the plane, and leaves forwards
    centres = np.array([s.centre_m for s in model.sources]) * 1000
    which = np.argmin(np.linalg.norm(rays[:, None, :2] - centres[None], axis=2), axis=1)
    assert np.all(np.linalg.norm(rays[:, :2] - centres[which], axis=1) <= 0.5 + 1e-4) and np.all(rays[:, 2] == 0)
    np.testing.assert_allclose(np.linalg.norm(rays[:, 3:6], axis=1), 1.0, atol=1e-6)
    assert np.all(rays[:, 5] >= 0)
    for i, s in enumerate(model.sources):  # every source carries its own flux
        assert flux[which == i].sum() == pytest.approx(s.flux(), rel=1e-5)
    # directions follow the intensity: flux per θ band against ∫ I dΩ
    edges = np.radians(np.arange(0, 91, 5.0))
    theta = np.arccos(np.clip(rays[:, 5].astype(np.float64), -1, 1))
    observed = np.histogram(theta, edges, weights=flux)[0]
    expected = theta_bin_flux(model, edges)
    counts = np.histogram(theta, edges)[0]
    stat = expected / np.sqrt(np.maximum(counts, 1))
    assert np.all(np.abs(observed - expected) < 5 * stat + 1e-4 * expected.sum())
    # the same seed writes the same rays
    _, again = read_tm25(write_tm25(model, tmp_path / "again.tm25ray", 200_000, seed=7))
    np.testing.assert_array_equal(again, rays)


def test_tm25_millions_of_rays_are_written_in_bounded_memory(tmp_path, asymmetric_model):
    import tracemalloc

    from processing.exports.tm25 import RAY_BLOCK

    def peak_writing(n: int) -> tuple[Path, int]:
        tracemalloc.start()
        try:
            path = write_tm25(asymmetric_model, tmp_path / f"{n}.tm25ray", n, seed=3)
            return path, tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()

    _, few = peak_writing(2 * RAY_BLOCK)
    n = 8 * RAY_BLOCK + 12_345  # blocks of both sources, and a part block
    path, peak = peak_writing(n)
    whole = n * 7 * 4  # the rays as written: 29 MB
    assert peak < 1.05 * few + 1e6 and peak < whole, f"{peak / 1e6:.1f} MB ({few / 1e6:.1f} MB for a quarter)"
    h, rays = read_tm25(path)
    assert h["n_rays"] == len(rays) == n and path.stat().st_size == 36288 + whole
    assert h["radiant_flux"] == pytest.approx(rays[:, 6].astype(np.float64).sum(), rel=1e-7)  # float32
    assert h["radiant_flux"] == pytest.approx(asymmetric_model.total_flux(), rel=1e-6)
    np.testing.assert_allclose(np.linalg.norm(rays[:, 3:6], axis=1), 1.0, atol=1e-6)


def test_tm25_samples_azimuth_of_an_elliptical_lobe(tmp_path, asymmetric_model):
    only = LightModel([asymmetric_model.sources[1]], "relative", PROVENANCE)
    h, rays = read_tm25(write_tm25(only, tmp_path / "e.tm25ray", 100_000, seed=1))
    assert "relative units" in h["texts"]["additional_info"]
    k = rays[:, 3:6].astype(np.float64)
    phi = np.mod(np.arctan2(k[:, 1], k[:, 0]), 2 * np.pi)
    edges = np.linspace(0, 2 * np.pi, 13)
    observed = np.histogram(phi, edges, weights=rays[:, 6])[0]
    t = np.linspace(0, np.pi / 2, 400)
    expected = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        p = np.linspace(lo, hi, 41)
        grid = only.far_field(t[:, None], p[None, :]) * np.sin(t)[:, None]
        expected.append(trapezoid(trapezoid(grid, t, axis=0), p))
    expected = np.array(expected)
    np.testing.assert_allclose(observed, expected, rtol=0.03)
    assert observed.max() / observed.min() > 1.5  # the test sees the ellipse


def test_tm25_errors_are_one_line(tmp_path, symmetric_model):
    good = write_tm25(symmetric_model, tmp_path / "good.tm25ray", 1000, seed=1)
    cut = tmp_path / "cut.tm25ray"
    cut.write_bytes(good.read_bytes()[:-100])
    with pytest.raises(TM25Error) as e:
        read_tm25(cut)
    assert one_line(e).startswith(f"{cut}: ") and "truncated" in one_line(e)

    other = tmp_path / "other.tm25ray"
    other.write_bytes(b"PK\x03\x04" + bytes(40000))
    with pytest.raises(TM25Error) as e:
        read_tm25(other)
    assert one_line(e) == f"{other}: not a TM-25 ray file (file type b'PK\\x03\\x04', expected b'TM25')"

    newer = tmp_path / "newer.tm25ray"
    data = bytearray(good.read_bytes())
    struct.pack_into("<i", data, 4, 2020)
    newer.write_bytes(bytes(data))
    with pytest.raises(TM25Error, match="file version: 2020, this reader knows TM-25-13"):
        read_tm25(newer)

    short = tmp_path / "short.tm25ray"
    short.write_bytes(b"TM25" + bytes(96))
    with pytest.raises(TM25Error, match="shorter than a TM-25 header"):
        read_tm25(short)

    with pytest.raises(ExportError, match="n_rays: must be a positive integer"):
        write_tm25(symmetric_model, tmp_path / "z.tm25ray", 0, seed=1)


# --------------------------------------------------------------------------- pbrt-v4 goniometric lights


def test_pbrt_goniometric_lights_reproduce_the_near_field(tmp_path, asymmetric_model):
    from drivers.pose import Pose
    from processing.exports.pbrt import write_pbrt_lights

    tinted = SourceModel(**{**vars(asymmetric_model.sources[1]), "colour": (1.2, 1.0, 0.8)})
    model = LightModel([asymmetric_model.sources[0], tinted], "relative")
    pose = Pose(0.05, -0.02, 0.30, 2.9, 0.3, 0.5)
    files = write_pbrt_lights(model, tmp_path / "light.pbrt", poses=[pose], pose_names=["p0"])
    assert [f.name for f in files] == ["light.pbrt", "light-p0.pbrt", "light-source-c.exr", "light-source-e.exr"]
    rng = np.random.default_rng(5)
    # points 5–30 cm in front of the light, lit from the light, in the light frame and in the rig's
    local = np.column_stack([rng.uniform(-0.12, 0.12, 400), rng.uniform(-0.12, 0.12, 400), rng.uniform(0.05, 0.3, 400)])
    normals = -local / np.linalg.norm(local, axis=1)[:, None] + rng.normal(0, 0.3, (400, 3))
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    want = model.irradiance_rgb(local, normals)
    for scene, points, n in [
        ("light.pbrt", local, normals),
        ("light-p0.pbrt", local @ pose.rotation.T + pose.position, normals @ pose.rotation.T),
    ]:
        got = pbrt_irradiance_rgb(read_pbrt_lights(tmp_path / scene), points, n)
        error = np.abs(got - want) / want.max()
        assert np.median(error) < 1e-3 and error.max() < 0.01, (scene, np.median(error), error.max())
        # the colour goes with its source: the red-to-blue ratio of the coloured lobe's side
        assert np.corrcoef(got[:, 0] / got[:, 2], want[:, 0] / want[:, 2])[0, 1] > 0.99


def test_pbrt_tables_hold_each_sources_flux_and_say_their_units(tmp_path, asymmetric_model):
    from processing.exports.pbrt import write_pbrt_lights

    write_pbrt_lights(asymmetric_model, tmp_path / "light.pbrt", calibration=250.0)
    lights = read_pbrt_lights(tmp_path / "light.pbrt")
    for (_, table, _, scale), source in zip(lights, asymmetric_model.sources, strict=True):
        # equal area: every pixel is 4π/n² sr, so the flux is the mean times 4π
        assert table.mean() * 4 * np.pi == pytest.approx(source.flux(), rel=2e-3)
        assert scale == 250.0
    assert "candela (250 cd per model unit)" in (tmp_path / "light.pbrt").read_text()
    write_pbrt_lights(asymmetric_model, tmp_path / "none.pbrt", extrapolation="none")
    measured_only = read_pbrt_lights(tmp_path / "none.pbrt")
    for (_, table, _, _), source in zip(measured_only, asymmetric_model.sources, strict=True):
        assert 0 < table.mean() * 4 * np.pi < source.flux()  # beyond the measured 40°, nothing
    with pytest.raises(ExportError, match=r"bad\.pbrt: calibration"):
        write_pbrt_lights(asymmetric_model, tmp_path / "bad.pbrt", calibration=-1.0)
    with pytest.raises(ExportError, match=r"bad\.pbrt: extrapolation"):
        write_pbrt_lights(asymmetric_model, tmp_path / "bad.pbrt", extrapolation="some")
