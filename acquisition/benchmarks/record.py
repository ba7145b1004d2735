"""The benchmarks' figures in one generated markdown file (``docs/benchmarks.md``).

``mirrorgonio bench NAME ... --record PATH`` writes NAME's section of the file, between the
lines ``<!-- bench:NAME -->`` and ``<!-- /bench:NAME -->``: it replaces that section where
the file has one and leaves the other sections as they are; a new section goes in the
order of :data:`ORDER`; a missing file is created with :data:`HEADER`. A section says how
the figures were made (the command line, the date and time in UTC, the machine, its load
before and after, the software's version) and holds the result: the benchmark's own
markdown table where it makes one, else a table of the result's main figures.

:func:`start_recording` notes the start (and checks the file before a long benchmark runs);
:func:`record_result` writes the section when the result is there.
"""

from __future__ import annotations

import datetime as _dt
import os
import platform
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import psutil

from drivers.contracts.version import __version__

#: The benchmarks in the order their sections appear.
ORDER = ("render", "acquire", "hdr", "accuracy", "repeatability", "reflectance", "brdf", "tolerance", "speed", "lab")
HEADER = """# Benchmark results

This file is generated: each section below is the last recorded result of one benchmark,
written by `mirrorgonio bench NAME ... --record docs/benchmarks.md` (NAME one of render,
acquire, hdr, accuracy, repeatability, reflectance, brdf, tolerance, speed, lab). A run
replaces its own section, between the marker lines that carry the benchmark's name, and
leaves the others as they are. Never edit it by hand: run the benchmark again. What each
benchmark measures: `mirrorgonio bench NAME --help` and the modules in
`acquisition/benchmarks/`.
"""
_MARKER = re.compile(r"^<!-- (/?)bench:([a-z0-9_-]+) -->[ \t]*$", re.MULTILINE)
#: Strings longer than this are left out of the table of a result's figures (explanations).
_LONGEST_STRING = 80
#: Lists longer than this are left out of the table of a result's figures.
_LONGEST_LIST = 8


class RecordError(ValueError):
    """The markdown file cannot take a benchmark's section (one line naming the file)."""


@dataclass(frozen=True)
class Recording:
    """A benchmark being recorded: where, its command line, and its start."""

    path: Path
    command: str
    started_utc: _dt.datetime
    started_s: float  # time.perf_counter() at the start
    load_before: float | None


def start_recording(path: Path, command: str) -> Recording:
    """Note a benchmark's start, for :func:`record_result` once it ends.

    Parameters
    ----------
    path : Path
        The markdown file the section goes in (created when missing).
    command : str
        The command line as run.

    Returns
    -------
    Recording
        The start's time and load.

    Raises
    ------
    RecordError
        The file's folder does not exist, or the file's markers do not pair up: said before
        the benchmark runs.
    """
    path = Path(path)
    if path.exists():
        if not path.is_file():
            raise RecordError(f"{path}: not a file")
        find_sections(path.read_text(encoding="utf-8"), path)
    elif not path.parent.is_dir():
        raise RecordError(f"{path}: its folder {path.parent} does not exist")
    return Recording(path, command, _dt.datetime.now(_dt.UTC), time.perf_counter(), _load_1min())


def record_result(recording: Recording, name: str, result: dict) -> None:
    """Write (or replace) the section ``name`` of the recording's file with ``result``.

    Parameters
    ----------
    recording : Recording
        What :func:`start_recording` returned when the benchmark started.
    name : str
        The benchmark's name (``render``, ``acquire``, ``hdr``, ...).
    result : dict
        The benchmark's JSON result.

    Raises
    ------
    RecordError
        The file's markers do not pair up.
    OSError
        The file cannot be read or written.
    """
    section = format_section(
        name,
        result,
        command=recording.command,
        started_utc=recording.started_utc,
        seconds=time.perf_counter() - recording.started_s,
        load_before=recording.load_before,
        load_after=_load_1min(),
        machine=describe_machine(),
        version=__version__,
    )
    path = recording.path
    text = path.read_text(encoding="utf-8") if path.exists() else HEADER
    updated = replace_section(_with_header(text), name, section, path)
    temporary = path.with_name(f".{path.name}.tmp")
    temporary.write_text(updated, encoding="utf-8")
    os.replace(temporary, path)


def _with_header(text: str) -> str:
    """``text`` with this program's :data:`HEADER` in place of the one it has (the list of
    benchmarks grows); a file without the generated header's title is left as it is."""
    first = text.find("<!-- bench:")
    if not text.startswith(HEADER.splitlines()[0]) or first < 0:
        return text
    return HEADER.rstrip("\n") + "\n\n" + text[first:]


# --- the file's sections --------------------------------------------------------------------------
def find_sections(text: str, path: Path | str = "the file") -> dict[str, tuple[int, int]]:
    """Each section's name and its span in ``text``: from its opening marker's first character
    to just after its closing marker's line.

    Raises
    ------
    RecordError
        A marker without its pair, sections nested or crossed, or a name twice.
    """
    spans: dict[str, tuple[int, int]] = {}
    open_name, open_at = None, 0
    for match in _MARKER.finditer(text):
        closing, name = match.group(1) == "/", match.group(2)
        line = text.count("\n", 0, match.start()) + 1
        if not closing:
            if open_name is not None:
                raise RecordError(f"{path}:{line}: section {name!r} opens inside section {open_name!r}")
            if name in spans:
                raise RecordError(f"{path}:{line}: a second section {name!r}")
            open_name, open_at = name, match.start()
        elif name != open_name:
            raise RecordError(f"{path}:{line}: section {name!r} closes where it was not open")
        else:
            end = match.end() + 1 if text[match.end() : match.end() + 1] == "\n" else match.end()
            spans[name] = (open_at, end)
            open_name = None
    if open_name is not None:
        raise RecordError(f"{path}: section {open_name!r} is not closed (<!-- /bench:{open_name} -->)")
    return spans


def replace_section(text: str, name: str, section: str, path: Path | str = "the file") -> str:
    """``text`` with the section ``name`` replaced by ``section`` (markers included), or with
    ``section`` added before the first section that comes after it in :data:`ORDER` (at the
    end when none does). The rest of ``text`` is left as it is."""
    spans = find_sections(text, path)
    section = section.rstrip("\n") + "\n"
    if name in spans:
        start, end = spans[name]
        return text[:start] + section + text[end:]
    rank = _rank(name)
    later = [start for other, (start, _) in spans.items() if _rank(other) > rank]
    if later:
        at = min(later)
        return text[:at] + section + "\n" + text[at:]
    return text.rstrip("\n") + "\n\n" + section


def _rank(name: str) -> int:
    return ORDER.index(name) if name in ORDER else len(ORDER)


# --- a section ------------------------------------------------------------------------------------
def format_section(
    name: str,
    result: dict,
    *,
    command: str,
    started_utc: _dt.datetime,
    seconds: float,
    load_before: float | None,
    load_after: float | None,
    machine: dict,
    version: str,
) -> str:
    """The markdown of one benchmark's section, its markers included."""
    cpu = f", {machine['cpu']}" if machine.get("cpu") else ""
    memory = f", {machine['memory_gb']:g} GB memory" if machine.get("memory_gb") else ""
    rows = [
        ("command", f"`{command}`"),
        ("date", f"{started_utc:%Y-%m-%d %H:%M} UTC"),
        ("duration", f"{seconds:.0f} s"),
        ("machine", f"{machine.get('cores')} cores{cpu}{memory}"),
        ("load average (1 min)", f"{_number(load_before)} before, {_number(load_after)} after"),
        ("software", f"mirrorgonio {version}"),
    ]
    lines = [
        f"<!-- bench:{name} -->",
        f"## `bench {name}`",
        "",
        "| run | |",
        "| --- | --- |",
        *(f"| {key} | {_cell(value)} |" for key, value in rows),
        "",
        result_tables(name, result),
        f"<!-- /bench:{name} -->",
    ]
    return "\n".join(lines) + "\n"


def result_tables(name: str, result: dict) -> str:
    """The result as markdown: the benchmark's own table (``result["markdown"]``) where it has
    one; else a table of its scalar figures, and a table of its parts where
    :data:`PART_TABLES` knows how to make one."""
    if isinstance(result.get("markdown"), str):
        return result["markdown"].rstrip("\n") + "\n"
    text = figures_table(result)
    part = PART_TABLES.get(name)
    if part is not None:
        text += "\n" + part(result)
    return text


def figures_table(result: dict) -> str:
    """A two-column table of the result's top-level figures: numbers, yes/no, short strings and
    short lists (explanations and nested parts are left out)."""
    lines = ["| figure | value |", "| --- | --- |"]
    for key, value in result.items():
        if key in ("benchmark", "markdown"):
            continue
        if isinstance(value, list) and len(value) <= _LONGEST_LIST and all(_is_scalar(v) for v in value):
            lines.append(f"| {key} | {_cell(', '.join(_number(v) for v in value))} |")
        elif _is_scalar(value) and not (isinstance(value, str) and len(value) > _LONGEST_STRING):
            lines.append(f"| {key} | {_cell(_number(value))} |")
    return "\n".join(lines) + "\n"


def _hdr_methods(result: dict) -> str:
    """``bench hdr``: one row per merge method."""
    head = "| method | status | ms / position | mean abs. rel. error % | RMS rel. error % | bias % | speed-up |"
    lines = [head, "| --- | --- | --- | --- | --- | --- | --- |"]
    for method, entry in result.get("methods", {}).items():
        status = entry.get("status", "")
        speedup = result.get(f"speedup_vs_{method}")
        cells = [
            method,
            "ok" if status == "ok" else status,
            _number(entry.get("ms_per_position")),
            _number(entry.get("mean_abs_rel_error_pct")),
            _number(entry.get("rms_rel_error_pct")),
            _number(entry.get("bias_pct")),
            f"{speedup:g}×" if speedup else "",
        ]
        lines.append("| " + " | ".join(_cell(c) for c in cells) + " |")
    return "\n".join(lines) + "\n"


def _accuracy_sources(result: dict) -> str:
    """``bench accuracy``: one row per truth emitter."""
    lines = [
        "| source | RMS / peak | θ covered (°) | cell sums: RMS / peak | found off by (µm) | within 1σ: parameters, "
        "samples, I(θ) band |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for source in result.get("sources", []):
        cover = source.get("coverage", {})
        cells = [
            source.get("name", ""),
            _number(source.get("rms_rel_error")),
            f"{_number(source.get('theta_min_deg'))}–{_number(source.get('theta_max_deg'))}",
            _number(source.get("cell_sum_rms_rel_error")),
            _number(source.get("centre_error_um")),
            ", ".join(
                f"{cover[f'{kind}_within']}/{cover[kind]}"
                for kind in ("parameters", "samples", "band")
                if kind in cover
            ),
        ]
        lines.append("| " + " | ".join(_cell(c) for c in cells) + " |")
    return "\n".join(lines) + "\n"


def _reflectance_methods(result: dict) -> str:
    """``bench reflectance``: one row per light model."""
    lines = [
        "| light model | median abs. rel. error | p90 abs. rel. error | median bias | uniform CV | profile range |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for method, scores in result.get("methods", {}).items():
        keys = ("median_abs_rel_error", "p90_abs_rel_error", "median_rel_bias", "uniform_cv", "uniform_profile_range")
        lines.append("| " + " | ".join([_cell(method), *(_cell(_number(scores.get(k))) for k in keys)]) + " |")
    return "\n".join(lines) + "\n"


def _brdf_methods(result: dict) -> str:
    """``bench brdf``: one row per light model and subset of points (own lobe, all fitted)."""
    lines = [
        "| light model | points | diffuse median (R, G, B) | diffuse p90 (R, G, B) | roughness median | "
        "specular median | within 1σ: α, ρ | relighting RMS (median position) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for method, scores in result.get("methods", {}).items():
        relit = scores.get("relighting", {})
        for subset in ("own", "all"):
            part = scores.get(subset, {})
            cells = [
                method,
                subset,
                ", ".join(_number(v) for v in part.get("diffuse_median") or []),
                ", ".join(_number(v) for v in part.get("diffuse_p90") or []),
                _number(part.get("roughness_median")),
                _number(part.get("specular_median")),
                ", ".join(_number(part.get(k)) for k in ("within_sigma_roughness_share", "within_sigma_diffuse_share")),
                f"{_number(relit.get('rms_relative'))} ({_number(relit.get('median_position_rms'))})",
            ]
            lines.append("| " + " | ".join(_cell(c) for c in cells) + " |")
    held = result.get("held_out_positions", [])
    lines += ["", "| light model | " + " | ".join(f"relit position {j}" for j in held) + " |"]
    lines.append("| --- |" + " --- |" * len(held))
    for method, scores in result.get("methods", {}).items():
        per = {p["position"]: p["rms_relative"] for p in scores.get("relighting", {}).get("per_position", [])}
        lines.append("| " + " | ".join([_cell(method), *(_cell(_number(per.get(j))) for j in held)]) + " |")
    times = {
        **result.get("times_s", {}),
        **{f"reflectance: {k}": v for k, v in result.get("reflectance_times_s", {}).items()},
    }
    lines += ["", "| step | seconds |", "| --- | --- |", *(f"| {_cell(k)} | {_number(v)} |" for k, v in times.items())]
    met = result.get("meets_target", {})
    if met:
        lines += ["", "| target (measured light) | met |", "| --- | --- |"]
        lines += [f"| {_cell(k)} | {'yes' if v else 'no'} |" for k, v in met.items()]
    return "\n".join(lines) + "\n"


def _repeatability_sources(result: dict) -> str:
    """``bench repeatability``: one row per truth source, then one per seed."""
    lines = [
        "| source | mean offset u, v (µm) | spread 1σ u, v (µm) | quoted 1σ u, v (µm) | peak: spread, quoted 1σ "
        "| quoted over spread (u, v, peak) | worst distance (µm) | worst RMS / peak |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name, entry in result.get("sources", {}).items():
        cells = [
            name,
            ", ".join(_number(v) for v in entry.get("mean_offset_um") or []),
            ", ".join(_number(v) for v in entry.get("std_um") or []),
            ", ".join(_number(v) for v in entry.get("quoted_sigma_um") or []),
            ", ".join(_number(entry.get(k)) for k in ("peak_spread_rel", "quoted_peak_sigma_rel")),
            ", ".join(_number(v) for v in entry.get("quoted_over_spread") or []),
            _number(entry.get("worst_distance_um")),
            _number(entry.get("worst_rms_rel_error")),
        ]
        lines.append("| " + " | ".join(_cell(c) for c in cells) + " |")
    lines += ["", "| seed | sources | worst distance (µm) | worst RMS / peak | quality | processing (s) |"]
    lines.append("| --- | --- | --- | --- | --- | --- |")
    for row in result.get("per_seed", []):
        keys = ("seed", "sources_found", "worst_distance_um", "worst_rms_rel_error", "quality", "process_s")
        lines.append("| " + " | ".join(_cell(_number(row.get(k))) for k in keys) + " |")
    return "\n".join(lines) + "\n"


#: The tables of a result's parts, by benchmark.
PART_TABLES: dict[str, Callable[[dict], str]] = {
    "hdr": _hdr_methods,
    "accuracy": _accuracy_sources,
    "reflectance": _reflectance_methods,
    "brdf": _brdf_methods,
    "repeatability": _repeatability_sources,
}


def _is_scalar(value: object) -> bool:
    return value is None or isinstance(value, (bool, int, float, str))


def _number(value: object) -> str:
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def _cell(text: object) -> str:
    """Text safe in a table cell: no line breaks, pipes escaped."""
    return " ".join(str(text).split()).replace("|", "\\|")


# --- the machine ----------------------------------------------------------------------------------
def describe_machine() -> dict:
    """The machine the benchmark runs on: its cores, CPU model (where /proc/cpuinfo or the
    platform says) and memory in GB."""
    return {
        "cores": os.cpu_count(),
        "cpu": _cpu_model(),
        "memory_gb": round(psutil.virtual_memory().total / 1e9, 1),
    }


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as cpuinfo:
            for line in cpuinfo:
                key, _, value = line.partition(":")
                if key.strip() in ("model name", "Model", "cpu model") and value.strip():
                    return " ".join(value.split())
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _load_1min() -> float | None:
    try:
        return round(os.getloadavg()[0], 2)
    except (AttributeError, OSError):  # no load average on this platform
        return None
