"""A point spread the lab measured (``[camera.measured_point_spread]``): read, checked and
centred before any work, and the plan made without the aperture fit it leaves nothing to.
Its templates against the simulator's frames: tests/test_fresnel_templates.py."""

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from acquisition.cli import app
from drivers.contracts.rig import load_rig
from processing.light_run.errors import ProcessingError
from processing.light_run.geometry import measured_point_spread
from processing.light_run.plan import plan_processing
from processing.options import ProcessingOptions
from processing.unmixing.measured import PointSpreadError, load_measured_point_spread

PITCH = 5.9e-6
DEMO_RIG = str(Path(__file__).parents[1] / "rigs" / "demo.toml")


def _spot(shift=(0.0, 0.0), side=41):
    y, x = np.mgrid[:side, :side] - side // 2
    return np.exp(-((x - shift[1]) ** 2 + (y - shift[0]) ** 2) / 8.0)


def _save(path, psf, distance=0.186, pitch=PITCH):
    np.savez(path, psf=psf, distance_m=distance, pixel_pitch_m=pitch)
    return path


def test_each_channel_is_centred_on_its_own_centroid_and_its_background_taken_off(tmp_path):
    """Three channels off the middle by different fractions of a pixel, on a background of 5:
    each kernel's centroid lands on the middle pixel to 0.01 px, and the background is gone."""
    shifts = [(0.3, -0.4), (-1.2, 0.25), (2.0, 0.0)]
    psf = np.stack([_spot(s) for s in shifts]) + 5.0
    kernels = load_measured_point_spread(_save(tmp_path / "psf.npz", psf), PITCH).kernels
    y, x = np.mgrid[:41, :41]
    for kernel in kernels:
        assert np.sum(kernel * y) / kernel.sum() == pytest.approx(20.0, abs=0.01)
        assert np.sum(kernel * x) / kernel.sum() == pytest.approx(20.0, abs=0.01)
        assert abs(kernel[:3].mean()) < 1e-4 * kernel.max()
    assert not kernels.flags.writeable


@pytest.mark.parametrize(
    ("write", "says"),
    [
        (lambda p: None, "measured point spread not found"),
        (lambda p: p.write_bytes(b"not a zip"), "camera.measured_point_spread.file: not a NumPy .npz"),
        (lambda p: np.savez(p, psf=np.ones((3, 41, 41)), distance_m=0.186), "pixel_pitch_m: missing"),
        (lambda p: _save(p, np.ones((41, 41))), "psf: shape (41, 41), expected (3, h, w)"),
        (lambda p: _save(p, np.ones((3, 41, 41)), pitch=11.8e-6), "pixel_pitch_m: 1.18e-05 m, but the rig's"),
        (lambda p: _save(p, np.ones((3, 41, 41)), distance=-1.0), "distance_m: must be one positive number"),
        (lambda p: _save(p, np.full((3, 41, 41), np.nan)), "psf: holds values that are not finite"),
        (lambda p: _save(p, np.ones((3, 41, 41))), "psf: channel R holds no light above its border's level"),
    ],
)
def test_a_point_spread_that_cannot_be_used_is_refused_in_one_line_naming_the_file(tmp_path, write, says):
    path = tmp_path / "psf.npz"
    write(path)
    with pytest.raises(PointSpreadError) as raised:
        load_measured_point_spread(path, PITCH)
    message = str(raised.value)
    assert str(path) in message and says in message and "\n" not in message


def test_the_rig_names_the_file_against_its_own_folder(tmp_path):
    """A relative ``file`` is found beside the rig file, so the rig stored in a run still finds
    it; the kernels are read once per file version."""
    _save(tmp_path / "psf.npz", np.stack([_spot()] * 3))
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text('[camera.measured_point_spread]\nfile = "psf.npz"\n')
    rig = load_rig(rig_file)
    assert rig.camera.measured_point_spread.file == str(tmp_path / "psf.npz")
    first = measured_point_spread(rig)
    assert first is measured_point_spread(rig) and first.distance_m == 0.186
    assert measured_point_spread(load_rig()) is None


def test_a_measured_point_spread_leaves_no_aperture_to_fit():
    """Where the sources are searched for and the rig held, the aperture is fitted alone; with a
    measured point spread no aperture changes the templates, so it is not, and asking for it
    always is refused in one line."""
    options = ProcessingOptions.checked(steps="hdr,sources", calibrate_rig="never")
    assert plan_processing(options).long_sweep.fit_aperture
    assert not plan_processing(options, point_spread_measured=True).long_sweep.fit_aperture
    always = ProcessingOptions.checked(steps="hdr,sources", calibrate_rig="never", fit_aperture="always")
    with pytest.raises(ProcessingError, match=r"^--fit-aperture always: the rig's camera has a measured point spread"):
        plan_processing(always, point_spread_measured=True)


def test_simulate_point_spread_writes_what_the_processing_reads(tmp_path):
    """``mirrorgonio simulate point-spread`` images an LED through the demo rig's pinhole as a
    lab would: the file loads, each channel peaked in the middle, red the widest (its longer
    wavelength spreads it most)."""
    out = tmp_path / "psf.npz"
    command = ["simulate", "point-spread", "-o", str(out), "--distance", "0.1856", "--side", "65", "--rig", DEMO_RIG]
    result = CliRunner().invoke(app, command)
    assert result.exit_code == 0, result.output
    assert "wrote" in result.output and "65x65 px a channel" in result.output
    kernels = load_measured_point_spread(out, 2 * PITCH).kernels
    assert kernels.shape == (3, 65, 65)
    assert all(np.unravel_index(np.argmax(k), k.shape) == (32, 32) for k in kernels)
    peaks = kernels.max(axis=(1, 2))
    assert peaks[0] < peaks[1] < peaks[2]
