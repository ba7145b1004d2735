"""A seeded simulated run is the same run whatever the timing: the frames and the poses a run
file records do not depend on how fast the machine is, how often the arm is polled, or what
else the camera captured (issue: the demo's centre source moved between runs of one seed)."""

from __future__ import annotations

import h5py
import hdf5plugin  # noqa: F401 - the frames' LZ4 filter
import numpy as np
from conftest import REDUCED_RIG

from acquisition.benchmarks.accuracy import take_run
from acquisition.daemon.models import FixedBracket, RunRequest
from acquisition.daemon.settings import load_settings
from drivers.contracts.rig import load_rig


def seeded_run(workdir, *, speed_m_s, latency_s):
    settings = load_settings(None, data_dir=workdir / "data")
    settings.arm.simulated.speed_m_s = speed_m_s
    settings.arm.simulated.accel_m_s2 = 10.0 * speed_m_s
    settings.camera.simulated.noise = True
    settings.camera.simulated.latency_s = latency_s
    request = RunRequest.model_validate(
        {"preset": "light-sweep", "count": 4, "bracket": FixedBracket(exposures_s=[0.001, 0.008])}
    )
    path = take_run(settings, load_rig(REDUCED_RIG), request)
    with h5py.File(path, "r") as f:
        return f["frames/raw"][:], f["positions/measured_pose"][:], f["frames/exposure_s"][:]


def test_two_runs_of_one_seed_at_different_speeds_record_the_same_frames_and_poses(tmp_path):
    fast = seeded_run(tmp_path / "fast", speed_m_s=2.0, latency_s=0.0)
    slow = seeded_run(tmp_path / "slow", speed_m_s=0.05, latency_s=0.05)  # many more polls per move
    frames, poses, exposures = fast
    assert frames.shape[0] == 4 and np.isfinite(poses).all() and frames.max() > frames.min()
    np.testing.assert_array_equal(slow[0], frames)
    np.testing.assert_array_equal(slow[1], poses)
    np.testing.assert_array_equal(slow[2], exposures)
