"""Reading the files a person gives a command, with one-line errors.

Every configuration and input file a command reads (daemon settings, rig descriptions,
device profiles, truth lights, layouts, light models, import CSVs, aperture masks) is read
by :func:`read_input_bytes` and what is built on it (:func:`read_input_text`,
:func:`read_toml`, :func:`read_json`): regular files only (a directory, a FIFO or a device
is refused before it is opened), a size limit, UTF-8 text. TOML files are validated into
pydantic models, so that all of them report a mistake the same way:
``FILE: field.path: cause (got VALUE)``. Arrays whose size a file sets (a rig's sensor) are
checked against the memory available before they are allocated (:func:`require_memory`).
"""

from __future__ import annotations

import json
import math
import os
import stat
import threading
import tomllib
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any, TypeVar, cast

import psutil
from pydantic import BaseModel, ConfigDict, ValidationError, ValidationInfo, field_validator

Model = TypeVar("Model", bound=BaseModel)

#: The largest magnitude a number in a configuration file may have, by the unit its name
#: ends in. A rig spans metres and an angle a turn, so a length past a kilometre or an
#: angle past 360° is a typo. Unbounded, 1e300 squared to inf in the geometry and came back
#: as nonsense ("the camera is inside the ball") or overflow warnings.
MAGNITUDE_LIMITS: dict[str, tuple[float, str]] = {"_m": (1e3, " m"), "_deg": (360.0, "°")}
#: Any other number: a direction's component, a refractive index, electrons, a rate.
UNITLESS_LIMIT = 1e12


def magnitude_problem(name: str, value: object) -> str | None:
    """Why ``value`` (a float, or a sequence of them) is too large for the field ``name``,
    or None when it is not. Non-finite numbers are left to ``allow_inf_nan``."""
    limit, unit = next(
        ((lim, u) for suffix, (lim, u) in MAGNITUDE_LIMITS.items() if name.endswith(suffix)), (UNITLESS_LIMIT, "")
    )
    for number in _numbers(value):
        if math.isfinite(number) and abs(number) > limit:
            return f"{number:g}{unit} is beyond the ±{limit:g}{unit} allowed"
    return None


def _numbers(value: object) -> Iterator[float]:
    # Only floats: integers are exact, and counts carry their own bounds.
    if isinstance(value, float):
        yield value
    elif isinstance(value, (tuple, list)):
        for item in value:
            yield from _numbers(item)


class ConfigModel(BaseModel):
    """A section of a file a person writes: unknown fields refused, numbers finite (``inf``
    and ``nan`` are TOML literals) and within their unit's bounds (:data:`MAGNITUDE_LIMITS`),
    the result frozen."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    @field_validator("*", mode="after")
    @classmethod
    def _within_magnitude(cls, value: object, info: ValidationInfo) -> object:
        problem = magnitude_problem(info.field_name or "", value)
        if problem is not None:
            raise ValueError(problem)
        return value


def _number(value: object) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


_READABLE = {
    "greater_than": lambda ctx: f"must be > {_number(ctx.get('gt'))}",
    "greater_than_equal": lambda ctx: f"must be >= {_number(ctx.get('ge'))}",
    "less_than": lambda ctx: f"must be < {_number(ctx.get('lt'))}",
    "less_than_equal": lambda ctx: f"must be <= {_number(ctx.get('le'))}",
    "missing": lambda ctx: "missing",
    "extra_forbidden": lambda ctx: "unknown field",
}


def field_path(location: Iterable[int | str]) -> str:
    """``("emitters", 0, "radius_m")`` as ``emitters[0].radius_m``."""
    text = ""
    for part in location:
        if isinstance(part, int):
            text += f"[{part}]"
        else:
            text += f".{part}" if text else str(part)
    return text


def describe_validation_error(error: ValidationError) -> str:
    """The first problem of a validation error as ``field: cause (got value)``."""
    first = error.errors()[0]
    location = field_path(first["loc"])
    kind = first["type"]
    if kind in _READABLE:
        message = _READABLE[kind](first.get("ctx") or {})
    else:
        message = first["msg"].removeprefix("Value error, ")
    got = first.get("input")
    if kind not in ("value_error", "missing", "extra_forbidden") and not isinstance(got, (dict, list)):
        message = f"{message} (got {got!r})"
    return f"{location}: {message}" if location else message


def validate_model(model: type[Model], data: dict, source: str, error: type[ValueError]) -> Model:
    """Validate ``data`` as ``model``; raise ``error`` with one line naming ``source``."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise error(f"{source}: {describe_validation_error(exc)}") from None


#: The largest text file (TOML, JSON, CSV) a command reads, in bytes. A rig of 10 000 poses
#: is about 1 MB and a light model 0.2 MB; a larger file is a mistake (a log, an image,
#: ``/dev/zero``) and is refused before it is read.
MAX_TEXT_BYTES = 16 * 2**20
#: The largest mesh (PLY, OBJ, STL) or image (an aperture mask) a command reads, in bytes.
MAX_BINARY_BYTES = 2 * 2**30
_CHUNK = 1 << 20


def _where(path: Path, field: str | None) -> str:
    return f"{field}: {path}" if field else str(path)


def _size(nbytes: float) -> str:
    """A byte count for people: ``512 bytes``, ``16 MiB``, ``2.33 TiB``."""
    if nbytes < 1024:
        return f"{nbytes:.0f} bytes"
    for unit in ("KiB", "MiB", "GiB", "TiB"):
        nbytes /= 1024
        if nbytes < 1024 or unit == "TiB":
            break
    return f"{nbytes:.3g} {unit}"


def _file_kind(mode: int) -> str:
    for test, name in (
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return name
    return "a special file"


def check_input_file(
    path: str | Path, what: str, error: type[ValueError], *, field: str | None = None, limit: int = MAX_TEXT_BYTES
) -> os.stat_result:
    """The status of an input file that is a regular file of at most ``limit`` bytes.

    Only ``stat``: nothing is opened, so a device (a serial port whose opening resets the
    board behind it, ``/dev/zero``) or a FIFO is refused without side effects or waiting.

    Raises
    ------
    error
        One line naming the file (after ``field``, when given): missing, unreadable, a
        directory or special file, or larger than ``limit``.
    """
    path = Path(path)
    where = _where(path, field)
    try:
        status = os.stat(path)
    except (FileNotFoundError, NotADirectoryError):
        raise error(f"{where}: {what} not found") from None
    except OSError as exc:
        raise error(f"{where}: cannot read the {what}: {exc.strerror or exc}") from None
    _check_status(status, where, what, error, limit)
    return status


def _check_status(status: os.stat_result, where: str, what: str, error: type[ValueError], limit: int) -> None:
    if not stat.S_ISREG(status.st_mode):
        raise error(f"{where}: {_file_kind(status.st_mode)}, not a {what} (a regular file)")
    if status.st_size > limit:
        raise error(f"{where}: {_size(status.st_size)}, more than the {_size(limit)} a {what} may have")


def read_input_bytes(
    path: str | Path,
    what: str,
    error: type[ValueError],
    *,
    field: str | None = None,
    limit: int = MAX_TEXT_BYTES,
    timeout_s: float | None = None,
) -> bytes:
    """The bytes of an input file: a regular file of at most ``limit`` bytes, read whole.

    The file is checked before it is opened (:func:`check_input_file`), opened without
    blocking (``O_NONBLOCK``: a FIFO put in its place meanwhile cannot hang the read) and
    checked again on the open descriptor; no more than ``limit`` bytes are read, whatever
    the size it claims.

    Parameters
    ----------
    path : str or Path
    what : str
        What the file is, for the messages (``"rig file"``).
    error : type of ValueError
        The exception raised, with one line naming the file.
    field : str, optional
        The option or request field that named the file; the messages start with it.
    limit : int
        The largest size accepted, in bytes.
    timeout_s : float, optional
        Give up after this many seconds (a hung network filesystem): the read is done in a
        daemon thread, left behind if it never returns.

    Raises
    ------
    error
        Missing, unreadable, not a regular file, too large, or not read in time.
    """
    path = Path(path)
    if timeout_s is None:
        return _read_regular(path, what, error, field, limit)
    outcome: dict[str, object] = {}

    def read() -> None:
        try:
            outcome["data"] = _read_regular(path, what, error, field, limit)
        except BaseException as exc:  # noqa: BLE001 - handed to the waiting thread, raised there
            outcome["error"] = exc

    reader = threading.Thread(target=read, name=f"read {path.name}", daemon=True)
    reader.start()
    reader.join(timeout_s)
    if reader.is_alive():
        raise error(f"{_where(path, field)}: the {what} was not read within {timeout_s:g} s")
    if "error" in outcome:
        raise cast(BaseException, outcome["error"])
    return cast(bytes, outcome["data"])


def _read_regular(path: Path, what: str, error: type[ValueError], field: str | None, limit: int) -> bytes:
    where = _where(path, field)
    check_input_file(path, what, error, field=field, limit=limit)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    except OSError as exc:
        raise error(f"{where}: cannot read the {what}: {exc.strerror or exc}") from None
    try:
        _check_status(os.fstat(fd), where, what, error, limit)  # the file opened is the file checked
        chunks, total = [], 0
        while block := os.read(fd, min(_CHUNK, limit + 1 - total)):
            chunks.append(block)
            total += len(block)
            if total > limit:  # it grew since: still refused, without reading the rest
                raise error(f"{where}: more than the {_size(limit)} a {what} may have")
        return b"".join(chunks)
    except OSError as exc:
        raise error(f"{where}: cannot read the {what}: {exc.strerror or exc}") from None
    finally:
        os.close(fd)


def read_input_text(
    path: str | Path,
    what: str,
    error: type[ValueError],
    *,
    field: str | None = None,
    limit: int = MAX_TEXT_BYTES,
    timeout_s: float | None = None,
    encoding: str = "utf-8",
) -> str:
    """The text of an input file (:func:`read_input_bytes`, then decoded as UTF-8).

    ``encoding`` is ``"utf-8"`` or ``"utf-8-sig"`` (a leading byte-order mark dropped).

    Raises
    ------
    error
        As :func:`read_input_bytes`; and one line for a binary file (a NUL byte in it) or
        bytes that are not UTF-8, with the offset and line of the first.
    """
    path = Path(path)
    data = read_input_bytes(path, what, error, field=field, limit=limit, timeout_s=timeout_s)
    where = _where(path, field)
    if b"\0" in data:
        raise error(f"{where}: a binary file, not a {what} (UTF-8 text expected)")
    try:
        return data.decode(encoding)
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise error(
            f"{where}: not UTF-8 text: byte 0x{data[exc.start]:02x} at offset {exc.start} (line {line}) "
            f"cannot be decoded; save the {what} as UTF-8"
        ) from None


def read_toml(
    path: str | Path,
    what: str,
    error: type[ValueError],
    *,
    field: str | None = None,
    limit: int = MAX_TEXT_BYTES,
    timeout_s: float | None = None,
) -> dict:
    """Parse a TOML file (:func:`read_input_text`); a malformed file raises ``error`` too."""
    text = read_input_text(path, what, error, field=field, limit=limit, timeout_s=timeout_s)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{_where(Path(path), field)}: not valid TOML: {exc}") from None
    except RecursionError:
        raise error(f"{_where(Path(path), field)}: not valid TOML: nested too deeply") from None


def read_json(
    path: str | Path,
    what: str,
    error: type[ValueError],
    *,
    field: str | None = None,
    limit: int = MAX_TEXT_BYTES,
    timeout_s: float | None = None,
) -> Any:
    """Parse a JSON file (:func:`read_input_text`); a malformed file raises ``error`` too."""
    text = read_input_text(path, what, error, field=field, limit=limit, timeout_s=timeout_s)
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise error(f"{_where(Path(path), field)}: not JSON ({exc.msg}, line {exc.lineno})") from None
    except RecursionError:
        raise error(f"{_where(Path(path), field)}: not JSON (nested too deeply)") from None


#: The share of the memory available now that the arrays sized by a file's numbers (a rig's
#: sensor) may take: the rest is the program's own, the page cache's and other processes'.
MEMORY_SHARE = 0.5


def available_memory() -> int:
    """Bytes of memory this process can have now: the system's available memory, or less
    where a container's cgroup (v2) limit leaves less."""
    available = int(psutil.virtual_memory().available)
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text(encoding="ascii").strip()
        used = Path("/sys/fs/cgroup/memory.current").read_text(encoding="ascii").strip()
        if limit != "max":
            available = min(available, int(limit) - int(used))
    except (OSError, ValueError):
        pass  # no cgroup v2 limit readable: the system's figure
    return max(available, 0)


def require_memory(nbytes: int, where: str, purpose: str, error: type[ValueError]) -> None:
    """Refuse, before anything is allocated, work whose arrays need more than
    :data:`MEMORY_SHARE` of :func:`available_memory`.

    Parameters
    ----------
    nbytes : int
        The estimated peak of the arrays, in bytes.
    where : str
        The file and the fields that size them (``rig.toml: camera.width × camera.height``).
    purpose : str
        What needs them (``rendering a 100000 × 100000 px frame``).
    error : type of ValueError
        The exception raised, with one line.
    """
    available = available_memory()
    budget = int(available * MEMORY_SHARE)
    if nbytes > budget:
        raise error(
            f"{where}: {purpose} needs about {_size(nbytes)}, more than the {_size(budget)} this machine can "
            f"spare ({MEMORY_SHARE:.0%} of the {_size(available)} available)"
        )


def load_model(path: str | Path, model: type[Model], what: str, error: type[ValueError]) -> Model:
    """Read a TOML file and validate it as ``model``."""
    return validate_model(model, read_toml(path, what, error), str(path), error)
