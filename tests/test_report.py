"""processing.report: one self-contained HTML file with real embedded figures, the header's
facts, the truth when given, notes instead of failures when inputs are missing, and the
report the pipeline writes after the light model."""

from __future__ import annotations

import base64
import html
import math
import re

import cv2
import numpy as np
import pytest

from processing.fit import Samples, fit_intensity
from processing.lightmodel import LightModel, SourceModel, samples_table
from processing.options import ProcessingOptions
from processing.photometry import summarize
from processing.report.figures import polar_figure
from processing.report.page import write_report
from processing.report.sections import NO_CALIBRATION

IMG = re.compile(r'<img src="data:image/png;base64,([A-Za-z0-9+/=]+)"')
# Three sources as a sweep past the ball sees them: θ from 3° to 40° on both sides of the axis.
SOURCES = (("centre", (0.0, 0.0), 1.0, 20.0), ("+u", (0.004, 0.0), 0.8, 25.0), ("-v", (0.0, -0.004), 0.6, 30.0))
RESOLUTION_M = 0.0131


def truth(source, theta):
    """The sources' true intensity, looked up by index or by name (as a simulation's caller would)."""
    index = source if isinstance(source, int) else [s[0] for s in SOURCES].index(source)
    _, _, peak, width = SOURCES[index]
    return peak * np.exp(-(np.asarray(theta) ** 2) / (2.0 * math.radians(width) ** 2))


def make_model(with_cell_sums=True, units="W/sr") -> LightModel:
    rng = np.random.default_rng(7)
    signed = np.radians(np.concatenate([np.linspace(40.0, 3.0, 12), -np.linspace(3.0, 40.0, 12)]))
    theta, phi = np.abs(signed), np.where(signed >= 0, 0.0, math.pi)
    sources = []
    for k, (name, centre, _, _) in enumerate(SOURCES):
        true = truth(k, theta)
        sigma = 0.01 * true.max() + 0.01 * true
        data = Samples(theta, phi, true + rng.normal(0.0, sigma), sigma, name)
        cell = 0.12 * true if with_cell_sums else None
        table = samples_table(data, np.arange(len(theta)) * 3, cell)
        sources.append(SourceModel(name, centre, 0.5e-3, fit_intensity(data, "gaussian"), table))
    provenance = {
        "run_id": "run-hand-made",
        "rig": "default",
        "method": "templates",
        "fit": "gaussian",
        "spatial_resolution_m": RESOLUTION_M,
        "software_version": "test",
    }
    return LightModel(sources, units=units, provenance=provenance)


def images(text: str) -> list[bytes]:
    return [base64.b64decode(data) for data in IMG.findall(text)]


def decode(png: bytes) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert image is not None, "not a PNG OpenCV can read"
    return image


def test_the_report_is_one_file_with_real_embedded_figures(tmp_path):
    model = make_model()
    path = write_report(tmp_path / "out" / "run.report.html", model, truth=truth)
    assert path == tmp_path / "out" / "run.report.html"
    assert sorted(p.name for p in path.parent.iterdir()) == ["run.report.html"]  # nothing beside it
    text = path.read_text(encoding="utf-8")
    assert text.startswith("<!DOCTYPE html>") and text.rstrip().endswith("</html>")
    # no external asset: every image is inline, no stylesheet or script is fetched
    assert not re.search(r'(src|href)="(?!data:)', text)
    pngs = images(text)
    assert len(pngs) == text.count("<img ") >= 4  # polar, layout, coverage, residuals at least
    for png in pngs:
        image = decode(png)
        assert image.shape[0] > 100 and image.shape[1] > 100
        assert image.std() > 5  # drawn on, not a blank canvas
    # the header's facts
    for source in model.sources:
        assert source.name in text
    assert "W/sr" in text
    assert "spatial resolution on the light plane" in text and f"{1e3 * RESOLUTION_M:.2f} mm" in text
    assert "templates" in text and "run-hand-made" in text
    # the truth: a column of errors against it, each small for these fits
    assert "error vs truth" in text
    summary = text.split("error vs truth", 1)[1].split("</table>", 1)[0]
    errors = [float(e) for e in re.findall(r"<td>([0-9.]+) %</td>", summary)]
    assert len(errors) == len(SOURCES) and max(errors) < 2.0, errors
    assert "could not be drawn" not in text


def test_without_run_samples_or_report_it_renders_with_notes(tmp_path):
    text = write_report(tmp_path / "r.html", make_model(with_cell_sums=False, units="relative")).read_text()
    assert "relative (not calibrated" in text
    assert "error vs truth" not in text and "truth" not in text.lower()
    assert NO_CALIBRATION in text
    assert "no run file given to the report" in text  # the chief-ray figure is skipped with a note
    assert "no HDR previews found" in text
    assert "noise model" in text and "not given to the report" in text
    assert "could not be drawn" not in text
    assert len(images(text)) == 2 + 5  # the whole light's diagrams and illuminance, then the sources' figures
    assert "1σ band on I per source" in text


def test_a_model_read_back_from_its_file_reports_the_same(tmp_path):
    model = make_model()
    loaded = LightModel.load(model.save(tmp_path / "m.light.json"))
    text = write_report(tmp_path / "r.html", loaded).read_text()
    assert all(s.name in text for s in model.sources) and "could not be drawn" not in text


def test_the_polar_figure_draws_samples_fit_cell_sums_and_truth(tmp_path):
    model = make_model()
    fig = polar_figure(model, truth=truth)
    # one half disc per source, drawn on a Cartesian axes: a point (θ, I) at (I sin θ, I cos θ) / top of the scale
    axes = fig.axes
    assert len(axes) == len(SOURCES)
    for ax, source in zip(axes, model.sources, strict=False):
        labels = [line.get_label() for line in ax.get_lines()]
        assert {"fit (θ covered)", "fit, extrapolated", "truth", "chief-ray cell sums", "samples ± 1σ"} <= set(labels)
        (truth_line,) = [line for line in ax.get_lines() if line.get_label() == "truth"]
        assert truth_line.get_linestyle() != "-"  # a broken line
        # θ runs from −90° (left) to 90° (right), 0° up
        marks = {t.get_text(): t.get_position() for t in ax.texts if t.get_text().endswith("°")}
        assert marks["-90°"][0] < -1 + 1e-6 and marks["90°"][0] > 1 - 1e-6 and marks["0°"][1] > 1
        assert abs(marks["0°"][0]) < 1e-9
        # the radius is the intensity (on one scale per panel)
        (dots,) = [line for line in ax.get_lines() if line.get_marker() == "o"]
        radius = np.hypot(dots.get_xdata(), dots.get_ydata())
        intensity = np.asarray(source.samples["intensity"])
        np.testing.assert_allclose(radius / intensity, radius[0] / intensity[0], rtol=1e-9)
    # the samples sit on both sides: a sweep past the ball, signed by azimuth
    theta = np.concatenate(
        [
            np.arctan2(line.get_xdata(), line.get_ydata())
            for ax in axes
            for line in ax.get_lines()
            if line.get_marker() == "o"
        ]
    )
    assert theta.min() < math.radians(-30) and theta.max() > math.radians(30)
    out = tmp_path / "polar.png"
    fig.savefig(out, dpi=100)
    assert decode(out.read_bytes()).shape[1] >= 1000
    without = polar_figure(model)
    assert all("truth" not in [line.get_label() for line in ax.get_lines()] for ax in without.axes)


def test_a_truth_that_only_knows_names_is_asked_by_name(tmp_path):
    names = {s[0]: k for k, s in enumerate(SOURCES)}

    def by_name(source, theta):
        return truth(names[source], theta)  # KeyError for an index

    text = write_report(tmp_path / "r.html", make_model(), truth=by_name).read_text()
    assert "no truth for this source" not in text and "error vs truth" in text


def test_a_calibration_result_is_shown(tmp_path):
    comparison = {
        "measured_mm": [0.1, -0.2, 0.05],
        "described_mm": [0.0, 0.0, 0.0],
        "discrepancy_mm": [0.1, -0.2, 0.05],
        "sigma_mm": [0.01, 0.01, 0.03],
        "distance_mm": 0.229,
        "significance": 12.0,
    }
    text = write_report(tmp_path / "r.html", make_model(), calibration=comparison).read_text()
    assert NO_CALIBRATION not in text
    assert "0.229 mm from where the rig description puts it" in text and "12.0 σ" in text


# --- with a run file: the rig's geometry, and the pipeline's report -------------------------------------
@pytest.fixture(scope="module")
def processed(tmp_path_factory):
    """A short simulated sweep of the reduced rig through hdr and sources, with the truth."""
    from conftest import REDUCED_RIG

    from drivers.contracts.rig import load_rig
    from drivers.contracts.runfile import PositionTimes, RunFileWriter, RunHeader
    from processing.light_run.run import process_run
    from sim_devices.camera import SimulatedCamera
    from sim_devices.lights import LIGHTS_DIR, load_truth
    from sim_devices.world import SimWorld

    folder = tmp_path_factory.mktemp("report-run")
    rig = load_rig(REDUCED_RIG)
    tools = rig.tool_poses()
    here = {"pose": tools[0]}
    light = load_truth("five-gaussians")
    camera = SimulatedCamera(rig, SimWorld(lambda: here["pose"]), folder / "spool", truth=light, seed=5)
    exposures = [1e-4, 1e-3, 1e-2]
    header = RunHeader(
        run_id="run-report",
        rig=rig,
        tool_poses=tools,
        light_poses=rig.light_poses(),
        max_exposures=len(exposures),
        frame_shape=(rig.camera.height, rig.camera.width),
        bracket={"mode": "fixed", "exposures_s": exposures},
        metadata={},
        devices={},
        software_version="test",
        created_utc="2026-11-21T00:00:00+00:00",
    )
    path = folder / "run-report.h5"
    with RunFileWriter.create(path, header) as writer:
        for index in range(1, len(tools), 8):
            here["pose"] = tools[index]
            writer.write_position(
                index, tools[index], PositionTimes(0.0, 0.0, 0.0), [camera.capture(t) for t in exposures]
            )
        writer.set_status("complete")
    report = process_run(
        path,
        folder / "out",
        ProcessingOptions.checked(
            steps=("hdr", "sources"), layout=LIGHTS_DIR / "five-gaussians.toml", noise="rig", units="W/sr"
        ),
        truth=lambda k, theta: light.emitters[k].intensity_w_sr(theta),
    )
    return path, report


def test_the_pipeline_writes_the_report_after_the_light_model(processed):
    path, report = processed
    (html_path,) = report.outputs["report"]
    assert html_path.name == "run-report.report.html" and html_path.parent == report.light_model.parent
    text = html_path.read_text(encoding="utf-8")
    assert "could not be drawn" not in text
    for name in ("centre", "+u", "-u", "+v", "-v"):
        assert f"<td>{name}</td>" in text
    assert report.estimator in text and html.escape(report.estimator_reason) in text
    assert f"{1e3 * report.spatial_resolution_m:.2f} mm" in text
    assert f"read noise {report.noise.read_noise_dn:.4g} DN" in text
    assert "error vs truth" in text and "no truth for this source" not in text
    assert NO_CALIBRATION in text and "What 1 mm of error in the ball's position costs" in text
    assert "Each dot is the chief ray of one pixel on the ball" in text
    assert "one pixel gathers light from" in text
    pngs = images(text)
    previews = re.findall(r'alt="position (\d+)"', text)
    assert 1 < len(previews) <= 6
    # the whole light's diagrams and illuminance; polar, layout, coverage, angles, residuals, the
    # 1σ band; the strip; and the colour over θ where it varies
    varies = any(s.chromaticity["over_theta"]["varies"] for s in report.model.sources)
    assert len(pngs) == 2 + 6 + len(previews) + varies
    for png in pngs:
        decode(png)


def test_the_pipeline_writes_the_photometry_in_the_model_the_files_and_first_in_the_report(processed):
    _, report = processed
    model = LightModel.load(report.light_model)
    photometry = model.photometry
    assert photometry["extrapolation"] == "fitted" and photometry["intensity_units"] == "W/sr"
    assert photometry == summarize(model).record()  # the figures of the light the file holds
    assert 0 < photometry["flux_beyond_measured_percent"] < 100
    text = report.outputs["ies"][0].read_text()
    assert f"[_BEAMANGLE_C0_C180] {photometry['beam_angle_deg']['C0-C180']:.1f}\n" in text
    assert f"[_MEASURED_THETA_MAX] {photometry['measured_theta_max_deg']:.1f}\n" in text
    assert "[_EXTRAPOLATION] fitted\n" in text
    page = report.outputs["report"][0].read_text(encoding="utf-8")
    top = page.index("<h2>Photometry of the whole light</h2>")
    assert top < page.index("<h2>The light source, source by source</h2>")
    assert f"{photometry['field_angle_deg']['C90-C270']:.1f}°" in page[top : page.index("<h2>", top + 10)]
