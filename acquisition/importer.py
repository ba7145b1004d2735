"""Build a run file from raw files captured elsewhere (``mirrorgonio import``).

The input is a folder of raw files (any format :func:`drivers.raw_decode.decode_raw` reads:
DNG, NEF, CR2, ARW, ...), a CSV that says which schedule position each file belongs to (or
which calibration set: ambient or dark frames, before or after the sweep), and the rig TOML
whose schedule those positions index (``docs/import.md``). The output is
the same run file the daemon writes (``docs/run-file.md``), so it processes the same way.

Nothing half-done is ever written. The import runs in three stages:

1. the rig and the CSV are read and checked (columns, values, files exist, no file named
   twice, positions within the schedule) without decoding a single raw file;
2. every raw file is decoded once to check it (readable, one frame size that matches the
   rig's ``camera.width`` x ``camera.height``, one CFA layout, a positive exposure, no
   position with two frames of the same exposure); the mosaics are not kept, so memory
   stays bounded by one frame;
3. only then is the run built, in a hidden temporary file in the output's folder, decoding
   each file again, and renamed onto the output path once complete. Any failure removes
   the temporary file.

Every error is a :class:`RunImportError` of one line naming the CSV line, the field or
the file.
"""

from __future__ import annotations

import contextlib
import csv
import io
import math
import os
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

from drivers.camera import RawFrame
from drivers.config_files import read_input_text
from drivers.contracts.rig import Rig, RigError, load_rig
from drivers.contracts.runfile import (
    CALIBRATION_MAX_FRAMES,
    CALIBRATION_ROLES,
    CALIBRATION_SETS,
    CALIBRATION_WHENS,
    PositionTimes,
    RunFileError,
    RunFileWriter,
    RunHeader,
    file_sha256,
)
from drivers.contracts.version import __version__
from drivers.errors import RawFileError
from drivers.pose import Pose
from drivers.raw_decode import RAW_EXTENSIONS, decode_raw

if TYPE_CHECKING:
    from _csv import Reader as CsvReader  # what csv.reader returns (typeshed's name for it)

#: The largest import CSV read, in bytes: a line is under 200 bytes, so some 300 000 frames.
MAX_CSV_BYTES = 64 * 2**20
#: Columns every import CSV must have.
REQUIRED_COLUMNS = ("file", "position")
#: The measured tool pose, optional, all six or none: metres and degrees (like the rig TOML).
POSE_COLUMNS = ("x_m", "y_m", "z_m", "rx_deg", "ry_deg", "rz_deg")
#: What a row's frame is (the ``role`` column): a frame of the sweep, at a position, or a
#: calibration frame (``docs/run-file.md``), in the set ``when`` names.
ROLES = ("sweep", *CALIBRATION_ROLES)
#: Every column an import CSV may have.
KNOWN_COLUMNS = (*REQUIRED_COLUMNS, "exposure_s", "role", "when", *POSE_COLUMNS)

#: Two exposures this close (relative) are the same exposure: a repeated frame.
SAME_EXPOSURE_RTOL = 1e-6

Progress = Callable[[str, int, int], None]
"""``progress(stage, done, total)``; ``stage`` is ``"checking"`` or ``"writing"``."""


class RunImportError(ValueError):
    """Input that cannot be imported (one line naming the CSV line, the field or the file)."""


@dataclass(frozen=True)
class ImportRow:
    """One frame, as the CSV gives it.

    Attributes
    ----------
    line : int
        The CSV line it was read from (the header is line 1).
    name : str
        The ``file`` cell as written.
    path : Path
        The raw file, resolved against the folder.
    position : int or None
        The schedule position; None for a calibration frame.
    exposure_s : float or None
        The CSV's exposure time, which overrides the file's; None to read it from the file.
    pose : Pose or None
        The measured tool pose the CSV gives (metres, radians), or None.
    role : str
        ``sweep``, or a calibration frame's role: ``ambient`` or ``dark``.
    when : str
        A calibration frame's set: ``before`` or ``after`` the sweep; empty for a sweep frame.
    """

    line: int
    name: str
    path: Path
    position: int | None
    exposure_s: float | None = None
    pose: Pose | None = None
    role: str = "sweep"
    when: str = ""


@dataclass(frozen=True)
class _Checked:
    """What stage 2 learnt of one file (the mosaic itself is not kept)."""

    shape: tuple[int, int]
    cfa_pattern: str
    exposure_s: float
    timestamp: float
    camera_id: str


@dataclass
class ImportReport:
    """What an import wrote.

    Attributes
    ----------
    run_file : Path
        The run file written.
    run_id : str
        Its run identifier.
    frames : int
        Frames imported.
    n_positions : int
        Positions of the rig's schedule (the run's length).
    positions_with_frames : list of int
        Positions written, complete.
    calibration_sets : dict
        The calibration sets written, ``"ambient before"`` and so on, with their frame counts.
    empty_positions : list of int
        Positions the CSV gives no frame for, left incomplete in the run file.
    frame_shape : tuple of int
        ``(height, width)`` of the mosaics.
    cfa_pattern : str
        The mosaics' CFA tile.
    exposures_s : list of float
        Every exposure time of the positions' frames, sorted, without repeats.
    cameras : list of str
        The cameras the files name.
    ignored_files : list of str
        Raw files in the folder that the CSV does not name (not imported).
    exposure_overrides : int
        Frames whose exposure time came from the CSV rather than from the file.
    """

    run_file: Path
    run_id: str
    frames: int
    n_positions: int
    positions_with_frames: list[int]
    empty_positions: list[int]
    frame_shape: tuple[int, int]
    cfa_pattern: str
    exposures_s: list[float]
    cameras: list[str]
    ignored_files: list[str] = field(default_factory=list)
    exposure_overrides: int = 0
    calibration_sets: dict[str, int] = field(default_factory=dict)


def format_ranges(values: list[int]) -> str:
    """``[0, 1, 2, 5, 7, 8]`` as ``"0-2, 5, 7-8"``."""
    parts, values = [], sorted(values)
    i = 0
    while i < len(values):
        j = i
        while j + 1 < len(values) and values[j + 1] == values[j] + 1:
            j += 1
        parts.append(str(values[i]) if i == j else f"{values[i]}-{values[j]}")
        i = j + 1
    return ", ".join(parts)


# --- stage 1: the CSV ---------------------------------------------------------------------
def _number(text: str, where: str, column: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise RunImportError(f"{where}: {column}: {text!r} is not a number") from None
    if not math.isfinite(value):
        raise RunImportError(f"{where}: {column}: must be a finite number (got {text!r})")
    return value


def read_import_csv(csv_path: str | Path, folder: str | Path, n_positions: int) -> list[ImportRow]:
    """Read and check an import CSV without decoding any raw file.

    Parameters
    ----------
    csv_path : str or Path
        The CSV (UTF-8, comma-separated, a header line; ``docs/import.md``).
    folder : str or Path
        The folder relative ``file`` cells are resolved against.
    n_positions : int
        The schedule's length: a ``position`` must be ``0 <= position < n_positions``.

    Returns
    -------
    list of ImportRow
        One per frame, in the CSV's order.

    Raises
    ------
    RunImportError
        A missing or unknown column, a bad value, a file that does not exist or is named
        twice, a position outside the schedule, rows of one position giving different
        poses, or no rows at all; the message names the CSV line and the column.
    """
    csv_path, folder = Path(csv_path), Path(folder)
    text = read_input_text(csv_path, "CSV file", RunImportError, limit=MAX_CSV_BYTES, encoding="utf-8-sig")
    try:
        return _read_rows(csv.reader(io.StringIO(text, newline="")), csv_path, folder, n_positions)
    except csv.Error as exc:
        raise RunImportError(f"{csv_path}: not a valid CSV file ({exc})") from None


def _read_rows(reader: CsvReader, csv_path: Path, folder: Path, n_positions: int) -> list[ImportRow]:
    columns = _read_columns(reader, csv_path)
    pose_given = any(name in columns for name in POSE_COLUMNS)
    rows: list[ImportRow] = []
    seen_files: dict[Path, int] = {}
    position_pose: dict[int, tuple[Pose, int]] = {}
    set_sizes: dict[tuple[str, str], int] = {}  # the frames of each calibration set so far
    for cells in reader:
        line = reader.line_num
        where = f"{csv_path}: line {line}"
        if not any(cell.strip() for cell in cells):
            continue  # a blank line
        if len(cells) > len(columns):
            raise RunImportError(f"{where}: {len(cells)} fields but the header names {len(columns)} columns")
        values = {name: (cells[i].strip() if i < len(cells) else "") for i, name in enumerate(columns)}
        name = values["file"]
        path = _row_file(name, where, folder)
        if path in seen_files:
            raise RunImportError(f"{where}: file: {name!r} repeats the frame of line {seen_files[path]}")
        seen_files[path] = line
        role, when = _row_role(values, where)
        position = _row_position(values["position"], where, n_positions) if role == "sweep" else None
        if position is None:
            _check_calibration_row(values, where, (role, when), pose_given)
            set_sizes[role, when] = set_sizes.get((role, when), 0) + 1
            if set_sizes[role, when] > CALIBRATION_MAX_FRAMES:
                raise RunImportError(
                    f"{where}: role: more than {CALIBRATION_MAX_FRAMES} {role} frames {when} the sweep "
                    f"(at most {CALIBRATION_MAX_FRAMES} a set)"
                )
        exposure = _row_exposure(values.get("exposure_s", ""), where)
        pose = _row_pose(values, where) if pose_given and position is not None else None
        if pose is not None and position is not None:
            if position in position_pose:
                other, other_line = position_pose[position]
                if other != pose:
                    raise RunImportError(
                        f"{where}: x_m..rz_deg: position {position} was given another pose on "
                        f"line {other_line} (one measured pose per position)"
                    )
            else:
                position_pose[position] = (pose, line)
        rows.append(ImportRow(line, name, path, position, exposure, pose, role, when))
    if not rows:
        raise RunImportError(f"{csv_path}: no frames: the CSV has a header but no rows")
    if all(row.position is None for row in rows):
        raise RunImportError(f"{csv_path}: no frames of the sweep: every row is a calibration frame")
    return rows


def _row_role(values: dict[str, str], where: str) -> tuple[str, str]:
    """The ``role`` and ``when`` cells: ``sweep`` (the default) without a time, or a calibration
    role with its time (``before`` by default)."""
    role = values.get("role", "").lower() or "sweep"
    if role not in ROLES:
        raise RunImportError(f"{where}: role: {values['role']!r} is not one of {', '.join(ROLES)}")
    when = values.get("when", "").lower()
    if role == "sweep":
        if when:
            raise RunImportError(f"{where}: when: only for calibration frames (role ambient or dark), not sweep")
        return role, ""
    when = when or "before"
    if when not in CALIBRATION_WHENS:
        raise RunImportError(f"{where}: when: {values['when']!r} is not one of {', '.join(CALIBRATION_WHENS)}")
    return role, when


def _check_calibration_row(values: dict[str, str], where: str, which: tuple[str, str], pose_given: bool) -> None:
    """Check that a calibration frame's row names no position and no pose (it has neither)."""
    role = which[0]
    frame = f"{'an' if role == 'ambient' else 'a'} {role} frame"
    if values["position"]:
        raise RunImportError(
            f"{where}: position: {frame} belongs to no position (leave it empty; got {values['position']!r})"
        )
    if pose_given and any(values[name] for name in POSE_COLUMNS):
        raise RunImportError(f"{where}: x_m..rz_deg: {frame} has no pose (leave them empty)")


def _read_columns(reader: CsvReader, csv_path: Path) -> list[str]:
    """The header line's column names (lower case), checked: known, required, pose as a set of six."""
    header = next(reader, None)
    while header is not None and not any(cell.strip() for cell in header):
        header = next(reader, None)
    if header is None:
        raise RunImportError(f"{csv_path}: empty CSV (expected a header line such as 'file,position,exposure_s')")
    where = f"{csv_path}: line {reader.line_num}"
    columns = [cell.strip().lower() for cell in header]
    for i, name in enumerate(columns):
        if not name:
            raise RunImportError(f"{where}: column {i + 1} has no name")
        if name not in KNOWN_COLUMNS:
            raise RunImportError(f"{where}: unknown column {name!r} (known: {', '.join(KNOWN_COLUMNS)})")
        if name in columns[:i]:
            raise RunImportError(f"{where}: column {name!r} appears twice")
    for name in REQUIRED_COLUMNS:
        if name not in columns:
            raise RunImportError(f"{where}: missing required column {name!r} (the header must name file and position)")
    pose_given = [name for name in POSE_COLUMNS if name in columns]
    if pose_given and len(pose_given) < len(POSE_COLUMNS):
        missing = [name for name in POSE_COLUMNS if name not in columns]
        raise RunImportError(
            f"{where}: missing column {missing[0]!r}: pose columns come as a set of six ({', '.join(POSE_COLUMNS)})"
        )
    return columns


def _row_file(name: str, where: str, folder: Path) -> Path:
    """The ``file`` cell as an existing file, resolved (relative to ``folder``)."""
    if not name:
        raise RunImportError(f"{where}: file: empty")
    path = Path(name).expanduser()
    path = path if path.is_absolute() else folder / path
    if not path.exists():
        raise RunImportError(f"{where}: file: {name!r} not found in {folder}")
    if not path.is_file():
        raise RunImportError(f"{where}: file: {name!r} is not a file")
    return path.resolve()


def _row_position(text: str, where: str, n_positions: int) -> int:
    """The ``position`` cell: a whole number within the schedule."""
    if not text:
        raise RunImportError(f"{where}: position: empty")
    try:
        position = int(text)
    except ValueError:
        raise RunImportError(f"{where}: position: {text!r} is not a whole number") from None
    if not 0 <= position < n_positions:
        raise RunImportError(f"{where}: position: {position} is outside the rig's schedule (0 to {n_positions - 1})")
    return position


def _row_exposure(text: str, where: str) -> float | None:
    """The ``exposure_s`` cell: a positive number of seconds, or None when empty."""
    if not text:
        return None
    exposure = _number(text, where, "exposure_s")
    if not exposure > 0:
        raise RunImportError(f"{where}: exposure_s: must be a positive number of seconds (got {text!r})")
    return exposure


def _row_pose(values: dict[str, str], where: str) -> Pose | None:
    """The pose cells (metres, degrees) as a Pose (radians): all six given, or None when all are empty."""
    cells_given = [name for name in POSE_COLUMNS if values[name]]
    if cells_given and len(cells_given) < len(POSE_COLUMNS):
        empty = next(name for name in POSE_COLUMNS if not values[name])
        raise RunImportError(f"{where}: {empty}: empty; give all six pose values or none")
    if not cells_given:
        return None
    x, y, z, rx, ry, rz = (_number(values[name], where, name) for name in POSE_COLUMNS)
    return Pose(x, y, z, math.radians(rx), math.radians(ry), math.radians(rz))


# --- stage 2: the raw files ---------------------------------------------------------------
def _decode(row: ImportRow, csv_path: Path) -> RawFrame:
    try:
        return decode_raw(row.path, exposure_s=row.exposure_s)  # the CSV's exposure, when it gives one
    except RawFileError as exc:
        raise RunImportError(f"{csv_path}: line {row.line}: {exc}") from None


def _check_frames(
    rows: list[ImportRow], csv_path: Path, rig_path: Path, rig: Rig, progress: Progress | None
) -> list[_Checked]:
    checked: list[_Checked] = []
    first: ImportRow | None = None
    brackets: dict[int, list[tuple[float, int]]] = {}
    for done, row in enumerate(rows):
        frame = _decode(row, csv_path)
        where = f"{csv_path}: line {row.line}"
        shape = (int(frame.mosaic.shape[0]), int(frame.mosaic.shape[1]))
        if checked:
            size, ref = checked[0], first
            assert ref is not None  # the row of checked[0]
            if shape != size.shape:
                raise RunImportError(
                    f"{where}: {row.name} is {shape[1]}x{shape[0]} but line {ref.line} ({ref.name}) is "
                    f"{size.shape[1]}x{size.shape[0]}: the frames mix sizes"
                )
            if frame.cfa_pattern != size.cfa_pattern:
                raise RunImportError(
                    f"{where}: {row.name} has CFA {frame.cfa_pattern} but line {ref.line} "
                    f"({ref.name}) has {size.cfa_pattern}: the frames mix CFA layouts"
                )
        else:
            first = row
            width, height = rig.camera.width, rig.camera.height
            if (height, width) != shape:
                raise RunImportError(
                    f"{rig_path}: camera.width x camera.height is {width}x{height} but the raw files "
                    f"are {shape[1]}x{shape[0]} (line {row.line}: {row.name})"
                )
        exposure = row.exposure_s if row.exposure_s is not None else float(frame.exposure_s)
        if not (exposure > 0 and math.isfinite(exposure)):  # decode_raw refuses these; be sure
            raise RunImportError(f"{where}: exposure_s: {row.name} has no positive exposure time")
        if row.position is not None:  # calibration sets may repeat an exposure (several dark frames)
            for other, other_line in brackets.setdefault(row.position, []):
                if math.isclose(other, exposure, rel_tol=SAME_EXPOSURE_RTOL):
                    raise RunImportError(
                        f"{where}: position {row.position} already has a frame of exposure {exposure:g} s "
                        f"(line {other_line}): the frame is repeated"
                    )
            brackets[row.position].append((exposure, row.line))
        checked.append(_Checked(shape, frame.cfa_pattern, exposure, float(frame.timestamp), frame.camera_id))
        del frame
        if progress:
            progress("checking", done + 1, len(rows))
    return checked


# --- stage 3: the run file ----------------------------------------------------------------
def _bracket(by_position: dict[int, list[int]], checked: list[_Checked]) -> dict:
    """``fixed`` with the exposures when every position has the same set, else ``auto``."""
    sets = {tuple(sorted(checked[k].exposure_s for k in ks)) for ks in by_position.values()}
    if len(sets) == 1:
        return {"mode": "fixed", "exposures_s": list(next(iter(sets))), "source": "import"}
    return {"mode": "auto", "source": "import"}


def _unused_temp(out: Path) -> Path:
    return out.with_name(f".{out.name}.import-{uuid.uuid4().hex[:12]}")


def _remove_temp(tmp: Path) -> None:
    for suffix in ("", ".tmp", ".lock"):
        with contextlib.suppress(OSError):
            Path(str(tmp) + suffix).unlink()


def _publish(tmp: Path, out: Path) -> None:
    """Move the finished run onto ``out`` without ever replacing an existing file."""
    try:
        os.link(tmp, out)  # fails if out exists: never overwrite a run created meanwhile
    except FileExistsError:
        raise RunImportError(f"{out}: already exists (not replaced)") from None
    except OSError:  # a file system without hard links
        if out.exists():
            raise RunImportError(f"{out}: already exists (not replaced)") from None
        os.replace(tmp, out)
    else:
        tmp.unlink()
    with contextlib.suppress(OSError):
        fd = os.open(out.parent, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def import_run(
    folder: str | Path,
    csv_path: str | Path,
    rig_path: str | Path,
    out: str | Path,
    *,
    run_id: str | None = None,
    metadata: dict | None = None,
    progress: Progress | None = None,
) -> ImportReport:
    """Build a run file from a folder of raw files, a CSV of their positions and a rig.

    Parameters
    ----------
    folder : str or Path
        The raw files' folder; the CSV's relative ``file`` cells are resolved against it.
    csv_path : str or Path
        The CSV: ``file``, ``position``, optional ``exposure_s`` and pose columns
        (``docs/import.md``).
    rig_path : str or Path
        The rig TOML the frames were taken with; its schedule defines the positions.
    out : str or Path
        The run file to create; it must not exist.
    run_id : str, optional
        The run's identifier (default: the output file's stem).
    metadata : dict, optional
        ``operator``, ``light_source``, ``notes``, stored in the run's header.
    progress : callable, optional
        ``progress(stage, done, total)`` after each file, ``stage`` ``"checking"`` then
        ``"writing"``.

    Returns
    -------
    ImportReport
        What was written, and which positions were left without frames.

    Raises
    ------
    RunImportError
        Any bad input (one line naming the CSV line, the field or the file); nothing has
        been written then.
    """
    folder, csv_path, rig_path, out = Path(folder), Path(csv_path), Path(rig_path), Path(out)
    rig = _check_destination(folder, rig_path, out)
    tool_poses, light_poses = rig.tool_poses(), rig.light_poses()
    n = len(tool_poses)

    rows = read_import_csv(csv_path, folder, n)
    checked = _check_frames(rows, csv_path, rig_path, rig, progress)

    by_position: dict[int, list[int]] = {}  # the rows of each position with frames
    by_set: dict[tuple[str, str], list[int]] = {}  # the rows of each calibration set
    for k, row in enumerate(rows):
        if row.position is None:
            by_set.setdefault((row.role, row.when), []).append(k)
        else:
            by_position.setdefault(row.position, []).append(k)
    by_set = {pair: by_set[pair] for pair in CALIBRATION_SETS if pair in by_set}  # the file's order
    cameras = sorted({c.camera_id for c in checked})
    metadata = {**(metadata or {}), "imported_from": _sources(folder, csv_path, rig_path)}
    header = _run_header(rig, (tool_poses, light_poses), run_id or out.stem, metadata, checked, by_position, cameras)
    header.calibration = {"switch": "import", "sets": [list(pair) for pair in by_set]}
    if not by_set:
        header.calibration["reason"] = "the import CSV gives no calibration frames"
    empty = [i for i in range(n) if i not in by_position]
    note = f"imported from {folder}: {len(by_position)} of {n} positions have frames"
    if empty:
        note += f"; positions {format_ranges(empty)} have none and are left incomplete"
    _write_run(out, header, rows, checked, (by_position, by_set), csv_path, note, progress)

    return ImportReport(
        run_file=out,
        run_id=header.run_id,
        frames=len(rows),
        n_positions=n,
        positions_with_frames=sorted(by_position),
        empty_positions=empty,
        frame_shape=checked[0].shape,
        cfa_pattern=checked[0].cfa_pattern,
        exposures_s=sorted({checked[k].exposure_s for ks in by_position.values() for k in ks}),
        cameras=cameras,
        ignored_files=_ignored_files(folder, rows),
        exposure_overrides=sum(row.exposure_s is not None for row in rows),
        calibration_sets={f"{role} {when}": len(ks) for (role, when), ks in by_set.items()},
    )


def _sources(folder: Path, csv_path: Path, rig_path: Path) -> dict:
    """Where an imported run came from, for its metadata (the CSV with its SHA-256)."""
    return {
        "folder": str(folder.resolve()),
        "csv": str(csv_path.resolve()),
        "csv_sha256": file_sha256(csv_path),
        "rig": str(rig_path.resolve()),
    }


def _run_header(
    rig: Rig,
    poses: tuple[list[Pose], list[Pose]],
    run_id: str,
    metadata: dict,
    checked: list[_Checked],
    by_position: dict[int, list[int]],
    cameras: list[str],
) -> RunHeader:
    """The imported run's header: the rig's schedule (``poses``: tool and light), the frames checked."""
    tool_poses, light_poses = poses
    return RunHeader(
        run_id=run_id,
        rig=rig,
        tool_poses=tool_poses,
        light_poses=light_poses,
        max_exposures=max(len(ks) for ks in by_position.values()),
        frame_shape=checked[0].shape,
        bracket=_bracket(by_position, checked),
        metadata={"operator": "", "light_source": "", "notes": "", **metadata},
        devices={"arm": "none (imported run: poses as planned unless the CSV gave them)", "camera": "; ".join(cameras)},
        software_version=__version__,
        created_utc=datetime.now(UTC).isoformat(timespec="seconds"),
        preset="import",
    )


def _ignored_files(folder: Path, rows: list[ImportRow]) -> list[str]:
    """The raw files in ``folder`` that the CSV does not name, by name."""
    named = {row.path for row in rows}
    return sorted(
        p.name
        for p in folder.iterdir()
        if p.suffix.lower() in RAW_EXTENSIONS and p.is_file() and p.resolve() not in named
    )


def _check_destination(folder: Path, rig_path: Path, out: Path) -> Rig:
    """The rig, once the folder, the rig and the output path are known to be usable."""
    if not folder.is_dir():
        raise RunImportError(f"{folder}: {'not a folder' if folder.exists() else 'no such folder'}")
    try:
        rig = load_rig(rig_path)
    except RigError as exc:
        raise RunImportError(str(exc)) from None
    if out.exists():
        raise RunImportError(f"{out}: already exists (choose another --out, or remove it)")
    if out.parent.exists() and not out.parent.is_dir():
        raise RunImportError(f"{out.parent}: not a folder")
    return rig


def _write_run(
    out: Path,
    header: RunHeader,
    rows: list[ImportRow],
    checked: list[_Checked],
    groups: tuple[dict[int, list[int]], dict[tuple[str, str], list[int]]],
    csv_path: Path,
    note: str,
    progress: Progress | None,
) -> None:
    """Stage 3: write the run in a hidden temporary file, decoding each raw file again, then
    publish it at ``out``; the temporary file is removed whatever happens. ``groups``: the
    rows of each position, and of each calibration set."""
    by_position, by_set = groups
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RunImportError(f"{out.parent}: cannot create the folder: {exc.strerror}") from None
    tmp = _unused_temp(out)
    try:
        with RunFileWriter.create(tmp, header) as writer:
            done = 0
            for position in sorted(by_position):
                ks = by_position[position]
                frames = [_decode_again(rows[k], checked[k], csv_path) for k in ks]
                done += len(ks)
                given = (rows[k].pose for k in ks)
                pose = next((p for p in given if p is not None), header.tool_poses[position])
                stamps = [checked[k].timestamp for k in ks]
                times = PositionTimes(min(stamps), min(stamps), max(stamps))
                writer.write_position(position, pose, times, frames)
                del frames
                if progress:
                    progress("writing", done, len(rows))
            for (role, when), ks in by_set.items():
                writer.write_calibration(role, when, [_decode_again(rows[k], checked[k], csv_path) for k in ks])
                done += len(ks)
                if progress:
                    progress("writing", done, len(rows))
            writer.set_status("complete", note)
        _publish(tmp, out)
    except RunFileError as exc:
        raise RunImportError(str(exc).replace(str(tmp), str(out))) from None
    except OSError as exc:
        raise RunImportError(f"{out}: cannot write the run file: {exc.strerror or exc}") from None
    finally:
        _remove_temp(tmp)


def _decode_again(row: ImportRow, info: _Checked, csv_path: Path) -> RawFrame:
    """The frame of ``row`` decoded for writing, with the exposure stage 2 settled on."""
    frame = _decode(row, csv_path)
    if frame.mosaic.shape != info.shape:  # the file changed since it was checked
        raise RunImportError(f"{csv_path}: line {row.line}: {row.name} changed while it was imported")
    frame.exposure_s = info.exposure_s
    return frame
