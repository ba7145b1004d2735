"""The reference simulation through the whole chain, compared with the truth.

``docs/measurement.md`` ("The ground-truth reference simulation"): the simulated rig (arm over Modbus,
pinhole camera with diffraction and noise) takes the default sweep into a run file through
the daemon's run engine; the processing merges the brackets, unmixes the sources with
templates and fits each one; every fit is compared with the truth over the θ range its
samples cover: ``error = RMS(I_fit − I_true) / max(I_true)``. The chief-ray cell sums are
fitted and scored on the same data, so the gain from unmixing is shown, not claimed.
"""

from __future__ import annotations

import json
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import h5py

from acquisition.benchmarks.acquire import run_file_of
from acquisition.benchmarks.scoring import fitted, score_sources
from acquisition.daemon.catalog import Catalog
from acquisition.daemon.devices import open_devices
from acquisition.daemon.engine import RunEngine
from acquisition.daemon.models import FixedBracket, RunRequest
from acquisition.daemon.settings import DaemonSettings, load_settings
from drivers.contracts.rig import Rig, load_rig
from processing.light_run.run import process_run
from processing.options import FitMethod, NoiseSource, ProcessingOptions, Units
from processing.steps import Step
from sim_devices.lights import LIGHTS_DIR, load_truth

#: The reference simulation's bracket: 20 µs to 12.5 ms in steps of 5.
REFERENCE_EXPOSURES_S = (2e-5, 1e-4, 5e-4, 2.5e-3, 1.25e-2)


def acquire_simulated(
    rig: Rig,
    truth_name: str,
    noise: bool,
    exposures: Sequence[float],
    positions: int | None,
    workdir: Path,
    *,
    preset: str = "light-sweep",
    light_results: str | None = None,
) -> Path:
    """Take one run on the simulated rig through the daemon's run engine; the run file's path."""
    settings = load_settings(None, data_dir=workdir / "data")
    settings.arm.simulated.speed_m_s = 1.0
    settings.arm.simulated.accel_m_s2 = 10.0
    settings.camera.simulated.truth = truth_name
    settings.camera.simulated.noise = noise
    settings.camera.simulated.diffraction = True
    request = RunRequest.model_validate(
        {
            "preset": preset,
            "count": positions,
            "bracket": FixedBracket(exposures_s=list(exposures)),
            "light_results": light_results,
        }
    )
    return take_run(settings, rig, request)


def take_run(settings: DaemonSettings, rig: Rig, request: RunRequest) -> Path:
    """One run of ``request`` through the daemon's run engine, on the devices ``settings``
    name (the simulated ones by default), in ``settings.data_dir``; the run file's path.

    Raises RuntimeError when the run does not complete."""
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    catalog = Catalog(settings.catalog_url, rig=settings.rig_name)
    devices = open_devices(settings, rig)
    try:
        engine = RunEngine(settings, rig, devices, catalog)
        record = engine.start_run(request)
        engine.wait()
        state = catalog.get_run(record.id)
        if state.state != "complete":
            raise RuntimeError(f"simulated run ended {state.state}: {state.last_error}")
        return run_file_of(state)
    finally:
        devices.close()
        catalog.close()


def bench_accuracy(
    *,
    noise: bool = True,
    truth: str = "five-gaussians",
    positions: int = 66,
    rig_path: str | Path | None = None,
    exposures: Sequence[float] = REFERENCE_EXPOSURES_S,
    fit_method: str = "gaussian",
    workdir: str | Path | None = None,
    layout_from_data: bool = False,
    templates: str | None = None,
) -> dict:
    """Run the reference simulation and score the fitted sources against the truth.

    ``layout_from_data``: the processing is not given the truth's layout but finds the
    sources in the data; each truth emitter is then scored against the nearest source found,
    and the distance between them is reported too. The target then also asks for as many
    sources as the truth has, each the nearest of a different emitter.

    ``templates``: the point spread the processing's templates model (``geometric-airy`` or
    ``fresnel``), where it is not the camera's (the rig's ``camera.point_spread``, which the
    simulated camera takes): the run's header then describes the camera with it, so that what
    a model costs on a camera of the other kind is measured."""
    if templates not in (None, "geometric-airy", "fresnel"):
        raise ValueError(f"--templates: {templates!r} is not geometric-airy or fresnel")
    rig = load_rig(rig_path)
    truth_light = load_truth(truth)
    layout = None if layout_from_data else LIGHTS_DIR / f"{truth}.toml"
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(workdir) if workdir is not None else Path(tmp)
        run_path = acquire_simulated(rig, truth, noise, exposures, positions, base)
        acquired = time.perf_counter()
        if templates is not None and templates != rig.camera.point_spread:
            describe_point_spread(run_path, templates)
        report = process_run(
            run_path,
            base / "out",
            ProcessingOptions(
                steps=(Step.HDR, Step.SOURCES),
                layout=layout,
                noise=NoiseSource.RIG,
                fit_method=FitMethod(fit_method),
                units=Units.WATTS_PER_SR,
            ),
        )
        processed = time.perf_counter()
    samples, model = fitted(report)
    scored = score_sources(model, samples, truth_light, matched=layout_from_data, fit_method=fit_method)
    out_sources = scored["sources"]
    worst = max(s["rms_rel_error"] for s in out_sources)
    target = 0.01 if noise else 0.003
    layout_ok = not layout_from_data or (len(model.sources) == len(truth_light.emitters) == len(set(scored["matched"])))
    return {
        "benchmark": "accuracy",
        "noise": noise,
        "truth": truth,
        "layout": model.provenance.get("layout", ""),
        "aperture": model.provenance.get("aperture_m", ""),  # fitted to the data where the sources were searched for
        "point_spread": {"camera": rig.camera.point_spread, "templates": templates or rig.camera.point_spread},
        "quality": model.quality,
        "sources_found": len(model.sources),
        "positions": positions,
        "exposures_s": list(exposures),
        "estimator": report.estimator,
        "estimator_reason": report.estimator_reason,
        "spatial_resolution_mm": round(1e3 * report.spatial_resolution_m, 3),
        "sources": out_sources,
        "max_rms_rel_error": worst,
        "target": target,
        "meets_target": worst <= target and layout_ok,
        # The share of quoted 1σ that hold the truth (68 % for a true 1σ; the 50-85 %).
        **{f"coverage_{kind}": share for kind, share in scored["coverage"].items()},
        "acquire_s": round(acquired - started, 1),
        "process_s": round(processed - acquired, 1),
    }


def describe_point_spread(run_path: Path, point_spread: str) -> None:
    """The run file's header made to describe its camera's point spread as ``point_spread``."""
    with h5py.File(run_path, "r+") as f:
        rig = json.loads(f["header/rig_json"][()])
        rig["camera"]["point_spread"] = point_spread
        del f["header/rig_json"]
        f.create_dataset("header/rig_json", data=json.dumps(rig, ensure_ascii=False), dtype=h5py.string_dtype("utf-8"))
