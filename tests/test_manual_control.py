"""The technician's manual control (:mod:`acquisition.daemon.manual`) through the daemon's API,
in process with the simulated rig: the alignment preview (the ball's expected outline,
saturation, histogram), the test shot, jog and home within the soft limits, and the log lines."""

from __future__ import annotations

import math
import re
import time

import cv2
import numpy as np
import pytest
from conftest import REDUCED_RIG, rig_with
from fastapi.testclient import TestClient

from acquisition.daemon.app import create_app
from acquisition.daemon.preview import SATURATED_RGB
from acquisition.daemon.settings import load_settings
from drivers.contracts.rig import load_rig

JSON = {"Content-Type": "application/json"}
TOKEN = "bench-test-token-0123"


@pytest.fixture()
def bench(tmp_path):
    """An in-process daemon (its lifespan starts the simulated rig) and a JSON client."""
    started = []

    def start(token=None, speed=0.5):
        extra = {"token": token} if token else {}
        settings = load_settings(None, data_dir=tmp_path / "data", rig=REDUCED_RIG, **extra)
        settings.arm.simulated.speed_m_s, settings.arm.simulated.accel_m_s2 = speed, 10 * speed
        client = TestClient(create_app(settings), base_url="http://127.0.0.1", headers=JSON)
        client.__enter__()
        started.append(client)
        return client, client.app.state.engine

    yield start
    for client in started:
        client.__exit__(None, None, None)


def test_the_outline_drawn_grazes_the_ball():
    """Each point of the ball's outline from the rig has a ray that grazes the ball: the
    processing's own miss (its fit of the rig, an independent formula) is zero. That the
    outline lies on the ball the simulated camera renders is checked on the ambient frames of
    tests/test_daemon_calibration.py."""
    from processing.rig_fit.silhouette import SilhouetteTerm
    from processing.trace import RigGeometry

    for rig in (load_rig(REDUCED_RIG), rig_with(camera__pose__look_at_m=[0.04, -0.02, 0.0])):
        outline = rig.ball_outline_px()
        assert outline.shape == (180, 2)
        misses = SilhouetteTerm(outline, 1.0, "outline").misses(RigGeometry.from_rig(rig))
        assert np.max(np.abs(misses)) < 1e-12  # metres
        # Off the axis the outline is an ellipse, not a circle about the ball's image.
        centre = RigGeometry.from_rig(rig).project(np.asarray(rig.ball.centre_m)[None, :])[0]
        radii = np.linalg.norm(outline - centre, axis=1)
        assert (radii.max() - radii.min() > 1.0) == (rig.camera.pose.look_at_m != rig.ball.centre_m)


def test_a_test_shot_is_shown_and_stored_nowhere(bench, tmp_path):
    http, engine = bench()
    assert http.get("/preview/frame").status_code == 404  # nothing taken yet
    shot = http.post("/preview/shot", json={"exposures_s": [0.001, 0.1]})
    assert shot.status_code == 200, shot.text
    frames = shot.json()["frames"]
    assert [f["exposure_s"] for f in frames] == [0.001, 0.1]
    frame = engine.latest_frame  # the last one is shown
    signal = frame.mosaic.astype(float) - frame.black_level[0, 0]
    top = frame.white_level - frame.black_level[0, 0]
    saturated = signal >= 0.98 * top
    assert frames[0]["saturated_pixels"] == 0 and frames[1]["saturated_pixels"] == int(saturated.sum()) > 0
    summary = http.get("/preview/frame").json()
    assert summary["run_id"] is None and summary["exposure_s"] == 0.1 and summary["serial"] == shot.json()["serial"]
    assert summary["saturated_pixels"] == int(saturated.sum())
    np.testing.assert_allclose(summary["ball_outline_px"], load_rig(REDUCED_RIG).ball_outline_px(), atol=0.005)
    assert summary["peak_dn"] == pytest.approx(signal.max())
    channels = summary["histogram"]["channels"]
    assert list(channels) == ["R", "G", "B"]
    h, w = frame.shape
    assert (summary["width"], summary["height"]) == (w, h)
    for name, share in (("R", 0.25), ("G", 0.5), ("B", 0.25)):
        assert channels[name]["below"] + sum(channels[name]["counts"]) == share * w * h
    # The view: the sensor's size, the saturated photosites magenta, a log scale elsewhere.
    png = http.get("/preview/frame.png")
    assert png.headers["content-type"] == "image/png"
    view = cv2.imdecode(np.frombuffer(png.content, np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]
    assert view.shape == (h, w, 3)
    magenta = np.all(view == SATURATED_RGB, axis=2)
    np.testing.assert_array_equal(magenta, saturated)
    grey = view[~saturated][:, 0]
    assert grey.min() == 0 and grey.max() > 200  # black at 1 DN above black, near white by the saturated core
    # Nothing is stored in a run.
    assert http.get("/runs").json() == []
    assert not list((tmp_path / "data" / "runs").glob("*"))


def test_jog_and_home_within_the_soft_limits(bench):
    http, engine = bench()
    arm = engine.devices.arm
    start = arm.position()
    moved = http.post("/arm/jog", json={"axis": "z", "step": -5.0})
    assert moved.status_code == 200, moved.text
    assert moved.json()["moved"] == "jog z -5 mm"
    assert moved.json()["position"]["z"] == pytest.approx(start.z - 0.005, abs=2e-5)
    # Beyond the rig's soft limits (z up to 0.45 m): refused in one line, the arm not moved.
    for _ in range(2):
        moved = http.post("/arm/jog", json={"axis": "z", "step": 100.0})
    assert moved.json()["position"]["z"] == pytest.approx(start.z + 0.195, abs=2e-5)
    refused = http.post("/arm/jog", json={"axis": "z", "step": 100.0})
    assert refused.status_code == 422
    detail = refused.json()["detail"]
    pattern = (
        r"jog z \+100 mm: z=0\.49\d{4} m outside the soft limits \[0\.000000, 0\.450000\] m "
        r"\(the rig's arm\.soft_limits\)"
    )
    assert re.fullmatch(pattern, detail), detail
    assert arm.position().z == pytest.approx(start.z + 0.195, abs=2e-5)
    # A turn past 180° is the same turn the other way round: within ±180°.
    turned = http.post("/arm/jog", json={"axis": "rx", "step": 10.0}).json()["position"]["rx"]
    assert abs(turned) == pytest.approx(170.0, abs=0.01)
    assert http.post("/arm/jog", json={"axis": "q", "step": 1.0}).status_code == 422
    assert http.post("/arm/jog", json={"axis": "x", "step": 1000.0}).status_code == 422
    home = http.post("/arm/home")
    assert home.status_code == 200 and home.json()["moved"] == "homed"
    assert home.json()["position"]["z"] == pytest.approx(start.z, abs=2e-5)
    assert abs(home.json()["position"]["rx"]) == pytest.approx(180.0, abs=0.01)
    # The requests that change something are JSON only.
    assert http.post("/arm/home", headers={"Content-Type": "text/plain"}).status_code == 415
    messages = [line["message"] for line in http.get("/log").json()]
    assert any(m.startswith("jog z -5 mm: at x ") for m in messages)
    assert any(m.startswith("homed: at ") for m in messages)
    seq = http.get("/log").json()[-1]["seq"]
    assert http.get("/log", params={"after": seq}).json() == []


def test_the_bench_is_refused_during_a_run_and_the_token_guards_it(bench):
    http, engine = bench(token=TOKEN, speed=0.05)
    assert http.post("/arm/jog", json={"axis": "z", "step": 1.0}).status_code == 401
    assert http.post("/preview/shot").status_code == 401
    assert http.get("/log").status_code == 401  # the token guards the reads too
    assert http.get("/preview/frame").status_code == 401
    http.headers["Authorization"] = f"Bearer {TOKEN}"
    run = http.post("/runs", json={"count": 3, "bracket": {"mode": "fixed", "exposures_s": [0.001]}}).json()
    for path, body in (("/arm/jog", {"axis": "z", "step": 1.0}), ("/preview/shot", {}), ("/arm/home", None)):
        refused = http.post(path, json=body)
        assert refused.status_code == 409, refused.text
        assert refused.json()["detail"] == f"run {run['id']} is already active on this rig"
    http.post(f"/runs/{run['id']}/abort")
    deadline = time.monotonic() + 30
    while http.get(f"/runs/{run['id']}").json()["state"] != "aborted" and time.monotonic() < deadline:
        time.sleep(0.05)
    assert http.post("/arm/jog", json={"axis": "z", "step": -1.0}).status_code == 200
    messages = [line["message"] for line in http.get("/log").json()]
    assert f"run {run['id']} started: light-sweep, 3 positions" in messages
    assert f"run {run['id']} aborted: aborted by the operator" in messages
    assert not math.isnan(engine.devices.arm.position().z)
