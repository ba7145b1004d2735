"""Frame checksums: bits flipped in a real run file's compressed chunks are caught by the reader,
the processing (one line, or skipped with --ignore-corrupt), `mirrorgonio verify` and the salvage
on resume; outputs keep the run's whole name and never overwrite another run's."""

from __future__ import annotations

import json
import logging
import shutil
import signal
import subprocess
import sys
from types import SimpleNamespace

import h5py
import numpy as np
import pytest
from conftest import REDUCED_RIG, write_simulated_run
from test_runfile import TESTS_DIR, frame_count, write_run
from typer.testing import CliRunner

from acquisition.cli import app
from drivers.contracts.rig import load_rig
from drivers.contracts.runfile import FrameCorruptError, RunFile, RunFileWriter
from processing.light_run.output_guard import outputs_of
from processing.light_run.outputs import skipped_record
from processing.report.trust import skipped_note
from processing.results import Results, results_path_for

runner = CliRunner()
EXPOSURES = [0.0002, 0.001, 0.005]
POSITIONS = (20, 33, 45)
BAD = (33, 2)  # the position and frame the tests corrupt


@pytest.fixture(autouse=True)
def _no_dask(monkeypatch):
    monkeypatch.setenv("MG_SCHEDULER", "none")


@pytest.fixture(scope="module")
def clean_run(tmp_path_factory):
    """A simulated run file named with a dot (``yaw-0.05.h5``): three positions of three exposures."""
    folder = tmp_path_factory.mktemp("run")
    return write_simulated_run(folder / "yaw-0.05.h5", load_rig(REDUCED_RIG), "run-yaw", POSITIONS, EXPOSURES, seed=3)


def flip_bit(path, position: int, frame: int, bit: int, group: str = "frames") -> None:
    """Flip one bit of a stored frame's compressed chunk, by its offset in the file (as a disk
    would, under HDF5)."""
    with h5py.File(path, "r", swmr=True) as f:
        info = f[f"{group}/raw"].id.get_chunk_info_by_coord((position, frame, 0, 0))
    assert info.size and 0 <= bit < 8 * info.size
    with open(path, "r+b") as stream:
        stream.seek(info.byte_offset + bit // 8)
        byte = stream.read(1)[0]
        stream.seek(info.byte_offset + bit // 8)
        stream.write(bytes([byte ^ (1 << (bit % 8))]))


@pytest.fixture()
def corrupt_run(clean_run, tmp_path):
    path = tmp_path / clean_run.name
    shutil.copy(clean_run, path)
    flip_bit(path, *BAD, bit=8 * 1000 + 3)
    return path


def test_every_single_bit_flip_in_a_compressed_frame_is_caught(clean_run, tmp_path):
    """60 flips at random bits of one frame's chunk: each is a FrameCorruptError naming the
    position and the frame (LZ4 alone decodes most such flips to other pixels, silently)."""
    path = tmp_path / "flips.h5"
    shutil.copy(clean_run, path)
    with h5py.File(path, "r", swmr=True) as f:
        size = f["frames/raw"].id.get_chunk_info_by_coord((*BAD, 0, 0)).size
    caught = 0
    for bit in np.random.default_rng(7).choice(8 * size, 60, replace=False):
        flip_bit(path, *BAD, bit=int(bit))
        with RunFile.open(path) as run, pytest.raises(FrameCorruptError) as raised:
            run.frame(*BAD)
        assert raised.value.corrupt.position == 33 and raised.value.corrupt.frame == 2
        caught += 1
        flip_bit(path, *BAD, bit=int(bit))  # back as it was
    assert caught == 60
    with RunFile.open(path) as run:
        assert run.checksummed and run.corrupt_frames() == []


def test_process_stops_at_a_corrupt_frame_in_one_line(corrupt_run, tmp_path):
    result = runner.invoke(app, ["process", str(corrupt_run), "--steps", "hdr", "--out", str(tmp_path / "out")])
    assert result.exit_code == 2
    assert result.stdout.strip() == ""
    assert result.stderr.strip() == (
        f"error: {corrupt_run}: position 33 frame 2 (exposure index 2, 0.005 s) fails its checksum "
        "(corrupt data: the stored bytes differ from those written); --ignore-corrupt processes the rest"
    )
    assert not (tmp_path / "out").exists()  # before any work


def test_ignore_corrupt_processes_the_rest_and_says_what_it_skipped(corrupt_run, tmp_path):
    out = tmp_path / "out"
    result = runner.invoke(app, ["process", str(corrupt_run), "--ignore-corrupt", "--steps", "hdr", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert result.stderr.strip() == (
        f"warning: {corrupt_run}: skipped positions 33 (--ignore-corrupt): 1 corrupt frames: position 33 frame 2 "
        "(exposure index 2, 0.005 s) fails its checksum (corrupt data: the stored bytes differ from those written)"
    )
    assert "2 positions" in result.stdout
    with Results.open(out / "yaw-0.05.results.h5") as results:
        assert np.flatnonzero(results.hdr_done).tolist() == [20, 45]
    assert sorted(p.name for p in (out / "yaw-0.05.hdr").glob("*.png")) == ["position-020.png", "position-045.png"]


def test_the_light_model_and_the_report_say_what_was_skipped(corrupt_run):
    """What the sources step records of the skip (the step itself takes a minute here: the
    functions it calls, on the real corrupt frame)."""
    with RunFile.open(corrupt_run) as run:
        corrupt = run.corrupt_frames()
    model = SimpleNamespace(provenance={"skipped_corrupt": skipped_record(corrupt)})
    assert model.provenance["skipped_corrupt"] == {
        "positions": [33],
        "frames": [
            {
                "where": "position 33",
                "position": 33,
                "frame": 2,
                "exposure_s": 0.005,
                "cause": "fails its checksum (corrupt data: the stored bytes differ from those written)",
            }
        ],
    }
    note = skipped_note(SimpleNamespace(provenance=json.loads(json.dumps(model.provenance))))  # as saved, read back
    assert "Corrupt frames skipped" in note and "positions left out: 33" in note and "position 33 frame 2" in note


def test_outputs_keep_the_whole_run_name(tmp_path):
    names = [p.name for p in outputs_of(tmp_path / "yaw-0.05.h5", tmp_path)]
    assert names == [
        "yaw-0.05.results.h5",
        "yaw-0.05.hdr",
        "yaw-0.05.light.json",
        "yaw-0.05.ies",
        "yaw-0.05.ldt",
        "yaw-0.05.tm25ray",
        "yaw-0.05.pbrt",
        "yaw-0.05.report.html",
        "yaw-0.05.rig-fitted.toml",
    ]
    assert results_path_for(tmp_path / "a.1.h5").name == "a.1.results.h5"


def test_verify_names_the_corrupt_frames_and_exits_non_zero(corrupt_run, clean_run, tmp_path):
    flip_bit(corrupt_run, 20, 0, bit=100)
    bad = runner.invoke(app, ["verify", str(corrupt_run)])
    assert bad.exit_code == 1
    lines = bad.stdout.strip().splitlines()
    assert "3 of 66 positions complete, 9 frames" in lines[0] and "frames checksummed (Fletcher32)" in lines[0]
    assert lines[1].startswith("  corrupt: position 20 frame 0 (exposure index 0, 0.0002 s) fails its checksum")
    assert lines[2].startswith("  corrupt: position 33 frame 2 (exposure index 2, 0.005 s) fails its checksum")
    assert lines[3] == f"{corrupt_run}: CORRUPT: 2 corrupt frames (position 20, position 33), 0 structure problems"
    good = runner.invoke(app, ["verify", str(clean_run)])
    assert good.exit_code == 0, good.output
    assert good.stdout.strip().splitlines()[-1] == f"{clean_run}: ok: every frame reads back through its checksum"
    text = tmp_path / "notes.h5"
    text.write_text("not a run file")
    foreign = runner.invoke(app, ["verify", str(text)])
    assert foreign.exit_code == 2 and foreign.stderr.strip() == f"error: {text}: not an HDF5 file"


def test_verify_says_a_file_without_checksums_carries_none(tmp_path):
    """A run file whose frames were written without Fletcher32 (the same layout otherwise) reads
    as before, and verify says it carries no checksums."""
    path = tmp_path / "old.h5"
    write_run(path, 3, range(3))
    with h5py.File(path, "a") as f:
        frames = f["frames/raw"][()]
        del f["frames/raw"]
        plain = f["frames"].create_dataset("raw", data=frames, chunks=(1, 1, *frames.shape[2:]), compression=32004)
        assert not plain.fletcher32
    with RunFile.open(path) as run:
        assert not run.checksummed and run.frames(2).shape[0] == frame_count(2)
    result = runner.invoke(app, ["verify", str(path)])
    assert result.exit_code == 0, result.output
    assert "frames carry NO checksums" in result.stdout and "no frame checksums" in result.stdout


KILLED_WRITER = """
import os, signal, sys
sys.path.insert(0, {tests!r})
from test_runfile import SEED, make_header, position_data
from drivers.contracts.runfile import RunFileWriter

writer = RunFileWriter.create(sys.argv[1], make_header(4))
for i in range(3):
    writer.write_position(i, *position_data(SEED, i))
os.kill(os.getpid(), signal.SIGKILL)
"""


def test_the_salvage_on_resume_drops_a_corrupt_position(tmp_path, caplog):
    path = tmp_path / "killed.h5"
    script = tmp_path / "killed.py"
    script.write_text(KILLED_WRITER.format(tests=str(TESTS_DIR)))
    proc = subprocess.run([sys.executable, str(script), str(path)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    flip_bit(path, 1, 1, bit=4242)
    with caplog.at_level(logging.WARNING, logger="mirrorgonio.runfile"), RunFileWriter.reopen(path) as writer:
        assert writer.complete.tolist() == [True, False, True, False]  # position 1 to be taken again
    assert any("salvage: position 1 frame 1 fails its checksum" in r.getMessage() for r in caplog.records)
    with RunFile.open(path) as run:
        assert run.status == "interrupted" and "positions 1 were unreadable or failed their checksums" in (
            run.status_message
        )
        assert run.checksummed and run.corrupt_frames() == []


def test_a_resume_without_salvage_drops_a_corrupt_position_too(tmp_path, caplog):
    path = tmp_path / "paused.h5"
    write_run(path, 4, range(3))
    flip_bit(path, 2, 0, bit=77)
    with caplog.at_level(logging.WARNING, logger="mirrorgonio.runfile"), RunFileWriter.reopen(path) as writer:
        assert writer.first_incomplete() == 2
    assert any("position 2 frame 0 fails its checksum" in r.getMessage() for r in caplog.records)


def test_runs_named_alike_after_a_dot_keep_their_own_outputs(clean_run, tmp_path):
    """``a.1.h5`` and ``a.2.h5`` in one --out folder: distinct files. A run of the same name but
    another run id is refused before any work, and replaces them with --overwrite."""
    runs = tmp_path / "runs"
    (runs / "other").mkdir(parents=True)
    for name in ("a.1.h5", "a.2.h5"):
        shutil.copy(clean_run, runs / name)
    out = tmp_path / "out"
    both = runner.invoke(
        app, ["process", str(runs / "a.1.h5"), str(runs / "a.2.h5"), "--steps", "hdr", "--out", str(out)]
    )
    assert both.exit_code == 0, both.output
    assert sorted(p.name for p in out.iterdir()) == ["a.1.hdr", "a.1.results.h5", "a.2.hdr", "a.2.results.h5"]
    other = runs / "other" / "a.1.h5"  # the same name, another run
    shutil.copy(clean_run, other)
    with h5py.File(other, "a") as f:
        run_json = json.loads(f["header/run_json"][()])
        run_json["run_id"] = "run-other"
        del f["header/run_json"]
        f["header"].create_dataset("run_json", data=json.dumps(run_json), dtype=h5py.string_dtype("utf-8"))
    before = (out / "a.1.results.h5").stat().st_mtime_ns
    refused = runner.invoke(app, ["process", str(other), "--steps", "hdr", "--out", str(out)])
    assert refused.exit_code == 2
    assert refused.stderr.strip() == (
        f"error: {out / 'a.1.results.h5'}: holds the outputs of another run (run-yaw), not of run run-other "
        f"({other}): pass --overwrite to replace it, or choose another --out"
    )
    assert (out / "a.1.results.h5").stat().st_mtime_ns == before
    stray = tmp_path / "stray"
    stray.mkdir()
    (stray / "a.1.ies").write_text("someone's file")
    unknown = runner.invoke(app, ["process", str(other), "--steps", "hdr", "--out", str(stray)])
    assert unknown.exit_code == 2 and "a.1.ies: already there and not known to be written for run run-other" in (
        unknown.stderr
    )
    again = runner.invoke(app, ["process", str(runs / "a.1.h5"), "--steps", "hdr", "--out", str(out), "--no-images"])
    assert again.exit_code == 0, again.output  # the same run's outputs are its own to replace
    replaced = runner.invoke(
        app, ["process", str(other), "--steps", "hdr", "--out", str(out), "--overwrite", "--no-images"]
    )
    assert replaced.exit_code == 0, replaced.output
    with h5py.File(out / "a.1.results.h5", "r") as results:
        assert results.attrs["run_id"] == "run-other"
