"""The demo's data folder: a fresh, timestamped one per demo, with the daemon's configuration.

Older demo folders are removed (the newest ``keep`` of them stay); only folders this module
made (they hold :data:`MARKER`) are ever removed.
"""

from __future__ import annotations

import datetime as _dt
import json
import shutil
from collections.abc import Callable
from pathlib import Path

#: Every demo folder holds this file; only such folders are cleaned up.
MARKER = ".mirrorgonio-demo"


def new_data_dir(root: Path, keep: int = 1, note: Callable[[str], None] = print) -> Path:
    """A fresh, timestamped demo folder under ``root``; older demo folders beyond ``keep`` removed."""
    root.mkdir(parents=True, exist_ok=True)
    previous = sorted(
        (p for p in root.iterdir() if p.is_dir() and (p / MARKER).is_file()),
        key=lambda p: ((p / MARKER).stat().st_mtime_ns, p.name),
    )  # oldest first
    for old in previous[: max(0, len(previous) - keep)]:
        shutil.rmtree(old, ignore_errors=True)
        note(f"removed an older demo folder: {old}")
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    folder, n = root / stamp, 1
    while folder.exists():
        n += 1
        folder = root / f"{stamp}-{n}"
    folder.mkdir()
    (folder / MARKER).write_text("made by `mirrorgonio demo`; removed by a later demo\n")
    return folder


def write_config(folder: Path, rig: Path) -> Path:
    """The daemon's configuration: the simulated rig, data in ``folder/data``."""
    path = folder / "daemon.toml"
    path.write_text(
        "# Written by `mirrorgonio demo` (docs/daemon.md). The token comes from MG_TOKEN.\n"
        f"data_dir = {json.dumps(str(folder / 'data'))}\n"
        f"rig = {json.dumps(str(rig))}\n"
        'host = "127.0.0.1"\n'
        "\n[arm]\n"
        'kind = "simulated"   # the simulated stage over Modbus TCP on loopback, through ModbusArm\n'
        "port = 0\n"
        "\n[arm.simulated]\n"
        "speed_m_s = 1.0\n"
        "accel_m_s2 = 10.0\n"
        "\n[camera]\n"
        'kind = "simulated"\n'
    )
    (folder / "data").mkdir(exist_ok=True)
    return path


def shown(path: Path) -> str:
    """A path relative to the working folder when it is inside it (shorter to read and copy)."""
    path = Path(path)
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)
