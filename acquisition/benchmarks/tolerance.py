"""``mirrorgonio bench tolerance``: how exact the rig description must be.

The templates that unmix the sources are traced through the rig as its description has
it: the pinhole's diameter sets the point spread's size, the ball's place and radius and
the light's offset from the arm's tool set where each source's image falls. One simulated
run is taken once; copies of it are processed with one number of the description wrong
(the raw frames and the measured poses untouched, as when a lab's rig file is off), and
the fitted sources are scored against the truth as ``bench accuracy`` scores them:
RMS(I_fit − I_true) / max(I_true) over the θ each source's samples cover.
"""

from __future__ import annotations

import json
import re
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

#: The numbers of the description an error can touch, by name: (the rig field, the component
#: of a 3-vector or None, whether a relative error in % makes sense for it).
ERROR_PARTS: dict[str, tuple[str, int | None, bool]] = {
    "pinhole": ("camera.pinhole_diameter_m", None, True),
    "sensor-distance": ("camera.sensor_distance_m", None, True),
    "ball-x": ("ball.centre_m", 0, False),
    "ball-y": ("ball.centre_m", 1, False),
    "ball-z": ("ball.centre_m", 2, False),
    "ball-radius": ("ball.radius_m", None, True),
    "light-x": ("light.light_to_tool.position_m", 0, False),
    "light-y": ("light.light_to_tool.position_m", 1, False),
    "light-z": ("light.light_to_tool.position_m", 2, False),
}
#: The errors tried by default. Sizes a lab can plausibly get wrong: a 0.2 mm pinhole drilled or
#: measured 10 % off, the sensor distance of a camera without a datasheet, the ball placed by eye,
#: the light's mount measured with a rule.
DEFAULT_ERRORS = (
    "pinhole+10%",
    "pinhole-10%",
    "sensor-distance+1%",
    "ball-x+0.2mm",
    "ball-z+0.2mm",
    "ball-radius+0.1mm",
    "light-x+0.2mm",
    "light-z+0.5mm",
)
_ERROR_SYNTAX = re.compile(r"(?P<part>[a-z-]+?)(?P<sign>[+-])(?P<size>\d+(?:\.\d+)?)(?P<unit>%|mm|um|µm)")
_METRES = {"mm": 1e-3, "um": 1e-6, "µm": 1e-6}


@dataclass(frozen=True)
class RigError:
    """One number of the rig description made wrong: ``field`` scaled by ``amount`` (``how`` is
    "scale") or ``amount`` added to it (a 3-vector for a vector field), in metres."""

    name: str
    field: str
    how: str
    amount: float | tuple[float, float, float]

    @property
    def what(self) -> str:
        return f"{self.field} {'×' if self.how == 'scale' else '+'} {self.amount}"


def parse_error(name: str) -> RigError:
    """The error a name such as ``pinhole+10%``, ``ball-x-20um`` or ``light-z+0.5mm`` stands for:
    PART±SIZE with PART one of :data:`ERROR_PARTS` and SIZE in % (of the pinhole, the sensor
    distance, the ball's radius) or in mm or µm.

    Raises
    ------
    ValueError
        One line naming the error and what an error looks like.
    """
    syntax = (
        f"PART±SIZE, PART one of {', '.join(ERROR_PARTS)}, SIZE in mm or um (or % of pinhole, "
        f"sensor-distance, ball-radius), e.g. pinhole+10%, ball-x-20um"
    )
    match = _ERROR_SYNTAX.fullmatch(name.strip())
    if match is None or match["part"] not in ERROR_PARTS:
        raise ValueError(f"--errors: {name!r} is not an error of the rig description: {syntax}")
    field, component, relative = ERROR_PARTS[match["part"]]
    size = float(match["size"]) * (-1.0 if match["sign"] == "-" else 1.0)
    if match["unit"] == "%":
        if not relative:
            raise ValueError(f"--errors: {name!r}: {match['part']} is a position: give its error in mm or um, not %")
        if size <= -100.0:
            raise ValueError(f"--errors: {name!r}: a length cannot shrink by 100 % or more")
        return RigError(name, field, "scale", round(1.0 + size / 100.0, 12))
    metres = round(size * _METRES[match["unit"]], 15)
    if component is None:
        return RigError(name, field, "add", metres)
    vector = [0.0, 0.0, 0.0]
    vector[component] = metres
    return RigError(name, field, "add", (vector[0], vector[1], vector[2]))


def described_wrong(rig: dict, error: str) -> dict:
    """``rig`` (the run file's JSON description) with the error named ``error`` made in it
    (:func:`parse_error`)."""
    wrong = parse_error(error)
    out = json.loads(json.dumps(rig))
    *parents, key = wrong.field.split(".")
    holder = out
    for name in parents:
        holder = holder[name]
    value = holder[key]
    if wrong.how == "scale":
        holder[key] = value * wrong.amount
    elif isinstance(wrong.amount, tuple):
        holder[key] = [v + a for v, a in zip(value, wrong.amount, strict=True)]
    else:
        holder[key] = value + wrong.amount
    return out


def _copy_described(run_path: Path, dst: Path, error: str | None) -> Path:
    """A copy of the run file whose header describes the rig with ``error`` (None: as taken)."""
    import h5py

    shutil.copy(run_path, dst)
    if error is not None:
        with h5py.File(dst, "r+") as f:
            rig = json.loads(f["header/rig_json"][()])
            text = json.dumps(described_wrong(rig, error), ensure_ascii=False)
            del f["header/rig_json"]
            f.create_dataset("header/rig_json", data=text, dtype=h5py.string_dtype("utf-8"))
    return dst


#: The ways each description is processed: (the truth's layout given, ``fit_aperture``,
#: ``fit_sensor_distance``, the table's column). The sensor distance is fitted as ``process
#: --fit-sensor-distance`` fits it: with the layout given, alone; found, with the aperture after it.
WAYS = {
    "given": (True, False, False, "fits, layout given (max RMS / peak)"),
    "given, aperture fitted": (True, True, False, "the aperture fitted to the data: diameter, fits"),
    "given, sensor distance fitted": (True, False, True, "the sensor distance fitted: distance, fits"),
    "found": (False, False, False, "layout found in the data: sources, farthest from the truth's, fits"),
    "found, aperture fitted": (False, True, False, "found, the aperture fitted: sources, farthest, diameter, fits"),
    "found, sensor distance fitted": (
        False,
        True,
        True,
        "found, the sensor distance and the aperture fitted: sources, farthest, distance, diameter, fits",
    ),
}


def bench_tolerance(
    *,
    rig_path=None,
    truth: str = "five-gaussians",
    positions: int = 66,
    errors=None,
    layout_from_data: bool = False,
    fit_aperture: bool = False,
    fit_sensor_distance: bool = False,
    noise: bool = True,
    exposures=(2e-5, 1e-4, 5e-4, 2.5e-3, 1.25e-2),
    scheduler: str = "local",
    workdir: str | Path | None = None,
    log=None,
) -> dict:
    """Take one simulated run, then process it with the rig described as taken and with each
    of ``errors`` (names :func:`parse_error` reads, default :data:`DEFAULT_ERRORS`), given the truth's layout and,
    with ``layout_from_data``, also finding the sources in the data; with ``fit_aperture``,
    each of those again with the aperture fitted to the data (``process --fit-aperture``), and
    with ``fit_sensor_distance`` with the sensor distance fitted (:data:`WAYS`).

    Returns the JSON the command prints: per error and layout, the sources found and how far
    from the truth's, and each source's error against the truth. ``log(text)`` hears of each
    processing as it ends."""
    from acquisition.benchmarks.accuracy import acquire_simulated, score_sources
    from acquisition.demo import DEMO_RIG_PATH
    from drivers.contracts.rig import load_rig
    from processing.light_run.errors import ProcessingError
    from processing.light_run.position import warm_up_worker
    from processing.light_run.run import process_run
    from processing.options import FitChoice
    from processing.parallel import open_compute
    from sim_devices.lights import LIGHTS_DIR, load_truth

    errors = list(DEFAULT_ERRORS) if errors is None else list(errors)
    for error in errors:
        parse_error(error)  # every name checked before anything is acquired
    rig = load_rig(rig_path or DEMO_RIG_PATH)
    truth_light = load_truth(truth)
    given = LIGHTS_DIR / f"{truth}.toml"
    asked = {"aperture fitted": fit_aperture, "sensor distance fitted": fit_sensor_distance}
    ways = {
        name: (given if given_layout else None, aperture, distance)
        for name, (given_layout, aperture, distance, _) in WAYS.items()
        if (given_layout or layout_from_data) and asked.get(name.partition(", ")[2], True)
    }
    rows = []
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(workdir) if workdir is not None else Path(tmp)
        run_path = acquire_simulated(rig, truth, noise, exposures, positions, base)
        acquired = time.perf_counter()
        if log:
            log(f"simulated run taken in {acquired - started:.0f} s: {run_path.name}")
        with open_compute(scheduler, warm_up=warm_up_worker) as compute:
            for k, error in enumerate([None, *errors]):
                copy = _copy_described(run_path, base / f"described-{k}.h5", error)
                for w, (layout_name, (layout, fitted, distance)) in enumerate(ways.items()):
                    t0 = time.perf_counter()
                    row = {"error": error or "none", "layout": layout_name}
                    if error is not None:
                        row["what"] = parse_error(error).what
                    try:
                        report = process_run(
                            copy,
                            base / f"out-{k}-{w}",
                            steps=("hdr", "sources"),
                            layout=layout,
                            noise="rig",
                            units="W/sr",
                            compute=compute,
                            images=False,
                            fit_aperture=FitChoice.ALWAYS if fitted else FitChoice.NEVER,
                            fit_sensor_distance=FitChoice.ALWAYS if distance else FitChoice.NEVER,
                        )
                    except ProcessingError as exc:  # e.g. an aperture fit at its bound: said, and on to the next
                        row.update(failed=str(exc), process_s=round(time.perf_counter() - t0, 1))
                        rows.append(row)
                        if log:
                            log(f"{row['error']}, layout {layout_name}: failed: {exc}")
                        continue
                    scored = score_sources(
                        report.model, report.samples, truth_light, matched=layout is None, cell_sums=False
                    )
                    row.update(
                        sources_found=len(report.model.sources),
                        max_rms_rel_error=max(s["rms_rel_error"] for s in scored["sources"]),
                        sources=scored["sources"],
                        process_s=round(time.perf_counter() - t0, 1),
                    )
                    if layout is None:
                        row["max_centre_error_um"] = max(s["centre_error_um"] for s in scored["sources"])
                    if fitted:
                        row["aperture_fit"] = report.aperture_fit.record()
                    if distance:
                        row["sensor_distance_fit"] = report.sensor_distance_fit.record()
                    rows.append(row)
                    if log:
                        log(
                            f"{row['error']}, layout {layout_name}: {row['sources_found']} sources, fits up to "
                            f"{100 * row['max_rms_rel_error']:.2f} % ({row['process_s']:.1f} s)"
                        )
    result = {
        "benchmark": "tolerance",
        "rig": str(Path(rig_path or DEMO_RIG_PATH)),
        "truth": truth,
        "noise": noise,
        "positions": positions,
        "exposures_s": list(exposures),
        "runs": rows,
        "acquire_s": round(acquired - started, 1),
        "how": "one simulated run; copies of it processed with one number of the rig description wrong (header "
        "/rig_json rewritten, frames and measured poses untouched), hdr + sources with the truth's layout given "
        "(and found in the data with --layout-from-data); each truth emitter scored as bench accuracy does "
        "(against the nearest source found when found)",
    }
    result["markdown"] = markdown_table(result)
    return result


def markdown_table(result: dict) -> str:
    """The runs as a markdown table: one row per error of the description."""
    by_error: dict[str, dict[str, dict]] = {}
    for row in result["runs"]:
        by_error.setdefault(row["error"], {})[row["layout"]] = row
    ways = [way for way in WAYS if any(way in rows for rows in by_error.values())]
    lines = ["| rig description |" + "".join(f" {WAYS[way][3]} |" for way in ways), "| --- |" + " --- |" * len(ways)]
    for error, rows in by_error.items():
        what = "as taken" if error == "none" else f"{error} (`{rows['given']['what']}`)"
        lines.append(f"| {what} |" + "".join(_cell(rows[way]) for way in ways))
    return "\n".join(lines)


def _cell(row: dict) -> str:
    """A table cell for one processing: for sources found in the data, how many and the farthest
    from the truth's; the sensor distance and the aperture when they were fitted; the fits; or
    why it failed."""
    if "failed" in row:
        return f" failed: {row['failed'].replace('|', '/')} |"
    parts = []
    if "max_centre_error_um" in row:
        parts += [f"{row['sources_found']} sources", f"{row['max_centre_error_um']:.0f} µm"]
    if "sensor_distance_fit" in row:
        parts.append(f"{1e3 * row['sensor_distance_fit']['fitted_m']:.3f} mm")
    if "aperture_fit" in row:
        parts.append(f"{1e3 * row['aperture_fit']['fitted_m']:.4f} mm")
    parts.append(f"{100 * row['max_rms_rel_error']:.2f} %")
    return f" {', '.join(parts)} |"
