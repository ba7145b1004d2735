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
import math
import shutil
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import h5py

from acquisition.benchmarks.accuracy import REFERENCE_EXPOSURES_S, acquire_simulated
from acquisition.benchmarks.description_errors import DEFAULT_ERRORS, described_wrong_all, parse_error, preset_errors
from acquisition.benchmarks.scoring import coverage_share, fitted, score_sources
from drivers.contracts.rig import RIGS_DIR, Rig, load_rig, rig_from_dict
from drivers.pose import Pose
from processing.light_run.errors import ProcessingError
from processing.light_run.position import warm_up_worker
from processing.light_run.run import process_run
from processing.lightmodel import LightModel
from processing.options import FitChoice, NoiseSource, ProcessingOptions, Units
from processing.parallel import Compute, open_compute
from processing.steps import Step
from sim_devices.lights import LIGHTS_DIR, load_truth

#: The rig taken by default: the demo's (``rigs/demo.toml``, the default geometry at half the
#: resolution), so that the many processings stay short.
DEFAULT_RIG_PATH = RIGS_DIR / "demo.toml"


def _copy_described(run_path: Path, dst: Path, errors: list[str]) -> Path:
    """A copy of the run file whose header describes the rig with ``errors`` made in it (none:
    as taken)."""
    shutil.copy(run_path, dst)
    if errors:
        with h5py.File(dst, "r+") as f:
            rig = json.loads(f["header/rig_json"][()])
            text = json.dumps(described_wrong_all(rig, errors), ensure_ascii=False)
            del f["header/rig_json"]
            f.create_dataset("header/rig_json", data=text, dtype=h5py.string_dtype("utf-8"))
    return dst


#: The ways each description is processed, by name: (the truth's layout given, ``fit_aperture``,
#: ``fit_sensor_distance``, ``calibrate_rig``, the table's column). The sensor distance is fitted as
#: ``process --fit-sensor-distance`` fits it: with the layout given, alone; found, with the aperture
#: after it. The self-calibrated ways fit the whole rig (``process`` does by default where it
#: searches for the sources); the others hold it as described.
WAYS = {
    "given": (True, False, False, False, "fits, layout given (max RMS / peak)"),
    "given, aperture fitted": (True, True, False, False, "the aperture fitted to the data: diameter, fits"),
    "given, sensor distance fitted": (True, False, True, False, "the sensor distance fitted: distance, fits"),
    "given, self-calibrated": (True, False, False, True, "layout given, the rig fitted to the data: quality, fits"),
    "found": (False, False, False, False, "layout found in the data: sources, farthest from the truth's, fits"),
    "found, aperture fitted": (
        False,
        True,
        False,
        False,
        "found, the aperture fitted: sources, farthest, diameter, fits",
    ),
    "found, sensor distance fitted": (
        False,
        True,
        True,
        False,
        "found, the sensor distance and the aperture fitted: sources, farthest, distance, diameter, fits",
    ),
    "found, self-calibrated": (
        False,
        False,
        False,
        True,
        "found, the rig fitted to the data (the default): sources, farthest, quality, fits",
    ),
}


def bench_tolerance(
    *,
    rig_path: str | Path | None = None,
    truth: str = "five-gaussians",
    positions: int = 66,
    errors: list[str] | None = None,
    preset: str | None = None,
    seeds: int = 5,
    ways: list[str] | None = None,
    layout_from_data: bool = False,
    fit_aperture: bool = False,
    fit_sensor_distance: bool = False,
    noise: bool = True,
    exposures: Sequence[float] = REFERENCE_EXPOSURES_S,
    scheduler: str = "local",
    workdir: str | Path | None = None,
    log: Callable[[str], None] | None = None,
) -> dict:
    """Take one simulated run, then process it with the rig described as taken and with each
    of ``errors`` (names :func:`parse_error` reads, default :data:`DEFAULT_ERRORS`), or with
    ``preset``'s errors all at once for each of ``seeds`` seeds (:func:`preset_errors`), in
    each of ``ways`` (names of :data:`WAYS`; by default the layout given, and found with
    ``layout_from_data``, with the aperture fitted too with ``fit_aperture`` and the sensor
    distance with ``fit_sensor_distance``).

    Returns the JSON the command prints: per case and way, the sources found and how far each
    is from the truth's (as the rig sees it: through the model's light frame), each source's
    error against the truth and how many of its quoted 1σ cover it, the rig's numbers fitted
    (with their truth where the error names one), the quality verdict and the time.
    ``log(text)`` hears of each processing as it ends."""
    say = log or (lambda _text: None)
    cases = _cases(errors, preset, seeds)
    rig = load_rig(rig_path or DEFAULT_RIG_PATH)
    truth_light = load_truth(truth)
    chosen = _ways(LIGHTS_DIR / f"{truth}.toml", ways, layout_from_data, fit_aperture, fit_sensor_distance)
    rows = []
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(workdir) if workdir is not None else Path(tmp)
        run_path = acquire_simulated(rig, truth, noise, exposures, positions, base)
        acquired = time.perf_counter()
        say(f"simulated run taken in {acquired - started:.0f} s: {run_path.name}")
        with open_compute(scheduler, warm_up=warm_up_worker) as compute:
            for k, (name, parts) in enumerate([("none", []), *cases]):
                copy = _copy_described(run_path, base / f"described-{k}.h5", parts)
                for w, (layout_name, way) in enumerate(chosen.items()):
                    row = {"error": name, "layout": layout_name}
                    if parts:
                        row["what"] = "; ".join(parse_error(part).what for part in parts)
                    out_dir = base / f"out-{k}-{w}"
                    rows.append(_process_one_way(copy, out_dir, way, compute, (rig, truth_light), row, say))
    result = {
        "benchmark": "tolerance",
        "rig": str(Path(rig_path or DEFAULT_RIG_PATH)),
        "truth": truth,
        "noise": noise,
        "positions": positions,
        "exposures_s": list(exposures),
        "preset": preset,
        "runs": rows,
        "summary": _summary(rows),
        "acquire_s": round(acquired - started, 1),
        "how": "one simulated run (with its calibration frames); copies of it processed with the rig description "
        "wrong (header /rig_json rewritten, frames and measured poses untouched), hdr + sources in each way; each "
        "truth emitter scored as bench accuracy does (against the nearest source found when found, through the "
        "model's light frame where the description moved it), its quoted 1σ against the truth (coverage)",
    }
    result["markdown"] = markdown_table(result)
    return result


def _cases(errors: list[str] | None, preset: str | None, seeds: int) -> list[tuple[str, list[str]]]:
    """The descriptions to try besides the exact one: (name, the errors made in it), every name
    checked before anything is acquired."""
    if preset is not None:
        if errors is not None:
            raise ValueError("--preset: give either --errors or --preset")
        if seeds < 1:
            raise ValueError(f"--seeds: {seeds}: at least one")
        cases = [(f"{preset} seed {seed}", preset_errors(preset, seed)) for seed in range(seeds)]
    else:
        cases = [(error, [error]) for error in (DEFAULT_ERRORS if errors is None else errors)]
    for _, parts in cases:
        for part in parts:
            parse_error(part)
    return cases


def _ways(
    given: Path, names: list[str] | None, layout_from_data: bool, fit_aperture: bool, fit_sensor_distance: bool
) -> dict:
    """The ways asked for, by name: (the layout file or None, ``fit_aperture``,
    ``fit_sensor_distance``, ``calibrate_rig``); by ``names``, or as the flags choose among the
    ways that hold the rig as described."""
    if names is not None:
        unknown = [name for name in names if name not in WAYS]
        if unknown or not names:
            raise ValueError(f"--ways: {', '.join(unknown) or 'none given'}: the ways are {'; '.join(WAYS)}")
    else:
        asked = {"aperture fitted": fit_aperture, "sensor distance fitted": fit_sensor_distance}
        names = [
            name
            for name, (given_layout, *_rest) in WAYS.items()
            if not WAYS[name][3] and (given_layout or layout_from_data) and asked.get(name.partition(", ")[2], True)
        ]
    return {name: (given if WAYS[name][0] else None, *WAYS[name][1:4]) for name in names}


def _process_one_way(
    copy: Path, out_dir: Path, way: tuple, compute: Compute, truth: tuple, row: dict, say: Callable[[str], None]
) -> dict:
    """``row`` completed with one processing of the run file ``copy`` the ``way`` :func:`_ways`
    names, its sources scored against the truth (the rig the run was taken with and its light);
    a processing that fails is said in the row."""
    truth_rig, truth_light = truth
    layout, fit_aperture, distance, calibrate = way
    t0 = time.perf_counter()
    try:
        options = ProcessingOptions(
            steps=(Step.HDR, Step.SOURCES),
            layout=layout,
            noise=NoiseSource.RIG,
            units=Units.WATTS_PER_SR,
            images=False,
            fit_aperture=FitChoice.ALWAYS if fit_aperture else FitChoice.NEVER,
            fit_sensor_distance=FitChoice.ALWAYS if distance else FitChoice.NEVER,
            calibrate_rig=FitChoice.ALWAYS if calibrate else FitChoice.NEVER,
        )
        report = process_run(copy, out_dir, options, compute=compute)
    except ProcessingError as exc:  # e.g. an aperture fit at its bound: said, and on to the next
        row.update(failed=str(exc), process_s=round(time.perf_counter() - t0, 1))
        say(f"{row['error']}, layout {row['layout']}: failed: {exc}")
        return row
    samples, model = fitted(report)
    frame = model_frame(model, truth_rig)
    scored = score_sources(model, samples, truth_light, matched=layout is None, cell_sums=False, frame=frame)
    row.update(
        sources_found=len(model.sources),
        max_rms_rel_error=max(s["rms_rel_error"] for s in scored["sources"]),
        sources=scored["sources"],
        coverage=scored["coverage"],
        quality=model.quality,
        process_s=round(time.perf_counter() - t0, 1),
        timings=report.timings,
    )
    if layout is None:
        row["max_centre_error_um"] = max(s["centre_error_um"] for s in scored["sources"])
        row["max_centre_error_relative_um"] = max(s["centre_error_relative_um"] for s in scored["sources"])
        row["centre_offset_um"] = scored["centre_offset_um"]
    if fit_aperture and report.aperture_fit is not None:
        row["aperture_fit"] = report.aperture_fit.record()
    if distance and report.sensor_distance_fit is not None:
        row["sensor_distance_fit"] = report.sensor_distance_fit.record()
    if report.rig_calibration is not None:
        row["rig_fit"] = _against_truth(report.rig_calibration.record(), row.get("what", ""), copy)
    say(
        f"{row['error']}, layout {row['layout']}: {row['sources_found']} sources, fits up to "
        f"{100 * row['max_rms_rel_error']:.2f} %, quality {row['quality'].get('status')} ({row['process_s']:.1f} s)"
    )
    return row


def _against_truth(record: dict, what: str, copy: Path) -> dict:
    """The rig's fitted numbers, each with the truth where the description's error names one:
    the sensor distance and the pinhole (a scale: the fit's change back to the truth is
    ``1/scale − 1``); the others move together with the held ones, and have no single truth."""
    fitted = record["fitted"]
    for number, field in (("sensor_distance", "camera.sensor_distance_m"), ("pinhole", "camera.pinhole_diameter_m")):
        scale = 1.0
        for part in what.split("; "):
            if part.startswith(f"{field} × "):
                scale *= float(part.rpartition(" ")[2])
        fitted[number]["truth"] = round(100.0 * (1.0 / scale - 1.0), 6)
        fitted[number]["within_sigma"] = (
            abs(fitted[number]["value"] - fitted[number]["truth"]) <= fitted[number]["sigma"]
        )
    return record


def _summary(rows: list[dict]) -> dict:
    """Per way: the worst source's error, the cases suspect, the coverage over every source."""
    out: dict[str, dict] = {}
    for row in rows:
        if "failed" in row:
            continue
        way = out.setdefault(row["layout"], {"cases": 0, "worst_rms_rel_error": 0.0, "suspect": 0, "cover": []})
        way["cases"] += 1
        way["worst_rms_rel_error"] = max(way["worst_rms_rel_error"], row["max_rms_rel_error"])
        way["suspect"] += int(row.get("quality", {}).get("status") == "suspect")
        way["cover"] += row["sources"]
    for way in out.values():
        way["coverage"] = coverage_share(way.pop("cover"))
    return out


def model_frame(model: LightModel, truth_rig: Rig) -> Pose | None:
    """The light frame the model was made in, in the truth's light frame, at the sweep's middle
    position (None where they are one): the model's rig (its provenance) composing the arm's
    tool pose there with its own base frame and mount, against the truth's."""
    model_rig = rig_from_dict(model.provenance["rig_description"])
    tool = truth_rig.tool_poses()[len(truth_rig.tool_poses()) // 2]
    frame = truth_rig.light_pose(tool).inverse().compose(model_rig.light_pose(tool))
    moved, turned = frame.distance_to(Pose(0.0, 0.0, 0.0))
    return None if moved < 1e-12 and turned < 1e-9 else frame


def markdown_table(result: dict) -> str:
    """The runs as a markdown table: one row per description, one column per way."""
    by_error: dict[str, dict[str, dict]] = {}
    for row in result["runs"]:
        by_error.setdefault(row["error"], {})[row["layout"]] = row
    ways = [way for way in WAYS if any(way in rows for rows in by_error.values())]
    lines = ["| rig description |" + "".join(f" {WAYS[way][4]} |" for way in ways), "| --- |" + " --- |" * len(ways)]
    for error, rows in by_error.items():
        what = next(iter(rows.values())).get("what", "")
        label = "as taken" if error == "none" else (error if len(what) > 80 else f"{error} (`{what}`)")
        lines.append(f"| {label} |" + "".join(_cell(rows[way]) if way in rows else " |" for way in ways))
    lines.append("")
    lines.append("Quoted 1σ that hold the truth, over every case and source (68 % for a true 1σ):")
    lines.append("")
    lines.append("| way | fits' parameters | samples | I(θ) band | rig's numbers with a truth |")
    lines.append("| --- | --- | --- | --- | --- |")
    for way in ways:
        share = result.get("summary", {}).get(way, {}).get("coverage", {})
        rig = [
            number["within_sigma"]
            for row in result["runs"]
            if row.get("layout") == way and "rig_fit" in row
            for number in row["rig_fit"]["fitted"].values()
            if "within_sigma" in number
        ]
        cells = [_share(share.get(kind)) for kind in ("parameters", "samples", "band")]
        cells.append(f"{sum(rig)}/{len(rig)}" if rig else "")
        lines.append(f"| {WAYS[way][4]} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _share(value: float | None) -> str:
    return "" if value is None else f"{100 * value:.0f} %"


def _cell(row: dict) -> str:
    """A table cell for one processing: for sources found in the data, how many and the farthest
    from the truth's; the sensor distance and the aperture when they were fitted; the quality
    where the rig was fitted; the fits; or why it failed."""
    if "failed" in row:
        return f" failed: {row['failed'].replace('|', '/')} |"
    parts = []
    if "max_centre_error_um" in row:
        parts.append(f"{row['sources_found']} sources")
        offset = math.hypot(*row.get("centre_offset_um", (0.0, 0.0)))
        if offset >= 1.0:  # a mount error moves the light's frame: the places after that common offset
            parts.append(f"{row['max_centre_error_relative_um']:.0f} µm (after a common {offset:.0f} µm)")
        else:
            parts.append(f"{row['max_centre_error_um']:.0f} µm")
    if "sensor_distance_fit" in row:
        parts.append(f"{1e3 * row['sensor_distance_fit']['fitted_m']:.3f} mm")
    if "aperture_fit" in row:
        parts.append(f"{1e3 * row['aperture_fit']['fitted_m']:.4f} mm")
    if "rig_fit" in row:
        parts.append(str(row["quality"].get("status", "")))
    parts.append(f"{100 * row['max_rms_rel_error']:.2f} %")
    return f" {', '.join(parts)} |"
