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
import shutil
import tempfile
import time
from pathlib import Path

import h5py

from acquisition.benchmarks.accuracy import REFERENCE_EXPOSURES_S, acquire_simulated
from acquisition.benchmarks.description_errors import DEFAULT_ERRORS, described_wrong, parse_error
from acquisition.benchmarks.scoring import score_sources
from drivers.contracts.rig import RIGS_DIR, load_rig, rig_from_dict
from drivers.pose import Pose
from processing.light_run.errors import ProcessingError
from processing.light_run.position import warm_up_worker
from processing.light_run.run import process_run
from processing.options import FitChoice
from processing.parallel import open_compute
from sim_devices.lights import LIGHTS_DIR, load_truth

#: The rig taken by default: the demo's (``rigs/demo.toml``, the default geometry at half the
#: resolution), so that the many processings stay short.
DEFAULT_RIG_PATH = RIGS_DIR / "demo.toml"


def _copy_described(run_path: Path, dst: Path, error: str | None) -> Path:
    """A copy of the run file whose header describes the rig with ``error`` (None: as taken)."""
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
    exposures=REFERENCE_EXPOSURES_S,
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
    say = log or (lambda _text: None)
    errors = list(DEFAULT_ERRORS) if errors is None else list(errors)
    for error in errors:
        parse_error(error)  # every name checked before anything is acquired
    rig = load_rig(rig_path or DEFAULT_RIG_PATH)
    truth_light = load_truth(truth)
    ways = _ways(LIGHTS_DIR / f"{truth}.toml", layout_from_data, fit_aperture, fit_sensor_distance)
    rows = []
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(workdir) if workdir is not None else Path(tmp)
        run_path = acquire_simulated(rig, truth, noise, exposures, positions, base)
        acquired = time.perf_counter()
        say(f"simulated run taken in {acquired - started:.0f} s: {run_path.name}")
        with open_compute(scheduler, warm_up=warm_up_worker) as compute:
            for k, error in enumerate([None, *errors]):
                copy = _copy_described(run_path, base / f"described-{k}.h5", error)
                for w, (layout_name, way) in enumerate(ways.items()):
                    row = {"error": error or "none", "layout": layout_name}
                    if error is not None:
                        row["what"] = parse_error(error).what
                    out_dir = base / f"out-{k}-{w}"
                    rows.append(_process_one_way(copy, out_dir, way, compute, (rig, truth_light), row, say))
    result = {
        "benchmark": "tolerance",
        "rig": str(Path(rig_path or DEFAULT_RIG_PATH)),
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


def _ways(given: Path, layout_from_data: bool, fit_aperture: bool, fit_sensor_distance: bool) -> dict:
    """The ways of :data:`WAYS` asked for, by name: (the layout file or None, ``fit_aperture``,
    ``fit_sensor_distance``)."""
    asked = {"aperture fitted": fit_aperture, "sensor distance fitted": fit_sensor_distance}
    return {
        name: (given if given_layout else None, aperture, distance)
        for name, (given_layout, aperture, distance, _) in WAYS.items()
        if (given_layout or layout_from_data) and asked.get(name.partition(", ")[2], True)
    }


def _process_one_way(copy: Path, out_dir: Path, way: tuple, compute, truth: tuple, row: dict, say) -> dict:
    """``row`` completed with one processing of the run file ``copy`` the ``way`` :func:`_ways`
    names, its sources scored against the truth (the rig the run was taken with and its light);
    a processing that fails is said in the row."""
    truth_rig, truth_light = truth
    layout, fitted, distance = way
    t0 = time.perf_counter()
    try:
        report = process_run(
            copy,
            out_dir,
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
        say(f"{row['error']}, layout {row['layout']}: failed: {exc}")
        return row
    frame = model_frame(report.model, truth_rig)
    scored = score_sources(
        report.model, report.samples, truth_light, matched=layout is None, cell_sums=False, frame=frame
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
    say(
        f"{row['error']}, layout {row['layout']}: {row['sources_found']} sources, fits up to "
        f"{100 * row['max_rms_rel_error']:.2f} % ({row['process_s']:.1f} s)"
    )
    return row


def model_frame(model, truth_rig) -> Pose | None:
    """The light frame the model was made in, in the truth's light frame, at the sweep's middle
    position (None where they are one): the model's rig (its provenance) composing the arm's
    tool pose there with its own base frame and mount, against the truth's."""
    model_rig = rig_from_dict(model.provenance["rig_description"])
    tool = truth_rig.tool_poses()[len(truth_rig.tool_poses()) // 2]
    frame = truth_rig.light_pose(tool).inverse().compose(model_rig.light_pose(tool))
    moved, turned = frame.distance_to(Pose(0.0, 0.0, 0.0))
    return None if moved < 1e-12 and turned < 1e-9 else frame


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
