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

#: The errors of the description tried, by name: (the rig field, "scale" or "add", by how much).
#: Sizes a lab can plausibly get wrong: a 0.2 mm pinhole drilled or measured 10 % off, the
#: sensor distance of a camera without a datasheet, the ball placed by eye, the light's
#: mount measured with a rule.
RIG_ERRORS: dict[str, tuple[str, str, float | tuple[float, float, float]]] = {
    "pinhole+10%": ("camera.pinhole_diameter_m", "scale", 1.10),
    "pinhole-10%": ("camera.pinhole_diameter_m", "scale", 0.90),
    "sensor-distance+1%": ("camera.sensor_distance_m", "scale", 1.01),
    "ball-x+0.2mm": ("ball.centre_m", "add", (2e-4, 0.0, 0.0)),
    "ball-z+0.2mm": ("ball.centre_m", "add", (0.0, 0.0, 2e-4)),
    "ball-radius+0.1mm": ("ball.radius_m", "add", 1e-4),
    "light-x+0.2mm": ("light.light_to_tool.position_m", "add", (2e-4, 0.0, 0.0)),
    "light-z+0.5mm": ("light.light_to_tool.position_m", "add", (0.0, 0.0, 5e-4)),
}


def _require_known(errors) -> None:
    unknown = [error for error in errors if error not in RIG_ERRORS]
    if unknown:
        raise ValueError(f"--errors: {unknown[0]!r} is not one of {', '.join(RIG_ERRORS)}")


def described_wrong(rig: dict, error: str) -> dict:
    """``rig`` (the run file's JSON description) with :data:`RIG_ERRORS` ``[error]`` made in it."""
    _require_known([error])
    field, how, amount = RIG_ERRORS[error]
    out = json.loads(json.dumps(rig))
    *parents, key = field.split(".")
    holder = out
    for name in parents:
        holder = holder[name]
    value = holder[key]
    if how == "scale":
        holder[key] = value * amount
    elif isinstance(amount, tuple):
        holder[key] = [v + a for v, a in zip(value, amount, strict=True)]
    else:
        holder[key] = value + amount
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


def bench_tolerance(*, rig_path=None, truth: str = "five-gaussians", positions: int = 66, errors=None,
                    layout_from_data: bool = False, fit_aperture: bool = False, noise: bool = True,
                    exposures=(2e-5, 1e-4, 5e-4, 2.5e-3, 1.25e-2), scheduler: str = "local",
                    workdir: str | Path | None = None, log=None) -> dict:  # fmt: skip
    """Take one simulated run, then process it with the rig described as taken and with each
    of ``errors`` (names of :data:`RIG_ERRORS`, default all), given the truth's layout and,
    with ``layout_from_data``, also finding the sources in the data; with ``fit_aperture``,
    each of those again with the aperture fitted to the data (``process --fit-aperture``).

    Returns the JSON the command prints: per error and layout, the sources found and how far
    from the truth's, and each source's error against the truth. ``log(text)`` hears of each
    processing as it ends."""
    from acquisition.benchmarks.accuracy import acquire_simulated, score_sources
    from acquisition.demo import DEMO_RIG_PATH
    from acquisition.rig import load_rig
    from processing.parallel import open_compute
    from processing.pipeline import process_run, warm_up_worker
    from sim_devices.lights import LIGHTS_DIR, load_truth

    errors = list(RIG_ERRORS) if errors is None else list(errors)
    _require_known(errors)
    rig = load_rig(rig_path or DEMO_RIG_PATH)
    truth_light = load_truth(truth)
    given = LIGHTS_DIR / f"{truth}.toml"
    ways = {"given": (given, False)}
    if fit_aperture:
        ways["given, aperture fitted"] = (given, True)
    if layout_from_data:
        ways["found"] = (None, False)
        if fit_aperture:
            ways["found, aperture fitted"] = (None, True)
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
                for w, (layout_name, (layout, fitted)) in enumerate(ways.items()):
                    t0 = time.perf_counter()
                    report = process_run(copy, base / f"out-{k}-{w}", steps=("hdr", "sources"), layout=layout,
                                         noise="rig", units="W/sr", compute=compute, images=False,
                                         fit_aperture=fitted)  # fmt: skip
                    scored = score_sources(report.model, report.samples, truth_light, matched=layout is None,
                                           cell_sums=False)  # fmt: skip
                    row = {"error": error or "none", "layout": layout_name, "sources_found": len(report.model.sources),
                           "max_rms_rel_error": max(s["rms_rel_error"] for s in scored["sources"]),
                           "sources": scored["sources"], "process_s": round(time.perf_counter() - t0, 1)}  # fmt: skip
                    if error is not None:
                        field, how, amount = RIG_ERRORS[error]
                        row["what"] = f"{field} {'×' if how == 'scale' else '+'} {amount}"
                    if layout is None:
                        row["max_centre_error_um"] = max(s["centre_error_um"] for s in scored["sources"])
                    if fitted:
                        row["aperture_fit"] = report.aperture_fit
                    rows.append(row)
                    if log:
                        log(f"{row['error']}, layout {layout_name}: {row['sources_found']} sources, fits up to "
                            f"{100 * row['max_rms_rel_error']:.2f} % ({row['process_s']:.1f} s)")  # fmt: skip
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
    }  # fmt: skip
    result["markdown"] = markdown_table(result)
    return result


def markdown_table(result: dict) -> str:
    """The runs as a markdown table: one row per error of the description."""
    by_error: dict[str, dict[str, dict]] = {}
    for row in result["runs"]:
        by_error.setdefault(row["error"], {})[row["layout"]] = row
    found = any("found" in rows for rows in by_error.values())
    fitted = any("given, aperture fitted" in rows for rows in by_error.values())
    found_fitted = any("found, aperture fitted" in rows for rows in by_error.values())
    head = "| rig description | fits, layout given (max RMS / peak) |"
    rule = "| --- | --- |"
    if fitted:
        head += " the aperture fitted to the data: diameter, fits |"
        rule += " --- |"
    if found:
        head += " layout found in the data: sources, farthest from the truth's, fits |"
        rule += " --- |"
    if found_fitted:
        head += " found, the aperture fitted: sources, farthest, diameter, fits |"
        rule += " --- |"
    lines = [head, rule]
    for error, rows in by_error.items():
        given = rows["given"]
        what = "as taken" if error == "none" else f"{error} (`{given['what']}`)"
        line = f"| {what} | {100 * given['max_rms_rel_error']:.2f} % |"
        if fitted:
            row = rows["given, aperture fitted"]
            line += f" {1e3 * row['aperture_fit']['fitted_m']:.4f} mm, {100 * row['max_rms_rel_error']:.2f} % |"
        if found:
            line += _found_cell(rows["found"])
        if found_fitted:
            line += _found_cell(rows["found, aperture fitted"])
        lines.append(line)
    return "\n".join(lines)


def _found_cell(row: dict) -> str:
    """A table cell for sources found in the data: how many, the farthest from the truth's,
    the aperture when it was fitted, the fits."""
    aperture = f"{1e3 * row['aperture_fit']['fitted_m']:.4f} mm, " if "aperture_fit" in row else ""
    return f" {row['sources_found']} sources, {row['max_centre_error_um']:.0f} µm, {aperture}{100 * row['max_rms_rel_error']:.2f} % |"
