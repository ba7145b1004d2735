"""The run file: round trip, compression, crash safety under SIGKILL, salvage, errors."""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import h5py
import hdf5plugin
import numpy as np
import pytest

from drivers.camera import RawFrame
from drivers.contracts.rig import DEFAULT_RIG_PATH, rig_from_dict
from drivers.contracts.runfile import (
    CALIBRATION_SETS,
    RUN_FILE_FORMAT,
    RUN_FILE_VERSION,
    CalibrationFrames,
    PositionTimes,
    RunFile,
    RunFileError,
    RunFileWriter,
    RunHeader,
)
from drivers.pose import Pose

H, W = 64, 96
MAX_EXPOSURES = 3
SEED = 1234
TESTS_DIR = Path(__file__).resolve().parent


# --- deterministic runs (also imported by the writer subprocess) ------------------------
def make_rig(n_positions: int):
    data = tomllib.loads(DEFAULT_RIG_PATH.read_text())
    data["camera"]["width"], data["camera"]["height"] = W, H
    data["schedule"]["count"] = n_positions
    return rig_from_dict(data)


def make_header(n_positions: int = 6, run_id: str = "run-0001") -> RunHeader:
    rig = make_rig(n_positions)
    return RunHeader(
        run_id=run_id,
        rig=rig,
        tool_poses=rig.tool_poses(),
        light_poses=rig.light_poses(),
        max_exposures=MAX_EXPOSURES,
        frame_shape=(H, W),
        bracket={"mode": "fixed", "exposures_s": [0.001, 0.004, 0.016]},
        metadata={"operator": "Ada", "light_source": "LED 3 W", "notes": "über ✓"},
        devices={"arm": "sim-arm 1", "camera": "sim-camera 2"},
        software_version="0.1.0",
        created_utc="2026-05-09T07:35:25+00:00",
        preset="sweep-66",
    )


def frame_count(i: int) -> int:
    return 1 + i % MAX_EXPOSURES


def position_data(seed: int, i: int, count: int | None = None) -> tuple[Pose, PositionTimes, list[RawFrame]]:
    """The measured pose, times and frames of position ``i``, the same on every call."""
    frames = []
    for k in range(frame_count(i) if count is None else count):
        rng = np.random.default_rng([seed, i, k])
        mosaic = np.full((H, W), 64, np.uint16)  # dark, with a bright noisy spot
        left = 20 + (2 * i) % 32
        mosaic[8:40, left : left + 40] = rng.integers(0, 4096, (32, 40))
        black = np.array([[64.0, 64.5], [63.75, 64.25]]) + k
        frames.append(
            RawFrame(mosaic, black, 4095 - k, "RGGB", 0.001 * 4**k, 1.7e9 + i + 0.1 * k, "sim", f"/tmp/{i}-{k}.dng")
        )
    measured = Pose(0.01 * i, 0.04 + 1e-6 * seed, 0.1, 0.1, -0.2, 0.3 + 1e-3 * i)
    times = PositionTimes(1.7e9 + i, 1.7e9 + i + 0.25, 1.7e9 + i + 0.75)
    return measured, times, frames


def check_position(run: RunFile, seed: int, i: int, count: int | None = None) -> None:
    measured, times, frames = position_data(seed, i, count)
    assert run.measured_pose(i) == measured
    assert run.times(i) == times
    stack = run.frames(i)
    assert stack.dtype == np.uint16 and stack.shape == (len(frames), H, W)
    for k, frame in enumerate(frames):
        assert np.array_equal(stack[k], frame.mosaic)
    np.testing.assert_array_equal(run.exposures(i), [f.exposure_s for f in frames])
    np.testing.assert_array_equal(run.black_level(i), [f.black_level for f in frames])
    np.testing.assert_array_equal(run.white_level(i), [f.white_level for f in frames])
    assert run.cfa_pattern(i) == [f.cfa_pattern for f in frames]


def write_run(path, n: int, positions, seed: int = SEED) -> None:
    with RunFileWriter.create(path, make_header(n)) as writer:
        for i in positions:
            writer.write_position(i, *position_data(seed, i))


WRITER_SCRIPT = """
import os, signal, sys, time
sys.path.insert(0, {tests!r})
from test_runfile import SEED, make_header, position_data
from drivers.contracts.runfile import RunFileWriter

path, n, stop_after, pause = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
print("ready", flush=True)
writer = RunFileWriter.reopen(path) if os.path.exists(path) else RunFileWriter.create(path, make_header(n))
writer.set_status("running")
print("opened", flush=True)
written = 0
index = writer.first_incomplete()
while index is not None:
    if written == stop_after:
        print("stopping", flush=True)
        os.kill(os.getpid(), signal.SIGKILL)
    writer.write_position(index, *position_data(SEED, index))
    print("wrote", index, flush=True)
    written += 1
    time.sleep(pause)
    index = writer.first_incomplete()
writer.set_status("complete")
writer.close()
print("done", flush=True)
"""


@pytest.fixture()
def writer_script(tmp_path):
    script = tmp_path / "writer.py"
    script.write_text(WRITER_SCRIPT.format(tests=str(TESTS_DIR)))
    return script


def start_writer(script, path, n, stop_after=-1, pause=0.0) -> subprocess.Popen:
    proc = subprocess.Popen(
        [sys.executable, str(script), str(path), str(n), str(stop_after), str(pause)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    line = proc.stdout.readline()
    if line != "ready\n":
        proc.kill()
        raise AssertionError(f"writer did not start: {line!r} {proc.stderr.read()}")
    return proc


def finish_writer(proc: subprocess.Popen) -> list[str]:
    """Wait for a killed writer; the lines it printed. A Python error fails the test."""
    out, err = proc.communicate(timeout=10)
    assert proc.returncode in (0, -signal.SIGKILL), err
    return out.splitlines()


# --- round trip ----------------------------------------------------------------------------
def test_round_trip(tmp_path):
    path = tmp_path / "run-0001.h5"
    n = 5
    header = make_header(n)
    with RunFileWriter.create(path, header) as writer:
        assert writer.first_incomplete() == 0
        for i in (0, 1, 2, 4):
            writer.write_position(i, *position_data(SEED, i))
        assert writer.complete.tolist() == [True, True, True, False, True]
        assert writer.first_incomplete() == 3
        writer.set_status("paused", "operator stop at position 3: ärm ✓")
    assert not Path(str(path) + ".lock").exists()
    with RunFile.open(path) as run:
        assert run.header == header
        assert run.header.rig == header.rig
        assert run.n_positions == n and run.max_exposures == MAX_EXPOSURES and run.frame_shape == (H, W)
        assert run.status == "paused"
        assert run.status_message == "operator stop at position 3: ärm ✓"
        assert run.completed_positions().tolist() == [0, 1, 2, 4]
        for i in (0, 1, 2, 4):
            check_position(run, SEED, i)
        frame = run.frame(2, 1)
        expected = position_data(SEED, 2)[2][1]
        assert np.array_equal(frame.mosaic, expected.mosaic)
        assert frame.exposure_s == expected.exposure_s and frame.timestamp == expected.timestamp
        assert frame.white_level == expected.white_level and frame.cfa_pattern == "RGGB"
        np.testing.assert_array_equal(frame.black_level, expected.black_level)
        assert frame.camera_id == "sim-camera 2"
        assert run.measured_pose(3) is None and run.times(3) is None
        with pytest.raises(RunFileError, match=r"run-0001\.h5: position 3 is not complete"):
            run.frames(3)
        with pytest.raises(RunFileError, match="out of range"):
            run.frames(5)
        with pytest.raises(RunFileError, match="no frame 1"):
            run.frame(0, 1)
        # The layout other readers rely on.
        f = h5py.File(path, "r", swmr=True)
        try:
            assert f.attrs["format"] == RUN_FILE_FORMAT and f.attrs["format_version"] == RUN_FILE_VERSION
            np.testing.assert_array_equal(f["schedule/commanded_pose"][2], header.tool_poses[2].as_tuple())
            np.testing.assert_array_equal(f["schedule/light_pose"][4], header.light_poses[4].as_tuple())
            assert np.isnan(f["positions/measured_pose"][3]).all() and np.isnan(f["positions/times"][3]).all()
            assert f["positions/frame_count"][()].tolist() == [1, 2, 3, 0, 2]
            assert np.isnan(f["frames/exposure_s"][0, 1:]).all()
            assert f["status/state"].dtype == np.dtype("S16") and f["status/message"].dtype == np.dtype("S1024")
        finally:
            f.close()


def test_status_message_truncated_to_fit(tmp_path):
    path = tmp_path / "run.h5"
    with RunFileWriter.create(path, make_header(2)) as writer:
        writer.set_status("failed", "é" * 600)  # 1200 bytes of UTF-8
        with pytest.raises(RunFileError, match="unknown status 'done'"):
            writer.set_status("done")
    with RunFile.open(path) as run:
        assert run.status == "failed" and run.status_message == "é" * 512


def test_frames_are_lz4_one_frame_per_chunk_and_plain_h5py_reads_them(tmp_path):
    path = tmp_path / "run.h5"
    write_run(path, 3, range(3))
    with h5py.File(path, "r") as f:  # a cleanly closed file opens without SWMR too
        raw = f["frames/raw"]
        assert raw.shape == (3, MAX_EXPOSURES, H, W) and raw.dtype == np.uint16
        assert raw.chunks == (1, 1, H, W)
        plist = raw.id.get_create_plist()
        filters = [plist.get_filter(j)[0] for j in range(plist.get_nfilters())]
        assert filters == [hdf5plugin.LZ4_ID, h5py.h5z.FILTER_FLETCHER32]  # the checksum of the compressed bytes
        assert raw.id.get_storage_size() < 6 * H * W * 2  # six frames stored, compressed
        assert np.array_equal(raw[2, 2], position_data(SEED, 2)[2][2].mosaic)
    code = (
        "import sys, h5py, hdf5plugin\n"
        "f = h5py.File(sys.argv[1], 'r')\n"
        "print(int(f['frames/raw'][1, 1].astype('int64').sum()), f['positions/complete'][:].tolist())\n"
    )
    out = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, check=True)
    expected = int(position_data(SEED, 1)[2][1].mosaic.astype(np.int64).sum())
    assert out.stdout.split(maxsplit=1) == [str(expected), "[1, 1, 1]\n"]


# --- crash safety ------------------------------------------------------------------------------
def _check_after_kill(path: Path, seed: int, n: int, before: set[int], reported: set[int]) -> set[int]:
    """Every complete position is bit-exact; none complete before or reported written is lost."""
    leftovers = {p.name for p in path.parent.iterdir()} - {path.name, "writer.py"}
    assert leftovers <= {path.name + s for s in (".tmp", ".salvage.tmp", ".lock")}, leftovers
    if not path.exists():
        assert not before and not reported
        return set()
    with RunFile.open(path) as run:
        assert run.n_positions == n
        assert run.status in ("created", "running", "interrupted", "complete")
        done = set(run.completed_positions().tolist())
        for i in done:
            check_position(run, seed, i)
    assert before | reported <= done
    return done


def test_sigkill_at_random_moments_then_salvage_and_finish(tmp_path, writer_script):
    """Eight SIGKILLs of a writer (creating, salvaging or writing); nothing complete is lost."""
    path = tmp_path / "run.h5"
    n, pause = 60, 0.01
    rng = np.random.default_rng(20260509)
    # The first moments fall in the creation, then in the salvage; the later ones in the
    # middle of writing (creating or salvaging takes about 10 ms here, a position 15 ms).
    delays = [rng.uniform(0.0, 0.012) for _ in range(3)] + [rng.uniform(0.0, 0.15) for _ in range(5)]
    done: set[int] = set()
    phases = []
    for delay in delays:
        crashed_before = path.exists()
        proc = start_writer(writer_script, path, n, pause=pause)
        time.sleep(float(delay))
        proc.send_signal(signal.SIGKILL)
        lines = finish_writer(proc)
        reported = {int(line.split()[1]) for line in lines if line.startswith("wrote")}
        phases.append(("salvage" if crashed_before else "create") if "opened" not in lines else "writing")
        done = _check_after_kill(path, SEED, n, done, reported)
    assert 0 < len(done) < n, (len(done), phases)
    assert "writing" in phases, phases
    with RunFileWriter.reopen(path) as writer:  # salvages the killed file
        assert set(np.flatnonzero(writer.complete).tolist()) == done
        with RunFile.open(path) as run:
            assert run.status == "interrupted"
            assert f"{len(done)} of {n} positions complete" in run.status_message
        writer.set_status("running")
        index = writer.first_incomplete()
        while index is not None:
            writer.write_position(index, *position_data(SEED, index))
            index = writer.first_incomplete()
        writer.set_status("complete")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.h5", "writer.py"]
    with RunFile.open(path) as run:
        assert run.complete.all() and run.status == "complete"
        for i in range(n):
            check_position(run, SEED, i)


def test_kill_during_create_leaves_no_file_or_a_whole_one(tmp_path):
    """A process creating run after run, frozen at random moments, then killed.

    What a process leaves on disk when SIGKILL stops it is what is on disk when SIGSTOP
    freezes it, so each freeze is copied aside and checked as if the process had been
    killed there: every run file present is whole; a half-built one is only ever a
    ``.tmp`` file.
    """
    script = tmp_path / "creator.py"
    script.write_text(
        f"import sys\nsys.path.insert(0, {str(TESTS_DIR)!r})\n"
        "from test_runfile import make_header\n"
        "from drivers.contracts.runfile import RunFileWriter\n"
        "header = make_header(66)\n"
        "print('ready', flush=True)\n"
        "for j in range(100000):\n"
        "    RunFileWriter.create(f'{sys.argv[1]}/run-{j:05d}.h5', header).close()\n"
    )
    folder = tmp_path / "runs"
    folder.mkdir()
    proc = subprocess.Popen([sys.executable, str(script), str(folder)], stdout=subprocess.PIPE, text=True)
    rng = np.random.default_rng(7)
    caught_building = 0
    try:
        assert proc.stdout.readline() == "ready\n"
        for moment in range(25):
            time.sleep(float(rng.uniform(0.0, 0.03)))
            proc.send_signal(signal.SIGSTOP)
            snapshot = tmp_path / f"snapshot-{moment}"
            shutil.copytree(folder, snapshot)
            proc.send_signal(signal.SIGCONT)
            runs = sorted(snapshot.glob("run-*.h5"))
            for path in runs[-2:]:  # the earlier ones were checked in earlier snapshots
                with RunFile.open(path) as run:
                    assert run.n_positions == 66 and run.status == "created" and not run.complete.any()
            others = {p.name for p in snapshot.iterdir()} - {p.name for p in runs}
            names = {p.name for p in runs[-1:]}
            if runs:
                names.add(f"run-{int(runs[-1].name[4:9]) + 1:05d}.h5")
            else:
                names.add("run-00000.h5")
            assert others <= {name + suffix for name in names for suffix in (".tmp", ".lock")}, others
            caught_building += any(name.endswith(".tmp") for name in others)
            shutil.rmtree(snapshot)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        proc.stdout.close()
    assert caught_building >= 1
    # After the kill: every run file is whole, and a stale .tmp does not stop the next run.
    runs = sorted(folder.glob("run-*.h5"))
    for path in runs[-3:]:
        with RunFile.open(path) as run:
            assert run.n_positions == 66
    following = folder / f"run-{int(runs[-1].name[4:9]) + 1:05d}.h5"
    RunFileWriter.create(following, make_header(66)).close()
    assert not Path(str(following) + ".tmp").exists()


def test_salvage_copies_frame_chunks_without_recompressing(tmp_path, writer_script):
    path = tmp_path / "run.h5"
    n = 6
    proc = start_writer(writer_script, path, n, stop_after=4)
    assert finish_writer(proc)[-1] == "stopping" and proc.returncode == -signal.SIGKILL
    with pytest.raises(OSError, match="already open for write"):
        h5py.File(path, "r")  # the premise: a killed writer's file needs SWMR to read
    with h5py.File(path, "r", swmr=True) as f:
        raw = f["frames/raw"]
        before = {(i, k): raw.id.read_direct_chunk((i, k, 0, 0)) for i in range(4) for k in range(frame_count(i))}
    with RunFileWriter.reopen(path) as writer:
        assert writer.complete.tolist() == [True] * 4 + [False] * 2
    with h5py.File(path, "r") as f:  # closed cleanly now
        raw = f["frames/raw"]
        for (i, k), chunk in before.items():
            assert raw.id.read_direct_chunk((i, k, 0, 0)) == chunk
        assert raw.id.get_chunk_info_by_coord((4, 0, 0, 0)).size == 0
    with RunFile.open(path) as run:
        assert run.status == "interrupted"
        for i in range(4):
            check_position(run, SEED, i)
        assert run.measured_pose(4) is None


def test_second_writer_is_refused(tmp_path):
    path = tmp_path / "run.h5"
    with RunFileWriter.create(path, make_header(2)):
        with pytest.raises(RunFileError, match=r"run\.h5: another process \(pid \d+\) is writing this run"):
            RunFileWriter.reopen(path)
        with pytest.raises(RunFileError, match="another process"):
            RunFileWriter.create(path, make_header(2))
    with pytest.raises(RunFileError, match="run file already exists"):
        RunFileWriter.create(path, make_header(2))


def test_live_reader_sees_new_positions_after_refresh(tmp_path):
    path = tmp_path / "run.h5"
    code = (
        f"import sys\nsys.path.insert(0, {str(TESTS_DIR)!r})\n"
        "from test_runfile import SEED, make_header, position_data\n"
        "from drivers.contracts.runfile import RunFileWriter\n"
        "w = RunFileWriter.create(sys.argv[1], make_header(4))\n"
        "w.write_position(0, *position_data(SEED, 0))\n"
        "print('one', flush=True); sys.stdin.readline()\n"
        "w.write_position(1, *position_data(SEED, 1)); w.set_status('running')\n"
        "print('two', flush=True); sys.stdin.readline()\n"
        "w.close()\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code, str(path)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout.readline() == "one\n"
        with RunFile.open(path) as run:
            assert run.completed_positions().tolist() == [0]
            proc.stdin.write("\n")
            proc.stdin.flush()
            assert proc.stdout.readline() == "two\n"
            run.refresh()
            assert run.completed_positions().tolist() == [0, 1] and run.status == "running"
            check_position(run, SEED, 1)
        proc.stdin.write("\n")
        proc.stdin.flush()
        assert proc.wait(timeout=10) == 0
    finally:
        proc.kill()
        proc.stdout.close()
        proc.stdin.close()


# --- validation --------------------------------------------------------------------------------
def _bad_frames(kind: str) -> tuple[int, list[RawFrame], str]:
    _, _, frames = position_data(99, 1)
    if kind == "shape":
        frames[1].mosaic = np.zeros((100, 80), np.uint16)
        return 1, frames, rf"position 1 frame 1: shape 100x80, expected {H}x{W}"
    if kind == "dtype":
        frames[0].mosaic = frames[0].mosaic.astype(np.float32)
        return 1, frames, "position 1 frame 0: mosaic dtype float32, expected uint16"
    if kind == "too many":
        return 1, frames * 2, f"position 1: 4 frames, expected 1 to {MAX_EXPOSURES}"
    if kind == "none":
        return 1, [], f"position 1: 0 frames, expected 1 to {MAX_EXPOSURES}"
    if kind == "exposure":
        frames[1].exposure_s = 0.0
        return 1, frames, r"position 1 frame 1: exposure_s must be finite and > 0 \(got 0.0\)"
    if kind == "nan exposure":
        frames[0].exposure_s = float("nan")
        return 1, frames, "position 1 frame 0: exposure_s must be finite"
    if kind == "black level":
        frames[0].black_level = np.zeros(4)
        return 1, frames, "position 1 frame 0: black_level must be 2x2"
    if kind == "index":
        return 7, frames, r"position 7 out of range \(0 to 3\)"
    if kind == "negative index":
        return -1, frames, "position -1 out of range"
    raise AssertionError(kind)


@pytest.mark.parametrize(
    "kind", ["shape", "dtype", "too many", "none", "exposure", "nan exposure", "black level", "index", "negative index"]
)
def test_bad_position_is_refused_and_writes_nothing(tmp_path, kind):
    path = tmp_path / "run-0001.h5"
    with RunFileWriter.create(path, make_header(4)) as writer:
        writer.write_position(0, *position_data(SEED, 0))
        writer.write_position(1, *position_data(SEED, 1))
        index, frames, message = _bad_frames(kind)
        measured, times, _ = position_data(99, 1)
        with pytest.raises(RunFileError, match=r"^" + str(path).replace(".", r"\.") + ": " + message) as info:
            writer.write_position(index, measured, times, frames)
        assert "\n" not in str(info.value)
        assert writer.complete.tolist() == [True, True, False, False]
    with RunFile.open(path) as run:
        check_position(run, SEED, 0)
        check_position(run, SEED, 1)  # the earlier take of position 1 is untouched


def test_bad_header_is_refused(tmp_path):
    header = make_header(3)
    header.light_poses = header.light_poses[:2]
    with pytest.raises(RunFileError, match=r"run\.h5: cannot create the run: light_poses: 2 poses for 3"):
        RunFileWriter.create(tmp_path / "run.h5", header)
    header = make_header(3)
    header.bracket = {"exposures_s": [0.1]}
    with pytest.raises(RunFileError, match="bracket: must be a dict with mode 'fixed' or 'auto'"):
        RunFileWriter.create(tmp_path / "run.h5", header)
    assert list(tmp_path.iterdir()) == []


# --- opening errors ------------------------------------------------------------------------------
def _future_version(path):
    write_run(path, 2, [0])
    with h5py.File(path, "a") as f:
        f.attrs["format_version"] = RUN_FILE_VERSION + 1


def _truncated(path):
    write_run(path, 3, range(3))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _foreign(path):
    with h5py.File(path, "w") as f:
        f["x"] = np.arange(3)


def _missing_dataset(path):
    write_run(path, 2, [0])
    with h5py.File(path, "a") as f:
        del f["positions/times"]


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (None, "run file not found"),
        (lambda p: p.write_text("hello\n"), "not an HDF5 file"),
        (_foreign, r"not a mirrorgonio run file \(no 'format' attribute\)"),
        (_future_version, r"run file format version 3 is newer than this software reads \(up to 2\)"),
        (_truncated, r"truncated or corrupt HDF5 file \(truncated: \d+ of \d+ bytes\)"),
        (_missing_dataset, "corrupt run file: /positions/times is missing"),
    ],
    ids=["missing", "text", "foreign-hdf5", "future-version", "truncated", "missing-dataset"],
)
def test_open_errors_are_one_line_naming_the_file(tmp_path, make, message):
    path = tmp_path / "run-0009.h5"
    if make is not None:
        make(path)
    with pytest.raises(RunFileError, match=r"^" + str(path).replace(".", r"\.") + ": " + message) as info:
        RunFile.open(path)
    assert "\n" not in str(info.value)
    with pytest.raises(RunFileError, match=r"^" + str(path).replace(".", r"\.") + ": " + message):
        RunFileWriter.reopen(path)
    assert not Path(str(path) + ".lock").exists()


def test_a_file_changed_since_it_was_opened_is_checked_again(tmp_path):
    path = tmp_path / "run.h5"
    write_run(path, 2, [0])
    with RunFile.open(path) as first, RunFile.open(path) as second:  # the second from the checked header
        assert second.header == first.header and second.header is not first.header
        second.header.metadata["notes"] = "changed by one reader"
        second.header.tool_poses.pop()
        assert first.header.metadata.get("notes") != "changed by one reader" and first.header.n_positions == 2
    with h5py.File(path, "a") as f:  # the same file, changed in place since
        del f["positions/times"]
    with pytest.raises(RunFileError, match="corrupt run file: /positions/times is missing"):
        RunFile.open(path)
    write_run(tmp_path / "other.h5", 3, [0])
    (tmp_path / "other.h5").replace(path)  # another file under the same name
    with RunFile.open(path) as replaced:
        assert replaced.header.n_positions == 3


# --- resuming ----------------------------------------------------------------------------------
def test_rewrite_completed_position_after_reopen(tmp_path):
    path = tmp_path / "run.h5"
    write_run(path, 4, [0, 1, 2])
    with RunFileWriter.reopen(path) as writer:
        assert writer.header == make_header(4)
        assert writer.first_incomplete() == 3
        writer.write_position(2, *position_data(555, 2, count=1))  # re-taken: 1 frame, not 3
        writer.write_position(3, *position_data(SEED, 3))
        writer.set_status("complete")
    with RunFile.open(path) as run:
        assert run.complete.all() and run.status == "complete" and run.status_message == ""
        check_position(run, SEED, 0)
        check_position(run, SEED, 1)
        check_position(run, 555, 2, count=1)
        check_position(run, SEED, 3)
    with h5py.File(path, "r") as f:  # the earlier take's extra frames are gone
        assert not f["frames/raw"][2, 1:].any()
        assert np.isnan(f["frames/exposure_s"][2, 1:]).all()


# --- calibration frames (format version 2) -----------------------------------------------------
def calibration_data(role: str, when: str, count: int = 2, seed: int = SEED) -> list[RawFrame]:
    """The frames of one calibration set, the same on every call."""
    frames = []
    for k in range(count):
        rng = np.random.default_rng([seed, CALIBRATION_SETS.index((role, when)), k])
        level = 64 if role == "dark" else 900
        mosaic = (level + rng.integers(0, 8, (H, W))).astype(np.uint16)
        black = np.array([[64.0, 64.5], [63.75, 64.25]]) + 0.5 * k
        frames.append(RawFrame(mosaic, black, 4095 - k, "RGGB", 0.01 * 4**k, 1.8e9 + k, "sim", f"/tmp/cal-{k}.dng"))
    return frames


def check_calibration(got: CalibrationFrames, expected: list[RawFrame]) -> None:
    assert got.frames.dtype == np.uint16 and got.frames.shape == (len(expected), H, W)
    for k, frame in enumerate(expected):
        assert np.array_equal(got.frames[k], frame.mosaic)
    np.testing.assert_array_equal(got.exposures_s, [f.exposure_s for f in expected])
    np.testing.assert_array_equal(got.timestamps, [f.timestamp for f in expected])
    assert got.exposures_s.dtype == np.float64 and got.timestamps.dtype == np.float64
    np.testing.assert_allclose(got.black_level, np.mean([f.black_level for f in expected], axis=0))
    assert got.black_level.shape == (2, 2) and got.black_level.dtype == np.float64
    assert got.white_level == min(f.white_level for f in expected) and isinstance(got.white_level, int)
    assert got.cfa_pattern == "RGGB"


def test_calibration_round_trip(tmp_path):
    path = tmp_path / "run.h5"
    plan = {"sets": [["ambient", "before"], ["dark", "before"], ["ambient", "after"]], "switch": "test"}
    header = make_header(3)
    header.calibration = plan
    with RunFileWriter.create(path, header) as writer:
        assert not writer.calibration_complete("ambient", "before")
        writer.write_calibration("ambient", "before", calibration_data("ambient", "before", 3))
        writer.write_calibration("dark", "before", calibration_data("dark", "before", 1))
        writer.write_position(0, *position_data(SEED, 0))
        writer.write_calibration("ambient", "after", calibration_data("ambient", "after", 2))
        writer.write_calibration("ambient", "after", calibration_data("ambient", "after", 1, seed=7))  # re-taken
        assert writer.calibration_complete("ambient", "before") and not writer.calibration_complete("dark", "after")
        with pytest.raises(RunFileError, match=r"run\.h5: calibration role 'flat' is not one of ambient, dark"):
            writer.write_calibration("flat", "before", calibration_data("ambient", "before"))
        with pytest.raises(RunFileError, match=r"calibration time 'during' is not one of before, after"):
            writer.write_calibration("dark", "during", calibration_data("dark", "before"))
        with pytest.raises(RunFileError, match=r"calibration dark after: 17 frames, expected 1 to 16"):
            writer.write_calibration("dark", "after", calibration_data("dark", "after", 17))
        mixed = calibration_data("dark", "after", 2)
        mixed[1].cfa_pattern = "BGGR"
        with pytest.raises(RunFileError, match=r"calibration dark after: the frames mix CFA patterns \(BGGR, RGGB\)"):
            writer.write_calibration("dark", "after", mixed)
        assert not writer.calibration_complete("dark", "after")  # refused input writes nothing
    with RunFile.open(path) as run:
        assert run.header.calibration == plan
        assert run.calibration_sets() == [("ambient", "before"), ("ambient", "after"), ("dark", "before")]
        check_calibration(run.calibration_frames("ambient"), calibration_data("ambient", "before", 3))
        check_calibration(run.calibration_frames("dark", "before"), calibration_data("dark", "before", 1))
        check_calibration(run.calibration_frames("ambient", "after"), calibration_data("ambient", "after", 1, 7))
        assert run.calibration_frames("dark", "after") is None
        with pytest.raises(RunFileError, match="calibration role 'Ambient'"):
            run.calibration_frames("Ambient")
        check_position(run, SEED, 0)
    with h5py.File(path, "r") as f:  # the layout docs/run-file.md gives
        cal = f["calibration"]
        assert [(r.decode(), w.decode()) for r, w in zip(cal["role"], cal["when"], strict=True)] == list(
            CALIBRATION_SETS
        )
        assert cal["raw"].shape == (4, 16, H, W) and cal["raw"].chunks == (1, 1, H, W)
        assert cal["complete"][()].tolist() == [1, 1, 1, 0] and cal["frame_count"][()].tolist() == [3, 1, 1, 0]
        assert not cal["raw"][1, 1:].any()  # the earlier take's second frame is gone
        assert cal["black_level"].shape == (4, 16, 2, 2) and cal["cfa_pattern"][0, 0] == b"RGGB"


def _as_version_1(path: Path) -> None:
    """A run file as format version 1 wrote it: the same without ``/calibration``."""
    with h5py.File(path, "a") as f:
        del f["calibration"]
        f.attrs["format_version"] = 1
        run = json.loads(f["header/run_json"][()])
        del run["calibration"]
        del f["header/run_json"]
        f["header"].create_dataset("run_json", data=json.dumps(run), dtype=h5py.string_dtype("utf-8"))


def test_a_version_1_file_reads_without_calibration_frames(tmp_path):
    path = tmp_path / "run.h5"
    write_run(path, 3, [0, 2])
    _as_version_1(path)
    with RunFile.open(path) as run:
        assert run.header.calibration == {} and not run.has_calibration_group
        assert run.calibration_frames("ambient") is None and run.calibration_frames("dark", "after") is None
        assert run.calibration_sets() == []
        check_position(run, SEED, 2)
        run.refresh()
    with RunFileWriter.reopen(path) as writer:  # resumed: positions as before, no room for calibration
        assert not writer.calibration_complete("ambient", "before")
        with pytest.raises(RunFileError, match="format version 1 has no room for calibration frames"):
            writer.write_calibration("ambient", "before", calibration_data("ambient", "before"))
        writer.write_position(1, *position_data(SEED, 1))
    with RunFile.open(path) as run:
        assert run.complete.all()


TORN_CALIBRATION_SCRIPT = """
import os, signal, sys
sys.path.insert(0, {tests!r})
from test_runfile import SEED, calibration_data, make_header, position_data
from drivers.contracts.runfile import CALIBRATION_SETS, RunFileWriter

writer = RunFileWriter.create(sys.argv[1], make_header(3))
writer.write_calibration("ambient", "before", calibration_data("ambient", "before", 2))
writer.write_position(0, *position_data(SEED, 0))
# The dark set torn: its first frame and records written and flushed, its complete flag not.
f, slot = writer._f, CALIBRATION_SETS.index(("dark", "before"))
frames = calibration_data("dark", "before", 2)
f["calibration/raw"][slot, 0] = frames[0].mosaic
f["calibration/exposure_s"][slot, 0] = frames[0].exposure_s
f["calibration/frame_count"][slot] = 2
f.flush()
os.kill(os.getpid(), signal.SIGKILL)
"""


def test_a_torn_calibration_set_is_salvaged_away(tmp_path):
    path = tmp_path / "run.h5"
    script = tmp_path / "torn.py"
    script.write_text(TORN_CALIBRATION_SCRIPT.format(tests=str(TESTS_DIR)))
    proc = subprocess.run([sys.executable, str(script), str(path)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    with RunFile.open(path) as run:  # read as it was left: the torn set is not trusted
        assert run.calibration_sets() == [("ambient", "before")]
        assert run.calibration_frames("dark") is None
    with RunFileWriter.reopen(path) as writer:  # salvaged
        assert writer.calibration_complete("ambient", "before") and not writer.calibration_complete("dark", "before")
    with RunFile.open(path) as run:
        assert run.status == "interrupted" and "calibration sets complete: ambient before" in run.status_message
        check_calibration(run.calibration_frames("ambient"), calibration_data("ambient", "before", 2))
        assert run.calibration_frames("dark") is None
        check_position(run, SEED, 0)
    with h5py.File(path, "r") as f:  # nothing of the torn set was copied
        slot = CALIBRATION_SETS.index(("dark", "before"))
        assert f["calibration/raw"].id.get_chunk_info_by_coord((slot, 0, 0, 0)).size == 0
        assert f["calibration/frame_count"][slot] == 0 and np.isnan(f["calibration/exposure_s"][slot]).all()
