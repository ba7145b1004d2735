"""The sources on the light plane (their layout) and the errors of the source estimate."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from drivers.config_files import magnitude_problem, read_toml


class SourcesError(ValueError):
    """A layout or a run the source estimate cannot work with (one line)."""


@dataclass(frozen=True)
class Source:
    name: str
    centre: tuple[float, float]  # (u, v) on the light plane, metres
    radius: float  # emitting disc, metres
    centre_sigma: tuple[float, float] | None = None  # 1σ of (u, v) where the centre was fitted, metres


def load_layout(path: str | Path, field: str | None = None) -> list[Source]:
    """Sources from a TOML file: ``[[sources]]`` (or ``[[emitters]]``, the simulation's
    truth format) with ``name``, ``centre_m = [u, v]`` and ``radius_m``. ``field``, the option
    or request field that named the file, starts the messages about reading it."""
    path = Path(path)
    return layout_from_dict(read_toml(path, "layout file", SourcesError, field=field), str(path))


def layout_from_dict(data: dict, source: str) -> list[Source]:
    """Sources from a layout file's parsed TOML (:func:`load_layout`); ``source`` names it
    in the errors."""
    entries = data.get("sources", data.get("emitters"))
    if not entries:
        raise SourcesError(f"{source}: no [[sources]] in the layout")
    if not isinstance(entries, list) or not all(isinstance(entry, dict) for entry in entries):
        raise SourcesError(f"{source}: sources: needs [[sources]] tables")
    out = []
    for i, entry in enumerate(entries):
        try:
            u, v = (float(x) for x in entry["centre_m"])
            radius = float(entry.get("radius_m", 0.5e-3))
        except (KeyError, TypeError, ValueError):
            raise SourcesError(f"{source}: sources[{i}].centre_m: needs [u, v] in metres") from None
        if not (math.isfinite(u) and math.isfinite(v)):  # inf and nan are TOML literals
            raise SourcesError(f"{source}: sources[{i}].centre_m: must be finite (got [{u}, {v}])")
        if not 0 < radius < math.inf:
            raise SourcesError(f"{source}: sources[{i}].radius_m: must be finite and > 0 (got {radius})")
        for name, value in (("centre_m", (u, v)), ("radius_m", radius)):
            if (problem := magnitude_problem(name, value)) is not None:
                raise SourcesError(f"{source}: sources[{i}].{name}: {problem}")
        out.append(Source(str(entry.get("name") or f"source-{i}"), (u, v), radius))
    return out
