"""processing.photometry: the photometric summary of the whole light against analytic cos^n
lobes and against an independent reading of the written IES and LDT files (photompy), the
measured-only option in the files, and the summary first in the report."""

from __future__ import annotations

import math
import re
import warnings

import numpy as np
import pytest
from pydantic import ValidationError

from acquisition.daemon.models import JobRequest
from processing.exports.ies import write_ies
from processing.exports.ldt import write_ldt
from processing.fit import IntensityFit
from processing.lightmodel import LightModel, SourceModel
from processing.options import Extrapolation, OptionsError, ProcessingOptions
from processing.photometry import far_field, near_field, summarize
from processing.report.page import write_report

try:  # the independent reader of the far-field files (the `test` extra)
    import photompy
except ImportError:  # pragma: no cover
    photompy = None
needs_photompy = pytest.mark.skipif(photompy is None, reason="photompy (the test extra) is not installed")

TOP = math.radians(42.3)  # the θ the demo's sweep measures to


def fit(method: str, params: dict, top: float = math.pi / 2) -> IntensityFit:
    """A fit made directly (no samples): ``params`` of ``method``, measured over ``0 ≤ θ ≤ top``."""
    n = len(params)
    zeros = dict.fromkeys(params, 0.0)
    return IntensityFit(method, params, zeros, np.zeros((n, n)), np.zeros(0), 1.0, 10, (0.0, top), (0.0, 2 * math.pi))


def cos_power(n: float, a: float = 1.0, top: float = math.pi / 2, centre=(0.0, 0.0)) -> LightModel:
    return LightModel([SourceModel("s", centre, 0.0, fit("cos-power", {"a": a, "mu": n}, top))], "W/sr")


def five_lobes(top: float = TOP) -> LightModel:
    """The demo's light: five Gaussian lobes 4 mm apart (sim_devices/lights/five-gaussians.toml),
    and an elliptical one off-centre so that the C-planes differ."""
    lobes = (("centre", (0, 0), 1.0, 20), ("+u", (4, 0), 0.8, 25), ("-u", (-4, 0), 0.6, 30), ("+v", (0, 4), 0.9, 15))
    sources = [
        SourceModel(name, (1e-3 * u, 1e-3 * v), 5e-4, fit("gaussian", {"a": a, "sigma": math.radians(s)}, top))
        for name, (u, v), a, s in lobes
    ]
    params = {"a": 0.7, "sigma1": math.radians(35), "sigma2": math.radians(18), "phi0": math.radians(30)}
    sources.append(SourceModel("-v", (0.0, -4e-3), 5e-4, fit("gaussian-2d", params, top)))
    return LightModel(sources, "W/sr", {"run_id": "run-photometry"})


# --------------------------------------------------------------------------- analytic lobes


@pytest.mark.parametrize("n", [1.0, 2.0, 7.5])
def test_a_cos_power_lobe_has_its_analytic_flux_zones_and_angles(n):
    summary = summarize(cos_power(n, a=2.0), near_field_m=None)
    assert summary.total_flux == pytest.approx(2 * math.pi * 2.0 / (n + 1), rel=1e-12)  # π·I0 for n = 1
    edges = np.radians(summary.zone_edges_deg)
    zones = 2 * math.pi * 2.0 * (np.cos(edges[:-1]) ** (n + 1) - np.cos(edges[1:]) ** (n + 1)) / (n + 1)
    np.testing.assert_allclose(summary.zone_measured, zones, rtol=1e-10, atol=1e-14)
    assert summary.beyond_fraction == 0.0
    for plane in ("C0-C180", "C90-C270"):
        assert summary.angle("beam", plane) == pytest.approx(2 * math.degrees(math.acos(0.5 ** (1 / n))), abs=2e-4)
        assert summary.angle("field", plane) == pytest.approx(2 * math.degrees(math.acos(0.1 ** (1 / n))), abs=2e-4)
    assert summary.peak == (pytest.approx(2.0), 0.0, 0.0, True)


def test_the_flux_beyond_the_measured_theta_and_the_measured_only_light():
    model = cos_power(4.0, top=math.radians(40.0))
    beyond = math.cos(math.radians(40.0)) ** 5  # the share of a cos⁴ lobe's flux beyond 40°
    fitted = summarize(model, near_field_m=None)
    assert fitted.beyond_fraction == pytest.approx(beyond, rel=1e-12)
    assert not fitted.angles["beam"]["C0-C180"].beyond_measured  # 65.5° wide: within the 40° measured
    assert fitted.angles["field"]["C0-C180"].beyond_measured  # 111.6° wide: on the extrapolation
    measured = summarize(model, "none", near_field_m=None)
    assert measured.total_flux == pytest.approx(fitted.total_flux * (1 - beyond), rel=1e-12)
    assert measured.beyond_fraction == 0.0 and measured.fitted_beyond_fraction == pytest.approx(beyond, rel=1e-12)
    assert far_field(model, math.radians(40.5), 0.0, "none") == 0.0 < far_field(model, math.radians(39.5), 0.0, "none")
    record = measured.record()
    assert record["extrapolation"] == "none" and record["measured_theta_max_deg"] == pytest.approx(40.0)
    assert record["fitted_flux_beyond_measured_percent"] == pytest.approx(100 * beyond)


def test_the_near_field_of_one_source_is_its_far_field_and_of_an_array_is_not():
    model = cos_power(1.0, a=3.0)
    near = near_field(model, 0.3, 0.2, n=41)
    # E = I0 cos θ · cos θ / r², r = d / cos θ: I0 cos⁴θ / d² for a Lambertian point
    xx, yy = np.meshgrid(near.x_m, near.y_m)
    cos_t = 0.3 / np.sqrt(xx**2 + yy**2 + 0.09)
    np.testing.assert_allclose(near.array, 3.0 * cos_t**4 / 0.09, rtol=1e-12)
    np.testing.assert_allclose(near.point, near.array, rtol=1e-12)
    assert near.largest_differences() == (0.0, 0.0)

    light = five_lobes()
    near = summarize(light).near
    assert near is not None and near.distance_m == 0.3 and near.array.shape == (121, 121)
    column = np.column_stack([np.full(121, near.x_m[60]), near.y_m, np.full(121, 0.3)])  # x = the centre's
    np.testing.assert_allclose(near.array[:, 60], light.irradiance(column, [0.0, 0.0, -1.0]), rtol=1e-12)
    of_peak, local = near.largest_differences()
    assert 0.05 < of_peak < 5.0 and of_peak <= local  # 4 mm apart at 30 cm: a small difference, but one


def test_the_options_take_the_extrapolation():
    assert ProcessingOptions().extrapolation is Extrapolation.FITTED
    assert ProcessingOptions.checked(extrapolation="none").extrapolation is Extrapolation.NONE
    with pytest.raises(OptionsError, match=r"^--extrapolation: 'zero' is not one of fitted, none$"):
        ProcessingOptions.checked(extrapolation="zero")
    assert JobRequest(extrapolation="none").options() == {"extrapolation": "none"}
    with pytest.raises(ValidationError, match="extrapolation"):
        JobRequest(extrapolation="zero")


# --------------------------------------------------------------------------- the files, read by photompy


def read(cls, path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return cls.read(path)


def keywords(path) -> dict[str, str]:
    return dict(re.findall(r"^\[(\w+)\] (.*?)\r?$", path.read_text(), flags=re.M))


@needs_photompy
def test_the_summary_agrees_with_photompy_on_the_written_ies(tmp_path):
    model = five_lobes()
    summary = summarize(model, near_field_m=None)
    path = write_ies(model, tmp_path / "light.ies")  # 1° × 5°: photompy agrees to 1e-4 (0.5°: 3e-5)
    ies = read(photompy.IESFile, path)
    photometry = ies.photometry
    # the table is scaled to a peak of 1000: lumens per lamp is our flux on that scale, photompy integrates the table
    scale = 1000.0 / summary.peak[0]
    assert ies.header.lumens_per_lamp == pytest.approx(scale * summary.total_flux, rel=1e-5)
    assert photometry.total_optical_power() == pytest.approx(scale * summary.total_flux, rel=5e-3)
    for kind, threshold in (("beam", 0.5), ("field", 0.1)):
        per_plane = photometry.get_beam_angle(threshold=threshold, num_points=4001).angles  # 2 × the half angle
        for right, left in (("C0", "C180"), ("C90", "C270")):
            theirs = 0.5 * (per_plane[float(right[1:])] + per_plane[float(left[1:])])
            ours = summary.angle(kind, f"{right}-{left}")
            assert ours == pytest.approx(theirs, rel=5e-3), (kind, right)
    assert summary.angle("field", "C0-C180") != pytest.approx(summary.angle("field", "C90-C270"), rel=0.01)
    words = keywords(path)
    assert words["_EXTRAPOLATION"] == "fitted" and words["_MEASURED_THETA_MAX"] == "42.3"
    assert words["_FLUX_BEYOND_MEASURED"] == f"{100 * summary.beyond_fraction:.1f} %"
    assert words["_BEAMANGLE_C0_C180"] == f"{summary.angle('beam', 'C0-C180'):.1f}"
    assert words["_FIELDANGLE_C90_C270"] == f"{summary.angle('field', 'C90-C270'):.1f}"
    assert "the table holds the fits' extrapolation" in ies.header.keywords["OTHER"]  # [MORE] lines joined


@needs_photompy
def test_the_measured_only_files_are_zero_beyond_and_say_so(tmp_path):
    model = five_lobes()
    ies_path = write_ies(model, tmp_path / "light.ies", extrapolation="none")
    ies = read(photompy.IESFile, ies_path)
    thetas, values = ies.photometry.thetas, ies.photometry.values
    assert np.all(values[:, thetas > 42.3] == 0) and np.all(values[:, thetas <= 42] > 0)
    words = keywords(ies_path)
    assert words["_EXTRAPOLATION"] == "none" and words["_FLUX_BEYOND_MEASURED"] == "0.0 %"
    assert "Measured range only" in ies.header.keywords["OTHER"]
    assert "values beyond are zero (measured range only)" in ies.header.keywords["FILEGENINFO"]
    measured = summarize(model, "none", near_field_m=None)
    assert ies.header.lumens_per_lamp == pytest.approx(1000 / measured.peak[0] * measured.total_flux, rel=1e-5)

    ldt_path = write_ldt(model, tmp_path / "light.ldt", extrapolation="none")
    ldt = read(photompy.LDTFile, ldt_path)
    assert np.all(ldt.photometry.values[:, ldt.photometry.thetas > 42.3] == 0)
    report_line = ldt_path.read_text().split("\n")[7].strip()
    assert re.fullmatch(
        r"to gamma 42\.3 deg, zero beyond, 1-sigma \d\.\d\d %; mirrorgonio run run-photometry", report_line
    )
    assert ldt.header.dff == 100 and ldt.header.lorl == 100
    fitted = read(photompy.LDTFile, write_ldt(model, tmp_path / "fitted.ldt"))
    assert np.all(fitted.photometry.values[:, (fitted.photometry.thetas > 45) & (fitted.photometry.thetas < 90)] > 0)


# --------------------------------------------------------------------------- the model's file and the report


def test_the_light_model_keeps_its_photometry_and_the_report_shows_it_first(tmp_path):
    model = five_lobes()
    model.photometry = summarize(model, "none").record()
    path = model.save(tmp_path / "light.json")
    again = LightModel.load(path)
    assert again.photometry == model.photometry
    assert again.photometry["near_field"]["distance_m"] == 0.3

    text = write_report(tmp_path / "report.html", again).read_text(encoding="utf-8")
    top = text.index("<h2>Photometry of the whole light</h2>")
    assert top == text.index("<h2>") and top < text.index("<h2>The light source, source by source</h2>")
    section = text[top : text.index("<h2>", top + 10)]
    measured = summarize(again, "none")
    assert f"<td>beam angle (50 % of peak), C0-C180</td><td>{measured.angle('beam', 'C0-C180'):.1f}°" in section
    assert "<td>flux beyond the measured γ</td><td>0.0 % (zero in the light files; the fits would put" in section
    assert 'alt="C-plane polar diagram and isocandela diagram"' in section and 'alt="illuminance at 30 cm"' in section
    assert "<th>zone γ</th>" in section and "<td>40–50°</td>" in section
    assert "could not be drawn" not in text


# --------------------------------------------------------------------------- the LDT's direct ratios


def _direct_ratio_by_brute_force(model: LightModel, k: float, lights: int = 12, floor: int = 150) -> float:
    """The share of the light's flux that falls directly on the floor of a square room of index k
    (height 1 above the work plane, side 2k), averaged over luminaires all over its ceiling (at
    lights × lights Gauss–Legendre nodes): for each, the illuminance I·cos³θ/h² summed over the
    centres of a floor × floor grid."""
    a = 2.0 * k
    cells = (np.arange(floor) + 0.5) * a / floor
    fx, fy = np.meshgrid(cells, cells, indexing="ij")
    nodes, weights = np.polynomial.legendre.leggauss(lights)
    at, weights = 0.5 * a * (nodes + 1.0), 0.5 * weights
    landed = 0.0
    for px, wx in zip(at, weights, strict=True):
        for py, wy in zip(at, weights, strict=True):
            dx, dy = fx - px, fy - py
            cos_t = 1.0 / np.sqrt(1.0 + dx * dx + dy * dy)
            on_floor = np.sum(model.far_field(np.arccos(cos_t), np.arctan2(dy, dx)) * cos_t**3) * (a / floor) ** 2
            landed += wx * wy * on_floor
    theta, phi = np.radians(np.linspace(0, 90, 721)), np.radians(np.linspace(0, 360, 145))
    grid = model.far_field(theta[:, None], phi[None, :]) * np.sin(theta)[:, None]
    flux = np.trapezoid(np.trapezoid(grid, phi, axis=1), theta)
    return float(landed / flux)


def test_the_ldt_direct_ratios_are_the_share_of_flux_on_a_rooms_floor(tmp_path):
    """EULUMDAT line 24, the direct ratios for the room indices 0.6 … 5, against a brute-force sum of
    the illuminance over a room's floor from luminaires all over its ceiling (within 0.1 %)."""
    model = five_lobes()
    lines = write_ldt(model, tmp_path / "light.ldt").read_bytes().decode("ascii").split("\r\n")
    ratios = [float(v) for v in lines[32:42]]
    assert lines[31] == "0" and float(lines[42]) == 0.0  # 26f (wattage) before, the first C angle after
    assert all(0 < r < 1 for r in ratios) and np.all(np.diff(ratios) > 0)
    for k, ratio in zip((0.6, 1.25, 5.0), (ratios[0], ratios[3], ratios[9]), strict=True):
        assert ratio == pytest.approx(_direct_ratio_by_brute_force(model, k), rel=1e-3), k  # measured: 1.3e-4
    assert summarize(model, near_field_m=None).record()["direct_ratios"]["ratio"] == pytest.approx(ratios, abs=5e-5)
    lambertian = [float(v) for v in write_ldt(cos_power(1.0), tmp_path / "l.ldt").read_text().split("\n")[32:42]]
    assert lambertian[0] < ratios[0] and lambertian[-1] < ratios[-1]  # a wide light loses more to the walls
