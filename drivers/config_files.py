"""Reading TOML configuration files into pydantic models, with one-line errors.

Used for every file a person writes (rig descriptions, device profiles, truth lights,
daemon settings), so that all of them report a mistake the same way:
``FILE: field.path: cause (got VALUE)``.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import TypeVar

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


def read_toml(path: str | Path, what: str, error: type[ValueError]) -> dict:
    """Parse a TOML file; a missing, unreadable or malformed file raises ``error``."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise error(f"{path}: {what} not found") from None
    except OSError as exc:
        raise error(f"{path}: cannot read the {what}: {exc.strerror}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{path}: not valid TOML: {exc}") from None


def load_model(path: str | Path, model: type[Model], what: str, error: type[ValueError]) -> Model:
    """Read a TOML file and validate it as ``model``."""
    return validate_model(model, read_toml(path, what, error), str(path), error)
