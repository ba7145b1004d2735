"""Every configuration and input file a command reads: a bad one ends the command with one
line on standard error naming the file (and the field or option that named it), never a
traceback, before any work is done (``drivers.config_files``)."""

from __future__ import annotations

import os
import re
import threading
import time
from pathlib import Path

import pytest
from conftest import REDUCED_RIG
from typer.testing import CliRunner

from acquisition.cli import app
from acquisition.importer import MAX_CSV_BYTES
from drivers.config_files import MAX_TEXT_BYTES, read_input_bytes, read_input_text, read_toml, require_memory
from drivers.contracts.rig import DEFAULT_RIG_PATH

runner = CliRunner()


def latin1(path: Path) -> Path:
    path.write_bytes("# caméra\nname = 'x'\n".encode("latin-1"))
    return path


def binary(path: Path) -> Path:
    path.write_bytes(bytes(range(256)) * 4)  # NUL bytes and more
    return path


def huge(path: Path) -> Path:
    with open(path, "wb") as f:  # sparse: no disk used, and it must never be read
        f.truncate((MAX_CSV_BYTES if path.suffix == ".csv" else MAX_TEXT_BYTES) + 1)
    return path


def directory(path: Path) -> Path:
    path.mkdir()
    return path


def fifo(path: Path) -> Path:
    os.mkfifo(path)  # nothing ever writes: opening it for reading the usual way blocks for ever
    return path


def device(path: Path) -> Path:
    path.symlink_to("/dev/zero")  # endless: read whole, it would fill the memory
    return path


#: The kinds of bad file, and the words the line must have.
BAD_FILES = {
    "latin-1": (latin1, r"not UTF-8 text: byte 0xe9 at offset 5 \(line 1\)"),
    "binary": (binary, r"a binary file"),
    "too large": (huge, r"(16|64) MiB, more than the (16|64) MiB a [a-zA-Z ]+ may have"),
    "directory": (directory, r"a directory, not a"),
    "fifo": (fifo, r"a FIFO \(named pipe\), not a"),
    "device": (device, r"a character device, not a"),
}


def commands(tmp_path: Path, bad: Path) -> dict[str, list[str]]:
    """Each command with ``bad`` in the place of one of its files (the others good)."""
    run = tmp_path / "run.h5"
    run.write_bytes(b"")  # only its existence is checked before the layout
    raws = tmp_path / "raws"
    raws.mkdir(exist_ok=True)
    csv = tmp_path / "frames.csv"
    csv.write_text("file,position\n")
    out = tmp_path / "out"
    return {
        "serve --config": ["serve", "--config", str(bad)],
        "worker --config": ["worker", "--config", str(bad), "--once"],
        "simulate capture --rig": ["simulate", "capture", "--rig", str(bad), "-o", str(out / "x.dng")],
        "simulate capture --truth": ["simulate", "capture", "--truth", f"{bad}", "-o", str(out / "x.dng")],
        "import --rig": ["import", str(raws), "--csv", str(csv), "--rig", str(bad), "--out", str(out / "r.h5")],
        "import --csv": ["import", str(raws), "--csv", str(bad), "--rig", str(REDUCED_RIG), "--out", str(out / "r.h5")],
        "process --layout": ["process", str(run), "--layout", str(bad), "--scheduler", "none"],
    }


COMMANDS = [
    "serve --config",
    "worker --config",
    "simulate capture --rig",
    "simulate capture --truth",
    "import --rig",
    "import --csv",
    "process --layout",
]


def one_line_error(args: list[str]) -> str:
    result = runner.invoke(app, args)
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    assert result.exit_code != 0
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("error: ")
    return lines[0]


@pytest.mark.parametrize("kind", list(BAD_FILES))
@pytest.mark.parametrize("command", COMMANDS)
def test_a_bad_input_file_is_one_line_naming_it(tmp_path, command, kind):
    make, words = BAD_FILES[kind]
    suffix = ".csv" if command.endswith("--csv") else ".toml"
    bad = make(tmp_path / f"bad{suffix}")
    started = time.monotonic()
    line = one_line_error(commands(tmp_path, bad)[command])
    assert time.monotonic() - started < 5  # the FIFO is never waited for
    assert str(bad) in line and re.search(words, line), line
    if command == "process --layout":
        assert line.startswith(f"error: --layout: {bad}: "), line


def test_a_rig_too_large_for_the_memory_is_refused_before_anything_is_allocated(tmp_path):
    """100 000 × 100 000 px is inside the rig's limits (a side of at most 100 000), but its
    rendering needs terabytes: refused in one line naming the fields, by `simulate capture`
    and by `serve` before its server starts."""
    text = DEFAULT_RIG_PATH.read_text()
    rig = tmp_path / "huge.toml"
    rig.write_text(text.replace("width = 2000", "width = 100000").replace("height = 1312", "height = 100000"))
    line = one_line_error(["simulate", "capture", "--rig", str(rig), "-o", str(tmp_path / "x.dng")])
    assert line.startswith(f"error: {rig}: camera.width × camera.height: rendering a 100000 × 100000 px frame needs")
    assert "TiB, more than the" in line and "this machine can spare" in line
    config = tmp_path / "daemon.toml"
    config.write_text(f'rig = "{rig}"\ndata_dir = "{tmp_path / "data"}"\n')
    line = one_line_error(["serve", "--config", str(config)])
    assert line.startswith(f"error: {rig}: camera.width × camera.height: ")
    assert not (tmp_path / "x.dng").exists()


def test_the_reading_helper_names_the_field_and_keeps_to_its_limits(tmp_path):
    good = tmp_path / "good.toml"
    good.write_text("a = 1\n")
    assert read_toml(good, "rig file", ValueError, field="--rig") == {"a": 1}
    assert read_input_bytes(good, "file", ValueError, limit=6) == b"a = 1\n"
    with pytest.raises(ValueError, match=rf"^--rig: {good}: 6 bytes, more than the 5 bytes a rig file may have$"):
        read_input_bytes(good, "rig file", ValueError, field="--rig", limit=5)
    with pytest.raises(ValueError, match=rf"^light_results: {tmp_path / 'no.json'}: light model not found$"):
        read_input_text(tmp_path / "no.json", "light model", ValueError, field="light_results")
    bom = tmp_path / "bom.csv"
    bom.write_bytes("\ufefffile\n".encode())
    assert read_input_text(bom, "CSV file", ValueError, encoding="utf-8-sig") == "file\n"
    nested = tmp_path / "nested.toml"
    nested.write_text("a = " + "[" * 100_000 + "]" * 100_000 + "\n")
    with pytest.raises(ValueError, match="not valid TOML"):
        read_toml(nested, "rig file", ValueError)


def test_a_read_that_does_not_end_in_time_is_given_up(tmp_path, monkeypatch):
    """The timeout holds whatever the read waits on: here an open that does not return (as on
    a hung network filesystem), the one thing a regular file's read can wait on."""
    slow = tmp_path / "slow.toml"
    slow.write_text("a = 1\n")
    gate = threading.Event()
    real_open = os.open

    def hanging_open(path, flags, *args):  # a hung network filesystem
        if Path(path) == slow:
            gate.wait(10)
        return real_open(path, flags, *args)

    monkeypatch.setattr(os, "open", hanging_open)
    started = time.monotonic()
    with pytest.raises(ValueError, match=rf"^layout: {slow}: the layout file was not read within 0.3 s$"):
        read_input_bytes(slow, "layout file", ValueError, field="layout", timeout_s=0.3)
    assert time.monotonic() - started < 2
    gate.set()


def test_the_memory_budget_is_a_share_of_what_is_available():
    require_memory(1 << 20, "rig.toml: camera.width", "a small frame", ValueError)
    with pytest.raises(ValueError, match=r"^rig.toml: camera.width: a frame needs about 1 TiB, more than the "):
        require_memory(1 << 40, "rig.toml: camera.width", "a frame", ValueError)
