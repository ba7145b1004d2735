"""Calibration frames in every run: the daemon, in process with the simulated rig, takes ambient
frames (the light off, the room lit) and dark frames (the room dark too) before the sweep and,
when asked, after it; the processing finds the ball's silhouette in the ambient frames where the
rig puts the ball. A manual light switch pauses the run with what the operator must do."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import ROOT
from test_daemon_api import daemon, wait_state  # noqa: F401 - the fixture

from acquisition.daemon.run_thread import RunThread
from drivers.contracts.runfile import RunFile
from drivers.errors import DeviceError
from drivers.light import ManualLightSwitch, NoLightSwitch
from processing.calibration import calibrate_ball, detect_silhouette, mosaic_luminance

AMBIENT_S = [0.01, 0.04, 0.16]  # the daemon's default ambient bracket
SWEEP_S = [0.0002, 0.001, 0.005]


def silhouette_error_px(rig, frame: np.ndarray, black: np.ndarray) -> float:
    """How far (pixels) the ball's centre measured from its silhouette projects from where the
    rig puts the ball."""
    fit = calibrate_ball(mosaic_luminance(frame, black), rig)
    k = rig.camera.camera_matrix()
    rot, t = rig.camera.pose.extrinsics()

    def project(point):
        p = k @ point
        return p[:2] / p[2]

    described = project(rot @ np.asarray(rig.ball.centre_m) + t)
    return float(np.linalg.norm(project(fit.centre_camera) - described))


def record_steps(monkeypatch) -> list[str]:
    """Every step a run's thread reports (``RunStatus.step``), in order."""
    steps: list[str] = []
    original = RunThread._set_step

    def recording(self, step):
        if not steps or steps[-1] != step:
            steps.append(step)
        original(self, step)

    monkeypatch.setattr(RunThread, "_set_step", recording)
    return steps


def test_the_simulated_rig_takes_ambient_and_dark_frames_before_and_after_the_sweep(daemon, monkeypatch):  # noqa: F811
    steps = record_steps(monkeypatch)
    http, engine = daemon(speed=float("inf"))
    run = http.post(
        "/runs", json={"count": 2, "bracket": {"mode": "fixed", "exposures_s": SWEEP_S}, "calibration": {"after": True}}
    ).json()
    assert wait_state(http, run["id"], {"complete", "failed"})["state"] == "complete"
    with RunFile.open(engine.catalog.get_run(run["id"]).path) as f:
        rig, cam = f.header.rig, f.header.rig.camera
        assert f.header.calibration == {
            "switch": "simulated light switch",
            "sets": [["ambient", "before"], ["dark", "before"], ["ambient", "after"], ["dark", "after"]],
            "ambient_exposures_s": AMBIENT_S,
            "dark": "room dark",
            "dark_exposures_s": AMBIENT_S,
        }
        sets = {(role, when): f.calibration_frames(role, when) for role, when in f.calibration_sets()}
        assert set(sets) == {("ambient", "before"), ("dark", "before"), ("ambient", "after"), ("dark", "after")}
        # In this order: ambient, dark, the sweep, ambient, dark.
        order = [sets["ambient", "before"].timestamps, sets["dark", "before"].timestamps]
        order += [
            f.timestamps(0),
            f.timestamps(1),
            sets["ambient", "after"].timestamps,
            sets["dark", "after"].timestamps,
        ]
        stamps = np.concatenate(order)
        assert np.all(np.diff(stamps) > 0)
        # The calibration frames before were taken where position 0's are, with no move between.
        assert f.measured_pose(0).distance_to(f.header.tool_poses[0])[0] < 50e-6
        headroom = cam.white_level - cam.black_level_dn
        for when in ("before", "after"):
            dark, ambient = sets["dark", when], sets["ambient", when]
            np.testing.assert_array_equal(dark.exposures_s, AMBIENT_S)
            np.testing.assert_array_equal(ambient.exposures_s, AMBIENT_S)
            # Dark: the bias and the read noise (3 e-, 0.6 DN) only.
            assert np.all(np.abs(dark.frames.mean(axis=(1, 2)) - cam.black_level_dn) < 0.05)
            assert np.all(dark.frames.std(axis=(1, 2)) < 1.0)
            # Ambient: the ball lit by the room, the longest frame well exposed and unclipped.
            peaks = ambient.frames.max(axis=(1, 2)).astype(float) - cam.black_level_dn
            assert np.all(np.diff(peaks) > 0) and 0.6 * headroom < peaks[-1] < 0.95 * headroom
            assert ambient.cfa_pattern == cam.cfa_pattern and ambient.white_level == cam.white_level
            np.testing.assert_array_equal(ambient.black_level, np.full((2, 2), cam.black_level_dn))
            for frame in ambient.frames:
                assert silhouette_error_px(rig, frame, ambient.black_level) < 0.5  # measured: 0.01-0.04 px
            # The outline the page draws (the rig's) lies on the silhouette the processing measures.
            measured = detect_silhouette(mosaic_luminance(ambient.frames[-1], ambient.black_level)).points
            outline = rig.ball_outline_px(3600)
            off = np.min(np.linalg.norm(measured[:, None, :] - outline[None, :, :], axis=2), axis=1)
            assert len(measured) > 300 and off.max() < 1.0, off.max()  # measured: 0.56 px mean, 0.82 max
        # The sweep in the dark room: the frames are black but for the light's emitters.
        assert np.median(f.frames(0)[-1]) <= cam.black_level_dn + 1
    assert steps[0] == "calibration: moving to position 1 for the frames before the sweep"
    assert "calibration: ambient frames before the sweep (the light off, the room lit), frame 3 of 3" in steps
    assert "calibration: dark frames before the sweep (the light off, the room dark), frame 1 of 3" in steps
    assert steps.index(f"sweep, position 1 of {run['n_positions']}") > steps.index(
        "calibration: dark frames before the sweep (the light off, the room dark), frame 3 of 3"
    )
    assert steps[-1] == "calibration: dark frames after the sweep (the light off, the room dark), frame 3 of 3"
    # The simulated world's lights as the dark frames after the sweep left them.
    assert not engine.devices.simulated["world"].light_on and not engine.devices.simulated["world"].room_lit
    assert http.get(f"/runs/{run['id']}").json()["step"] is None  # the run is over


# The demo's rig: the default rig's field of view at half its resolution. The full resolution
# takes 35-40 s more here (its room rendered at 2000 x 1312) for the same path through the code.
@pytest.mark.slow
@pytest.mark.parametrize("rig_name", ["demo"])
def test_the_silhouette_of_the_daemons_ambient_frames_is_where_the_rig_puts_the_ball(daemon, rig_name):  # noqa: F811
    http, engine = daemon(speed=float("inf"), rig=ROOT / "rigs" / f"{rig_name}.toml")
    run = http.post("/runs", json={"count": 1, "calibration": {"dark": False}}).json()
    assert wait_state(http, run["id"], {"complete", "failed"}, timeout=600)["state"] == "complete"
    with RunFile.open(engine.catalog.get_run(run["id"]).path) as f:
        ambient = f.calibration_frames("ambient")
        assert f.calibration_frames("dark") is None and ambient.frames.shape[1:] == f.frame_shape
        errors = [silhouette_error_px(f.header.rig, frame, ambient.black_level) for frame in ambient.frames]
    assert max(errors) < 0.5, errors  # measured: 0.01-0.04 px on both rigs


def test_a_manual_switch_pauses_the_run_until_the_operator_has_switched_the_lights(daemon):  # noqa: F811
    http, engine = daemon(speed=float("inf"), light={"kind": "manual"})
    assert isinstance(engine.devices.light, ManualLightSwitch)
    run = http.post("/runs", json={"count": 1, "bracket": {"mode": "fixed", "exposures_s": [0.001]}}).json()
    for instruction in (
        "turn the light off and the room lights on, then resume",
        "turn the light off and the room lights off, then resume",
        "turn the light on and the room lights off, then resume",
    ):
        paused = wait_state(http, run["id"], {"paused", "complete", "failed"})
        assert paused["state"] == "paused" and paused["step"] == f"waiting for the operator: {instruction}"
        assert paused["last_error"] is None and paused["positions_done"] == 0
        resumed = http.post(f"/runs/{run['id']}/resume")
        assert resumed.status_code == 200 and resumed.json()["state"] == "running"
    assert wait_state(http, run["id"], {"complete", "failed"})["state"] == "complete"
    with RunFile.open(engine.catalog.get_run(run["id"]).path) as f:
        assert f.header.calibration["switch"].startswith("manual")
        assert f.calibration_sets() == [("ambient", "before"), ("dark", "before")] and f.complete.all()
    # The lights are on for the sweep now: a run without calibration frames asks for nothing.
    run = http.post("/runs", json={"count": 1, "calibration": {"before": False}}).json()
    assert wait_state(http, run["id"], {"complete", "paused", "failed"})["state"] == "complete"


def test_a_rig_without_a_light_switch_records_that_its_runs_have_no_calibration_frames(daemon):  # noqa: F811
    http, engine = daemon(speed=float("inf"), light={"kind": "none"})
    assert isinstance(engine.devices.light, NoLightSwitch)
    run = http.post("/runs", json={"count": 1, "bracket": {"mode": "fixed", "exposures_s": [0.001]}}).json()
    assert wait_state(http, run["id"], {"complete", "failed"})["state"] == "complete"
    with RunFile.open(engine.catalog.get_run(run["id"]).path) as f:
        assert f.header.calibration == {
            "switch": "none",
            "sets": [],
            "reason": "the daemon has no light switch (light.kind = none)",
        }
        assert f.calibration_sets() == [] and f.calibration_frames("ambient") is None


def test_a_room_that_cannot_be_darkened_gives_one_dark_frame_at_the_shortest_exposure(daemon):  # noqa: F811
    light = {"room_can_be_dark": False, "ambient_exposures_s": [0.02, 0.08]}  # the daemon's default bracket
    http, engine = daemon(speed=float("inf"), light=light)
    run = http.post("/runs", json={"count": 1, "bracket": {"mode": "fixed", "exposures_s": [0.001]}}).json()
    assert wait_state(http, run["id"], {"complete", "failed"})["state"] == "complete"
    with RunFile.open(engine.catalog.get_run(run["id"]).path) as f:
        plan = f.header.calibration
        assert plan["dark"] == "shortest exposure, room lit" and plan["dark_exposures_s"] == [1e-4]
        np.testing.assert_array_equal(f.calibration_frames("ambient").exposures_s, [0.02, 0.08])
        np.testing.assert_array_equal(f.calibration_frames("dark").exposures_s, [1e-4])


def test_a_resumed_run_does_not_take_its_complete_calibration_sets_again(daemon, monkeypatch):  # noqa: F811
    http, engine = daemon(speed=float("inf"))
    camera = engine.devices.camera
    original, taken, jammed = camera.capture, [], []

    def capture(exposure_s):
        taken.append(exposure_s)
        if exposure_s == 0.005 and taken.count(0.005) == 2 and not jammed:  # position 1's longest frame
            jammed.append(exposure_s)
            raise DeviceError(camera.identity, "capture", "the shutter jammed")
        return original(exposure_s)

    monkeypatch.setattr(camera, "capture", capture)
    request = {"count": 3, "bracket": {"mode": "fixed", "exposures_s": SWEEP_S}, "calibration": {"after": True}}
    run = http.post("/runs", json=request).json()
    failed = wait_state(http, run["id"], {"failed", "complete"})
    assert failed["state"] == "failed" and "the shutter jammed" in failed["last_error"]
    path = engine.catalog.get_run(run["id"]).path
    with RunFile.open(path) as f:
        assert f.calibration_sets() == [("ambient", "before"), ("dark", "before")]
        kept = {role: f.calibration_frames(role).timestamps for role in ("ambient", "dark")}
    taken.clear()
    assert http.post(f"/runs/{run['id']}/resume").status_code == 200
    assert wait_state(http, run["id"], {"complete", "failed"})["state"] == "complete"
    # Resumed: positions 1 and 2, then the sets after the sweep; none of those before again.
    assert taken == SWEEP_S * 2 + AMBIENT_S * 2
    with RunFile.open(path) as f:
        assert f.complete.all() and len(f.calibration_sets()) == 4
        for role, stamps in kept.items():
            np.testing.assert_array_equal(f.calibration_frames(role).timestamps, stamps)


@pytest.mark.parametrize(
    ("calibration", "field"),
    [
        ({"ambient_exposures_s": []}, "ambient_exposures_s"),
        ({"ambient_exposures_s": [-0.01]}, "ambient_exposures_s"),
        ({"ambient_exposures_s": [0.01] * 17}, "ambient_exposures_s"),
        ({"before": "yes"}, "before"),
        ({"dark": 1}, "dark"),
        ({"lamp": "off"}, "lamp"),
    ],
)
def test_bad_calibration_options_are_a_422_naming_the_field(daemon, calibration, field):  # noqa: F811
    http, _ = daemon()
    answer = http.post("/runs", json={"count": 1, "calibration": calibration})
    assert answer.status_code == 422, answer.text
    assert any(field in error["loc"] for error in answer.json()["detail"])
