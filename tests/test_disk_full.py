"""Write failures on a small file system the test mounts (a tmpfs; skipped, with the reason,
where mounting is not allowed): a full disk and a read-only one, at the level each happens —
the run file's writer, the catalog, and the daemon's run engine through its API."""

from __future__ import annotations

import errno
import gc
import os
import subprocess
from pathlib import Path

import h5py
import numpy as np
import pytest
from test_runfile import SEED, make_header, position_data

from drivers.contracts.runfile import RunFile, RunFileWriteError, RunFileWriter

N_POSITIONS = 20


@pytest.fixture()
def small_fs(tmp_path):
    """``mount(path, size_kb)``: a tmpfs of that size at ``path``, unmounted at the end."""
    mounted: list[Path] = []

    def mount(path: Path, size_kb: int) -> Path:
        if os.geteuid() != 0:
            pytest.skip("mounting a small file system needs root")
        path.mkdir(parents=True, exist_ok=True)
        result = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={size_kb}k", "tmpfs", str(path)], capture_output=True, text=True
        )
        if result.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here: {result.stderr.strip()}")
        mounted.append(path)
        return path

    yield mount
    for path in reversed(mounted):
        subprocess.run(["umount", "-l", str(path)], check=False)


def fill(path: Path, leave: int = 0) -> Path:
    """A file taking all the free space of ``path``'s file system but ``leave`` bytes."""
    free = os.statvfs(path.parent).f_bavail * os.statvfs(path.parent).f_frsize
    block = b"\xa5" * 65536
    with open(path, "wb") as f:
        todo = max(free - leave, 0)
        try:
            while todo > 0:
                todo -= f.write(block[: min(todo, len(block))])
                f.flush()
        except OSError as exc:
            assert exc.errno == errno.ENOSPC
    return path


def noisy_position(i: int):
    """Position ``i`` of test_runfile's run, its frames noise (which does not compress)."""
    measured, times, frames = position_data(SEED, i)
    for k, frame in enumerate(frames):
        frame.mosaic[:] = np.random.default_rng([SEED, i, k]).integers(0, 4096, frame.mosaic.shape)
    return measured, times, frames


def hdf5_open_objects() -> int:
    gc.collect()
    return h5py.h5f.get_obj_count(h5py.h5f.OBJ_ALL, h5py.h5f.OBJ_ALL)


def assert_positions_intact(path: Path, positions) -> None:
    with RunFile.open(path) as f:
        assert list(np.flatnonzero(f.complete)) == list(positions)
        for i in positions:
            expected = [frame.mosaic for frame in noisy_position(i)[2]]
            np.testing.assert_array_equal(f.frames(i)[: len(expected)], expected)


def test_a_write_the_disk_refuses_is_one_line_and_every_committed_position_survives(small_fs, tmp_path):
    disk = small_fs(tmp_path / "disk", 1024)
    baseline = hdf5_open_objects()
    filler = fill(disk / "filler", leave=300_000)
    path = disk / "run.h5"
    writer = RunFileWriter.create(path, make_header(N_POSITIONS))
    written: list[int] = []
    with pytest.raises(RunFileWriteError) as failure:
        for i in range(N_POSITIONS):
            writer.write_position(i, *noisy_position(i))
            written.append(i)
    assert str(failure.value) == f"no space left on device writing {path} (position {len(written)})"
    assert failure.value.errno == errno.ENOSPC and 5 <= len(written) < N_POSITIONS
    # The writer writes nothing more, and closes: HDF5 keeps nothing of the file open (a file
    # it could not close crashed the process at its next flush or at exit).
    with pytest.raises(RunFileWriteError, match="stopped after a failed write: no space left on device"):
        writer.set_status("failed", str(failure.value))
    writer.close()
    assert hdf5_open_objects() == baseline
    assert_positions_intact(path, written)
    # Space again: the run goes on (the file is salvaged, as a killed writer's) to its end.
    filler.unlink()
    with RunFileWriter.reopen(path) as writer:
        assert writer.first_incomplete() == len(written)
        for i in range(len(written), N_POSITIONS):
            writer.write_position(i, *noisy_position(i))
        writer.set_status("complete")
    assert hdf5_open_objects() == baseline
    assert_positions_intact(path, range(N_POSITIONS))
