"""Raw decoding, the DNG writer, the folder camera and the gphoto2 camera.

Every DNG here is written by :func:`sim_devices.dng.write_dng` and read back through the
same :func:`drivers.raw_decode.decode_raw` that reads a real camera's NEF or CR2.
"""

from __future__ import annotations

import struct
import sys
import threading
import time
import types
import zlib
from pathlib import Path

import numpy as np
import pytest

from drivers.errors import DeviceError, DeviceTimeoutError, RawFileError
from drivers.folder_camera import FolderCamera
from drivers.gphoto2_camera import Gphoto2Camera, nearest_shutter_choice, parse_shutter_speed
from drivers.raw_decode import RAW_EXTENSIONS, decode_raw
from sim_devices.dng import write_dng

PER_SITE_BLACK = np.array([[60, 61], [62, 63]])


def random_mosaic(shape, bits, seed=0):
    return np.random.default_rng(seed).integers(0, 1 << bits, size=shape, dtype=np.uint16)


def assert_one_line_naming(error: Exception, path: Path) -> None:
    message = str(error)
    assert str(path) in message
    assert "\n" not in message


# -- decode_raw on DNGs written by write_dng --------------------------------------------


@pytest.mark.parametrize(
    ("pattern", "shape", "bits", "exposure_s"),
    [
        ("RGGB", (48, 64), 12, 1 / 250),
        ("BGGR", (23, 37), 12, 0.0123),  # odd sizes: 12-bit rows end mid-byte
        ("GRBG", (45, 61), 16, 2.5),
        ("GBRG", (22, 22), 16, 1 / 8000),  # LibRaw's smallest image
    ],
)
def test_dng_decodes_to_exactly_what_was_written(tmp_path, pattern, shape, bits, exposure_s):
    mosaic = random_mosaic(shape, bits, seed=len(pattern) + shape[0])
    white = (1 << bits) - 1
    taken_at = 1_700_000_000.25
    path = write_dng(
        tmp_path / "frame.dng",
        mosaic,
        cfa_pattern=pattern,
        black_level=PER_SITE_BLACK,
        white_level=white,
        bits_per_sample=bits,
        exposure_s=exposure_s,
        timestamp=taken_at,
    )

    frame = decode_raw(path)

    assert frame.mosaic.dtype == np.uint16
    np.testing.assert_array_equal(frame.mosaic, mosaic)
    assert frame.cfa_pattern == pattern
    np.testing.assert_array_equal(frame.black_level, PER_SITE_BLACK)
    assert frame.white_level == white
    assert frame.exposure_s == exposure_s  # the exact rational, not a float32
    assert frame.extra["exposure_source"].startswith("ExposureTime")
    assert frame.timestamp == pytest.approx(taken_at, abs=1e-3)
    assert frame.camera_id == "mirrorgonio simulated pinhole camera, serial SIM-0001"
    assert frame.source == str(path)


def test_scalar_black_level_and_camera_identity(tmp_path):
    mosaic = random_mosaic((30, 40), 12, seed=7)
    path = write_dng(
        tmp_path / "id.dng",
        mosaic,
        black_level=64,
        exposure_s=0.01,
        camera_make="Acme",
        camera_model="Acme Lab 1",
        serial="42",
    )
    frame = decode_raw(path)
    np.testing.assert_array_equal(frame.black_level, np.full((2, 2), 64.0))
    assert frame.camera_id == "Acme Lab 1, serial 42"  # the make is not repeated
    assert frame.extra["make"] == "Acme" and frame.extra["serial"] == "42"


def test_write_dng_refuses_what_a_dng_cannot_hold(tmp_path):
    with pytest.raises(ValueError, match="12 bits"):
        write_dng(tmp_path / "a.dng", np.full((24, 24), 4096, np.uint16), exposure_s=1)
    with pytest.raises(ValueError, match="smaller"):
        write_dng(tmp_path / "a.dng", np.zeros((8, 8), np.uint16), exposure_s=1)
    with pytest.raises(ValueError, match="cfa_pattern"):
        write_dng(
            tmp_path / "a.dng",
            np.zeros((24, 24), np.uint16),
            cfa_pattern="RGBG",
            exposure_s=1,
        )
    assert list(tmp_path.iterdir()) == []  # nothing half-written left behind


# -- decode_raw failures ----------------------------------------------------------------


def test_missing_file_is_a_raw_file_error(tmp_path):
    path = tmp_path / "nowhere.nef"
    with pytest.raises(RawFileError, match="no such file") as caught:
        decode_raw(path)
    assert_one_line_naming(caught.value, path)


def png_bytes(width=32, height=32):
    rows = b"".join(b"\x00" + bytes(range(width * 3)) for _ in range(height))
    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)

    def chunk(kind, data):
        checksum = struct.pack(">I", zlib.crc32(kind + data))
        return struct.pack(">I", len(data)) + kind + data + checksum

    body = chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b"")
    return b"\x89PNG\r\n\x1a\n" + body


@pytest.mark.parametrize(
    ("name", "content"),
    [("picture.png", png_bytes()), ("notes.dng", b"this is not a raw file\n" * 40)],
)
def test_non_raw_file_is_a_raw_file_error(tmp_path, name, content):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(RawFileError) as caught:
        decode_raw(path)
    assert_one_line_naming(caught.value, path)


def test_truncated_dng_is_a_raw_file_error(tmp_path):
    path = write_dng(tmp_path / "cut.dng", random_mosaic((40, 60), 12), exposure_s=0.02)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(RawFileError, match="truncated") as caught:
        decode_raw(path)
    assert_one_line_naming(caught.value, path)


def test_file_without_exposure_time_is_refused_not_assumed(tmp_path):
    path = write_dng(tmp_path / "noexp.dng", random_mosaic((30, 30), 12), exposure_s=0.02)
    data = path.read_bytes()
    # Renumber the ExposureTime entry (tag 33434, RATIONAL, count 1) to an unknown tag.
    entry = struct.pack("<HHI", 33434, 5, 1)
    assert data.count(entry) == 1
    path.write_bytes(data.replace(entry, struct.pack("<HHI", 33435, 5, 1)))
    with pytest.raises(RawFileError, match="no exposure time in the file's metadata") as caught:
        decode_raw(path)
    assert_one_line_naming(caught.value, path)
    # Given from elsewhere (an import CSV), the exposure is the frame's, and says so.
    frame = decode_raw(path, exposure_s=0.03)
    assert frame.exposure_s == 0.03 and frame.extra["exposure_source"] == "given"
    assert "file_exposure_s" not in frame.extra


def test_a_given_exposure_time_wins_over_the_files(tmp_path):
    path = write_dng(tmp_path / "exp.dng", random_mosaic((30, 30), 12), exposure_s=0.02)
    frame = decode_raw(path, exposure_s=0.05)
    assert frame.exposure_s == 0.05 and frame.extra["exposure_source"] == "given"
    assert frame.extra["file_exposure_s"] == 0.02
    assert decode_raw(path).exposure_s == 0.02
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="exposure_s must be a positive number of seconds"):
            decode_raw(path, exposure_s=bad)


# -- FolderCamera ---------------------------------------------------------------------


def test_folder_camera_returns_the_new_raw_file_once_it_settles(tmp_path, monkeypatch):
    folder = tmp_path / "tether"
    folder.mkdir()
    staging = tmp_path / "staging"
    staging.mkdir()
    old = random_mosaic((24, 24), 12, seed=1)
    write_dng(folder / "IMG_0001.dng", old, exposure_s=1 / 60)  # a previous shot
    new = random_mosaic((33, 47), 12, seed=2)
    # The "camera" rounds the requested exposure to its 1/250 step; the file says so.
    dng_bytes = write_dng(staging / "x.dng", new, exposure_s=1 / 250).read_bytes()
    settle_s = 0.3
    written = {}

    def tethering_software(exposure_s):
        def shoot():
            time.sleep(0.05)
            (folder / "IMG_0002.JPG").write_bytes(b"\xff\xd8\xff\xe0 not a raw file")
            with open(folder / "IMG_0002.DNG", "wb") as file:  # two steps, as over USB
                file.write(dng_bytes[: len(dng_bytes) // 2])
                file.flush()
                time.sleep(settle_s / 2)
                file.write(dng_bytes[len(dng_bytes) // 2 :])
            written["at"] = time.monotonic()

        written["requested"] = exposure_s
        written["thread"] = threading.Thread(target=shoot)
        written["thread"].start()

    decoded = []
    import drivers.folder_camera as folder_camera_module

    def counting_decode(path, camera_id=None):
        decoded.append(Path(path).name)
        return decode_raw(path, camera_id)

    monkeypatch.setattr(folder_camera_module, "decode_raw", counting_decode)
    camera = FolderCamera(folder, trigger=tethering_software, timeout_s=5, settle_s=settle_s, poll_s=0.02)
    camera.connect()
    frame = camera.capture(0.0041)
    returned_at = time.monotonic()
    written["thread"].join()

    assert written["requested"] == 0.0041
    np.testing.assert_array_equal(frame.mosaic, new)
    assert frame.exposure_s == 0.004  # from the file, not the request
    assert frame.extra["requested_exposure_s"] == 0.0041
    assert Path(frame.source).name == "IMG_0002.DNG"
    assert decoded == ["IMG_0002.DNG"]  # never the half file, the old one or the JPEG
    assert returned_at - written["at"] >= settle_s - 0.05
    assert camera.identity == frame.camera_id


def test_folder_camera_times_out_naming_the_folder(tmp_path):
    def jpeg_only(exposure_s):
        (tmp_path / "IMG_0003.JPG").write_bytes(b"\xff\xd8")

    camera = FolderCamera(tmp_path, trigger=jpeg_only, timeout_s=0.3, settle_s=0.05, poll_s=0.02)
    started = time.monotonic()
    with pytest.raises(DeviceTimeoutError) as caught:
        camera.capture(0.01)
    assert time.monotonic() - started < 2
    message = str(caught.value)
    assert str(tmp_path) in message and "IMG_0003.JPG" in message and "\n" not in message


def test_folder_camera_reports_a_failing_trigger_and_a_missing_folder(tmp_path):
    def broken(exposure_s):
        raise OSError("remote shutter not reachable")

    camera = FolderCamera(tmp_path, trigger=broken, timeout_s=0.1)
    with pytest.raises(DeviceError, match="trigger failed: OSError: remote shutter"):
        camera.capture(0.01)
    with pytest.raises(DeviceError, match="is not a folder"):
        FolderCamera(tmp_path / "absent").connect()


# -- shutter speeds ---------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "seconds"),
    [
        ("1/250", 0.004),
        ("1/8000", 1 / 8000),
        ("0.5", 0.5),
        ("2", 2.0),
        ("30", 30.0),
        ('1"3', 1.3),
        ('30"', 30.0),
        ("2s", 2.0),
        ("1/60 s", 1 / 60),
        ("0,8", 0.8),
        ("bulb", None),
        ("Bulb", None),
        ("Time", None),
        ("auto", None),
        ("x 1/200", None),
        ("", None),
        ("0", None),
    ],
)
def test_parse_shutter_speed(text, seconds):
    assert parse_shutter_speed(text) == (pytest.approx(seconds) if seconds else None)


CANON_CHOICES = ["bulb", '30"', '1"3', "1", "0.8", "1/4", "1/125", "1/250", "1/500"]


@pytest.mark.parametrize(
    ("exposure_s", "choice"),
    [
        (1 / 300, "1/250"),  # nearest in stops
        (1 / 400, "1/500"),
        (1.2, '1"3'),
        (100.0, '30"'),  # beyond the range: the longest timed speed, never bulb
        (1e-5, "1/500"),
        (0.004, "1/250"),
    ],
)
def test_nearest_shutter_choice(exposure_s, choice):
    assert nearest_shutter_choice(CANON_CHOICES, exposure_s) == choice


def test_nearest_shutter_choice_ties_and_errors():
    assert nearest_shutter_choice(["2", "1/2"], 1.0) == "1/2"  # the shorter, on a tie
    with pytest.raises(ValueError, match="no timed shutter speed"):
        nearest_shutter_choice(["bulb", "auto"], 0.01)
    with pytest.raises(ValueError, match="positive"):
        nearest_shutter_choice(CANON_CHOICES, 0)


# -- Gphoto2Camera ----------------------------------------------------------------------


def test_gphoto2_camera_says_how_to_install_python_gphoto2(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "gphoto2", None)  # makes `import gphoto2` fail
    camera = Gphoto2Camera(download_dir=tmp_path)
    with pytest.raises(DeviceError, match=r"python-gphoto2 is not installed \(pip install"):
        camera.connect()


def fake_gphoto2(staging: Path, *, busy_captures: int, shoots_raw=True) -> types.ModuleType:
    """The part of python-gphoto2's API the driver uses, over a camera shooting RAW+JPEG.

    The capture returns the JPEG and announces the raw file as an event, as Nikon and
    Canon bodies do; the first ``busy_captures`` captures answer GP_ERROR_CAMERA_BUSY.
    Without ``shoots_raw`` it is set to JPEG only.
    """
    gp = types.ModuleType("gphoto2")
    DCIM = "/store_00010001/DCIM/100NIKON"  # noqa: N806 - a constant of this fake
    gp.GP_ERROR_CAMERA_BUSY, gp.GP_ERROR_NOT_SUPPORTED, gp.GP_ERROR_MODEL_NOT_FOUND = -110, -6, -105
    gp.GP_ERROR_IO, gp.GP_ERROR_IO_USB_CLAIM, gp.GP_ERROR_TIMEOUT = -7, -53, -10
    gp.GP_EVENT_TIMEOUT, gp.GP_EVENT_FILE_ADDED, gp.GP_EVENT_CAPTURE_COMPLETE = 1, 2, 4
    gp.GP_CAPTURE_IMAGE, gp.GP_FILE_TYPE_NORMAL = 0, 1

    class GPhoto2Error(Exception):
        def __init__(self, code, string):
            super().__init__(f"[{code}] {string}")
            self.code, self.string = code, string

    class CameraFilePath:
        def __init__(self, folder, name):
            self.folder, self.name = folder, name

    class Widget:
        choices = ["bulb", '30"', "1", "1/125", "1/250", "1/500"]

        def __init__(self):
            self.value = "1/125"

        def get_choices(self):
            return iter(self.choices)

        def get_value(self):
            return self.value

        def set_value(self, value):
            self.value = value

        def get_readonly(self):
            return 0

    class Camera:
        def __init__(self):
            self.shutter = "1/125"
            self.busy_left = busy_captures
            self.events = []
            self.card = {}
            self.shots = 0

        def init(self):
            pass

        def exit(self):
            pass

        def get_abilities(self):
            return types.SimpleNamespace(model="Fake DSLR")

        def get_summary(self):
            return "Manufacturer: Fake\nModel: DSLR\n  Serial Number: 000123\n"

        def get_config(self):
            config = types.SimpleNamespace(widget=Widget())
            config.widget.value = self.shutter
            config.get_child_by_name = lambda name: config.widget
            return config

        def set_single_config(self, name, widget):
            self.shutter = widget.get_value()

        def capture(self, kind):
            if self.busy_left:
                self.busy_left -= 1
                raise GPhoto2Error(gp.GP_ERROR_CAMERA_BUSY, "I/O in progress")
            self.shots += 1
            stem = f"DSC_{self.shots:04d}"
            exposure = parse_shutter_speed(self.shutter)
            mosaic = random_mosaic((26, 30), 12, seed=self.shots)
            raw = write_dng(staging / f"{stem}.dng", mosaic, exposure_s=exposure)
            self.card[f"{stem}.NEF"] = raw.read_bytes()
            self.card[f"{stem}.JPG"] = b"\xff\xd8 jpeg"
            self.events = [
                (gp.GP_EVENT_TIMEOUT, None),  # still writing the card
                (gp.GP_EVENT_FILE_ADDED, CameraFilePath(DCIM, f"{stem}.NEF")),
                (gp.GP_EVENT_CAPTURE_COMPLETE, None),
            ][: 3 if shoots_raw else 1]
            return CameraFilePath(DCIM, f"{stem}.JPG")

        def wait_for_event(self, timeout_ms):
            return self.events.pop(0) if self.events else (gp.GP_EVENT_TIMEOUT, None)

        def file_get(self, folder, name, kind):
            data = self.card[name]
            return types.SimpleNamespace(save=lambda target: Path(target).write_bytes(data))

    gp.GPhoto2Error, gp.CameraFilePath, gp.Camera = GPhoto2Error, CameraFilePath, Camera
    return gp


def test_gphoto2_capture_sets_shutter_retries_busy_keeps_raw_of_raw_jpeg(tmp_path, monkeypatch):
    staging = tmp_path / "staging"
    staging.mkdir()
    monkeypatch.setitem(sys.modules, "gphoto2", fake_gphoto2(staging, busy_captures=2))
    pauses = []
    downloads = tmp_path / "downloads"
    with Gphoto2Camera(download_dir=downloads, busy_wait_s=0.5, sleep=pauses.append) as camera:
        assert camera.identity == "Fake DSLR, serial 000123"
        frame = camera.capture(1 / 300)
        again = camera.capture(1 / 300)

    assert pauses == [0.5, 0.5]  # two busy answers, retried
    assert frame.exposure_s == 0.004  # the camera's 1/250 step, read from the raw file
    assert frame.extra["shutterspeed_choice"] == "1/250"
    assert frame.extra["requested_exposure_s"] == 1 / 300
    assert Path(frame.source).name == "DSC_0001.NEF"
    assert [Path(p).name for p in frame.extra["companion_files"]] == ["DSC_0001.JPG"]
    assert Path(again.source).name == "DSC_0002.NEF"
    assert sorted(p.name for p in downloads.iterdir()) == [
        "DSC_0001.JPG",
        "DSC_0001.NEF",
        "DSC_0002.JPG",
        "DSC_0002.NEF",
    ]
    np.testing.assert_array_equal(frame.mosaic, random_mosaic((26, 30), 12, seed=1))


def test_gphoto2_capture_without_raw_file_says_to_set_raw_quality(tmp_path, monkeypatch):
    jpeg_only = fake_gphoto2(tmp_path, busy_captures=0, shoots_raw=False)
    monkeypatch.setitem(sys.modules, "gphoto2", jpeg_only)
    with Gphoto2Camera(download_dir=tmp_path / "downloads", event_timeout_s=0.05) as camera:
        with pytest.raises(DeviceTimeoutError, match="set the camera's quality to RAW"):
            camera.capture(0.01)


@pytest.mark.hardware_camera
def test_real_gphoto2_camera_captures_a_raw_frame(tmp_path):
    gp = pytest.importorskip("gphoto2", reason="python-gphoto2 is not installed")
    try:
        detected = gp.Camera.autodetect()
    except gp.GPhoto2Error as exc:
        pytest.skip(f"gphoto2 cannot look for cameras: {exc}")
    if detected.count() == 0:
        pytest.skip("no camera detected by gphoto2")

    with Gphoto2Camera(download_dir=tmp_path) as camera:
        frame = camera.capture(1 / 100)

    assert frame.mosaic.ndim == 2 and frame.mosaic.dtype == np.uint16
    assert frame.cfa_pattern in {"RGGB", "BGGR", "GRBG", "GBRG"}
    # The nearest shutter step of any camera is within a third of a stop or so.
    assert 1 / 200 < frame.exposure_s < 1 / 50
    assert Path(frame.source).suffix.lower() in RAW_EXTENSIONS


# -- the simulated camera and the lights of the simulated world --------------------------
def test_the_simulated_camera_renders_the_light_only_when_on_and_the_room_only_when_lit(tmp_path):
    from conftest import rig_with

    from drivers.light import AMBIENT, DARK, SWEEP, Lighting
    from sim_devices.camera import ROOM_RADIANCE, SimulatedCamera
    from sim_devices.world import SimulatedLightSwitch, SimWorld

    rig = rig_with(camera__width=250, camera__height=164, camera__pixel_pitch_m=47.2e-6)
    pose = rig.tool_poses()[33]  # the light faces the camera
    world = SimWorld(lambda: pose, rig.light.light_to_tool.to_pose(), light_on=True, room_lit=False)
    camera = SimulatedCamera(rig, world, tmp_path, seed=1, diffraction=False, environment_radiance=ROOM_RADIANCE)
    switch = SimulatedLightSwitch(world)
    assert switch.state == SWEEP  # as the world was built
    rates = {}
    for lighting in (SWEEP, AMBIENT, DARK, Lighting(light_on=True, room_lit=True)):
        switch.set(lighting)
        assert (world.light_on, world.room_lit) == (lighting.light_on, lighting.room_lit)
        rates[lighting] = camera.rendering().rate
    sweep, ambient, dark, both = rates.values()
    assert not dark.any()  # nothing lit: a dark frame is the bias and the read noise
    # The sweep: the emitters' reflection, a few pixels; the room: the whole ball, at the
    # Fresnel reflectance of chrome (about 0.55 head-on) times the sensitivity and the radiance.
    assert 0 < np.count_nonzero(sweep.sum(axis=0)) < 0.02 * sweep[0].size
    assert np.count_nonzero(ambient.sum(axis=0)) > 0.3 * ambient[0].size
    assert ambient.max() == pytest.approx(0.55 * rig.camera.sensitivity_e_per_s * ROOM_RADIANCE, rel=0.05)
    assert both.sum() == pytest.approx(sweep.sum() + ambient.sum(), rel=0.01)  # both, less what the emitters hide
    # One rendering kept per state of the lights: back to the sweep, nothing is rendered again.
    switch.set(SWEEP)
    assert camera.rendering().rate is sweep
    # The camera's own switch of the light is the world's.
    camera.light_on = False
    assert not world.light_on and not camera.rendering().rate.any()
    frame = camera.capture(0.1)
    black, gain = (
        rig.camera.black_level_dn,
        rig.camera.full_well_e / (rig.camera.white_level - rig.camera.black_level_dn),
    )
    assert abs(frame.mosaic.mean() - black) < 0.05
    assert frame.mosaic.std() == pytest.approx(np.hypot(rig.camera.read_noise_e / gain, 12**-0.5), rel=0.25)


def test_the_simulated_stage_reads_back_the_same_pose_however_often_it_is_polled():
    import math

    from drivers.pose import Pose
    from sim_devices.clock import ManualClock
    from sim_devices.stage import SimulatedStage, StageConfig

    readings = []
    for polls in (1, 500):
        clock = ManualClock()
        stage = SimulatedStage(StageConfig(seed=3), clock=clock)
        moves = []
        for target in (Pose(0.05, 0.1, 0.2, math.pi, 0.0, 0.0), Pose(0.0, 0.12, 0.25, math.pi, 0.1, 0.0)):
            stage.move(target)
            for _ in range(polls):  # a host that polls often while the arm moves, or seldom
                stage.readback_pose()
                clock.advance(5.0 / polls)
            assert stage.in_position
            moves.append(stage.readback_pose().as_tuple())
        readings.append(moves)
    assert readings[0] == readings[1]
    first, second = (np.array(m) for m in readings[0])
    assert 0 < np.max(np.abs(first[:3] - (0.05, 0.1, 0.2))) < 5 * StageConfig().readback_noise_m  # noise, held per move
    assert np.any(first[:3] - (0.05, 0.1, 0.2) != second[:3] - (0.0, 0.12, 0.25))
