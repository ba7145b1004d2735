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


def load_layout(path: str | Path) -> list[Source]:
    """Sources from a TOML file: ``[[sources]]`` (or ``[[emitters]]``, the simulation's
    truth format) with ``name``, ``centre_m = [u, v]`` and ``radius_m``."""
    path = Path(path)
    data = read_toml(path, "layout file", SourcesError)
    entries = data.get("sources", data.get("emitters"))
    if not entries:
        raise SourcesError(f"{path}: no [[sources]] in the layout")
    out = []
    for i, entry in enumerate(entries):
        try:
            u, v = (float(x) for x in entry["centre_m"])
            radius = float(entry.get("radius_m", 0.5e-3))
        except (KeyError, TypeError, ValueError):
            raise SourcesError(f"{path}: sources[{i}].centre_m: needs [u, v] in metres") from None
        if not (math.isfinite(u) and math.isfinite(v)):  # inf and nan are TOML literals
            raise SourcesError(f"{path}: sources[{i}].centre_m: must be finite (got [{u}, {v}])")
        if not 0 < radius < math.inf:
            raise SourcesError(f"{path}: sources[{i}].radius_m: must be finite and > 0 (got {radius})")
        for name, value in (("centre_m", (u, v)), ("radius_m", radius)):
            if (problem := magnitude_problem(name, value)) is not None:
                raise SourcesError(f"{path}: sources[{i}].{name}: {problem}")
        out.append(Source(str(entry.get("name") or f"source-{i}"), (u, v), radius))
    return out
