"""The ``mirrorgonio`` command line: one program, one subcommand per job.

Bad input ends with a one-line ``error: ...`` on standard error and exit status 2; the
message names the file or the field.
"""

from __future__ import annotations

import json
import math
import statistics
import sys
import time
from pathlib import Path
from typing import Annotated

import typer

app = typer.Typer(
    name="mirrorgonio",
    help="A mirror-ball goniophotometer: measure a near-field light source.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
simulate_app = typer.Typer(
    help="Simulated devices: the arm's Modbus server, one rendered capture.", no_args_is_help=True
)
bench_app = typer.Typer(help="Benchmarks that print what they measured.", no_args_is_help=True)
app.add_typer(simulate_app, name="simulate")
app.add_typer(bench_app, name="bench")

RigOption = Annotated[Path, typer.Option("--rig", help="Rig description (TOML).")]
SchedulerOption = Annotated[
    str,
    typer.Option(
        "--scheduler",
        envvar="MG_SCHEDULER",
        help="Where positions are processed: local (a Dask cluster on this machine, one process per core), "
        "tcp://HOST:8786 (an existing Dask scheduler), or none (this process, no Dask).",
    ),
]
WorkersOption = Annotated[
    int | None, typer.Option("--workers", min=1, help="Worker processes of the local cluster (default: the cores).")
]


@app.callback()
def main_options(
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log the libraries' own messages.")] = False,
) -> None:
    """A mirror-ball goniophotometer: measure a near-field light source."""
    import logging

    # pymodbus logs connection failures straight to stderr; our errors already say it in one line.
    logging.getLogger("pymodbus").setLevel(logging.DEBUG if verbose else logging.CRITICAL)


def _fail(message: str) -> typer.Exit:
    typer.echo(f"error: {message}", err=True)
    return typer.Exit(code=2)


def _domain_errors():
    from drivers.contracts.rig import RigError
    from drivers.errors import DeviceError
    from sim_devices.lights import TruthError

    return (RigError, TruthError, DeviceError, OSError)


def _print_result(result: dict, as_json: bool) -> None:
    """A benchmark's result: one JSON line with --json, indented for people otherwise."""
    typer.echo(json.dumps(result) if as_json else json.dumps(result, indent=2))


def _default_rig() -> Path:
    from drivers.contracts.rig import DEFAULT_RIG_PATH

    return DEFAULT_RIG_PATH


# --- serve ----------------------------------------------------------------------------------
@app.command("serve")
def serve(
    config: Annotated[
        Path | None, typer.Option("--config", help="daemon.toml (docs/daemon.md); simulated rig without one.")
    ] = None,
    host: Annotated[
        str | None, typer.Option(help="Address to listen on (default from the configuration: 127.0.0.1).")
    ] = None,
    port: Annotated[int | None, typer.Option(help="TCP port (default from the configuration: 8000).")] = None,
    data_dir: Annotated[Path | None, typer.Option("--data-dir", help="Where run files and the catalog live.")] = None,
) -> None:
    """Run the acquisition daemon (REST API and web page) under uvicorn."""
    from acquisition.settings import SettingsError, load_settings

    try:
        settings = load_settings(config, host=host, port=port, data_dir=data_dir)
        settings.require_token_off_loopback()
    except (SettingsError, OSError) as exc:
        raise _fail(str(exc)) from None
    import uvicorn

    from acquisition.app import create_app

    try:
        uvicorn.run(create_app(settings), host=settings.host, port=settings.port, log_level="info")
    except _domain_errors() as exc:
        raise _fail(str(exc)) from None


# --- process ------------------------------------------------------------------------------
def _distinct_runs(runs: list[Path]) -> list[Path]:
    """The runs in the order given, a file named twice kept once (with a note)."""
    seen: dict[Path, Path] = {}
    for run in runs:
        key = run.resolve()
        if key in seen:
            typer.echo(f"note: {run} is the same file as {seen[key]}: processed once", err=True)
            continue
        seen[key] = run
    return list(seen.values())


def _output_folders(runs: list[Path], out: Path | None) -> dict[Path, Path | None]:
    """Where each run's results go: ``out`` (files named after the run), or beside the run.

    Runs that share a name (``day1/run-0001.h5``, ``day2/run-0001.h5``) would write the
    same files in ``out``: each of them goes to a subfolder named after its own folder
    (``out/day1/``, ``out/day2/``), with a short hash of its path when those names are
    the same too.
    """
    import hashlib

    if out is None:
        return {run: None for run in runs}
    by_stem: dict[str, list[Path]] = {}
    for run in runs:
        by_stem.setdefault(run.stem, []).append(run)
    folders: dict[Path, Path | None] = {}
    for group in by_stem.values():
        if len(group) == 1:
            folders[group[0]] = out
            continue
        parents = [run.resolve().parent.name for run in group]
        distinct = len(set(parents)) == len(parents) and all(parents)
        for run, parent in zip(group, parents, strict=True):
            digest = hashlib.sha1(str(run.resolve()).encode()).hexdigest()[:8]
            folders[run] = out / (parent if distinct else f"{parent or 'root'}-{digest}")
    return folders


def _naming(run: Path, message: str) -> str:
    """An error message on one line, starting with the run when it does not name it."""
    message = " ".join(message.split())
    return message if str(run) in message or run.name in message else f"{run}: {message}"


def _print_batch_summary(outcomes: list) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title="processed runs", title_justify="left")
    table.add_column("#", justify="right", no_wrap=True)
    table.add_column("run", overflow="fold")
    table.add_column("result", no_wrap=True)
    table.add_column("positions", justify="right", no_wrap=True)
    table.add_column("time", justify="right", no_wrap=True)
    table.add_column("results", overflow="fold")
    for number, (run, report, seconds, error) in enumerate(outcomes, 1):
        if error:
            table.add_row(str(number), str(run), "[red]failed[/red]", "", f"{seconds:.1f} s", "(see the error below)")
        else:
            table.add_row(
                str(number),
                str(run),
                "[green]ok[/green]",
                str(report.positions),
                f"{seconds:.1f} s",
                str(report.results_file),
            )
    failed = sum(1 for *_, error in outcomes if error)
    console = Console()
    console.print(table)
    console.print(
        f"{len(outcomes) - failed} of {len(outcomes)} runs processed" + (f", {failed} failed" if failed else ""),
        highlight=False,
    )


@app.command("process")
def process(
    runs: Annotated[list[Path], typer.Argument(help="Run files (HDF5) to process.")],
    out: Annotated[
        Path | None, typer.Option("--out", help="Folder for the results (default: beside each run).")
    ] = None,
    steps: Annotated[str, typer.Option(help="Comma-separated steps: hdr, sources.")] = "hdr,sources",
    method: Annotated[str, typer.Option(help="HDR estimator: optimal or poisson.")] = "optimal",
    noise: Annotated[
        str, typer.Option(help="Noise model: auto (estimate, else the rig's), estimated, or rig.")
    ] = "auto",
    layout: Annotated[
        Path | None, typer.Option(help="The sources on the light plane (TOML); found in the data without one.")
    ] = None,
    estimator: Annotated[str, typer.Option(help="auto (from the footprint), templates, or cell-sums.")] = "auto",
    fit: Annotated[str, typer.Option(help="Fit: gaussian, polynomial, cos-power, gaussian-2d.")] = "gaussian",
    ball_centre: Annotated[
        str | None,
        typer.Option("--ball-centre", help="Measured ball centre X,Y,Z in metres (rig frame; from `calibrate`)."),
    ] = None,
    images: Annotated[
        bool, typer.Option(help="Write an OpenEXR and a PNG preview of every position (hdr step).")
    ] = True,
    fit_aperture: Annotated[
        bool | None,
        typer.Option(
            "--fit-aperture/--no-fit-aperture",
            help="Fit the camera's aperture "
            "(pinhole) diameter to the data before the sources are estimated "
            "(docs/light-model.md). Default: fitted when the sources are searched "
            "for in the data (no --layout), the rig's diameter kept if that "
            "fit fails.",
            show_default=False,
        ),
    ] = None,
    fit_sensor_distance: Annotated[
        bool,
        typer.Option(
            "--fit-sensor-distance",
            help="Fit the sensor distance (pinhole "
            "to sensor) to the data too, before the aperture: about a minute "
            "more on the demo rig (docs/light-model.md).",
        ),
    ] = False,
    scheduler: SchedulerOption = "local",
    workers: WorkersOption = None,
) -> None:
    """Turn run files into results: HDR radiance per position (OpenEXR, PNG), the light model,
    and the IES, LDT and TM-25 files.

    Several runs in one call: each is processed in turn, a failed run does not stop the
    others, a summary table ends the output and the exit status is 2 if any run failed.
    With --out, each run's results are named after the run (RUN.results.h5, RUN.hdr/, ...);
    runs of the same name from different folders go to a subfolder each (docs/import.md)."""
    from rich.progress import Progress, TextColumn

    from processing.hdr import HDRError
    from processing.lightmodel import describe_fitted
    from processing.pipeline import ProcessingError, process_run

    if noise not in ("auto", "estimated", "rig"):
        raise _fail(f"--noise: {noise!r} is not one of auto, estimated, rig")
    step_list = tuple(s for s in steps.split(",") if s)
    centre = None
    if ball_centre is not None:
        try:
            centre = tuple(float(v) for v in ball_centre.split(","))
            assert len(centre) == 3
        except (ValueError, AssertionError):
            raise _fail(f"--ball-centre: expected X,Y,Z in metres, got {ball_centre!r}") from None
    from processing.pipeline import STEPS

    unknown = [s for s in step_list if s not in STEPS]
    if unknown:
        raise _fail(f"--steps: unknown step {unknown[0]!r} (known: {', '.join(STEPS)})")
    distinct = _distinct_runs(runs)
    folders = _output_folders(distinct, out)
    batch = len(distinct) > 1
    outcomes: list[tuple[Path, object, float, str]] = []  # run, report or None, seconds, error
    from processing.parallel import ComputeError, open_compute
    from processing.pipeline import warm_up_worker

    try:
        compute = open_compute(scheduler, workers=workers, warm_up=warm_up_worker)
    except ComputeError as exc:
        raise _fail(str(exc)) from None
    with compute, Progress(*Progress.get_default_columns(), TextColumn("{task.fields[note]}"), transient=True) as bar:
        overall = bar.add_task("runs", total=len(distinct), note="") if batch else None
        for number, run in enumerate(distinct, 1):
            label = f"[{number}/{len(distinct)}] {run.name}" if batch else run.name
            task = bar.add_task(label, total=None, note="positions")
            started = time.perf_counter()
            try:
                report = process_run(
                    run,
                    folders[run],
                    steps=step_list,
                    method=method,
                    noise=noise,
                    layout=layout,
                    estimator=estimator,
                    fit_method=fit,
                    ball_centre=centre,
                    compute=compute,
                    images=images,
                    fit_aperture=fit_aperture,
                    fit_sensor_distance=fit_sensor_distance,
                    progress=lambda done, total, task=task: bar.update(task, completed=done, total=total),
                )
            except (ProcessingError, HDRError, ValueError, OSError) as exc:
                if not batch:
                    raise _fail(str(exc)) from None
                outcomes.append((run, None, time.perf_counter() - started, _naming(run, str(exc))))
                continue
            except Exception as exc:  # noqa: BLE001 - one run's failure must not stop the batch
                if not batch:
                    raise
                outcomes.append(
                    (run, None, time.perf_counter() - started, _naming(run, f"unexpected {type(exc).__name__}: {exc}"))
                )
                continue
            finally:
                bar.remove_task(task)
                if overall is not None:
                    bar.advance(overall)
            outcomes.append((run, report, time.perf_counter() - started, ""))
            noise_model = report.noise
            typer.echo(
                f"{run}: {report.positions} positions -> {report.results_file} "
                f"(noise {noise_model.source}: gain {noise_model.gain_e_per_dn:.3f} e-/DN, "
                f"read noise {noise_model.read_noise_dn:.3f} DN; EXR and PNG in "
                f"{report.results_file.parent / (run.stem + '.hdr')})"
            )
            if report.light_model:
                typer.echo(f"  sources: {report.estimator_reason}")
                for label, fitted, digits in (
                    ("aperture", report.aperture_fit, ".4g"),
                    ("sensor distance", report.sensor_distance_fit, ".3f"),
                ):
                    if fitted.get("fitted_m") is not None:
                        later = f" (a later fit failed: {fitted['failed']})" if fitted.get("failed") else ""
                        typer.echo(f"  {label}: {describe_fitted(fitted, digits)}{later}")
                    elif fitted.get("failed"):
                        typer.echo(
                            f"  {label}: as the rig describes it (the fit to the data failed: {fitted['failed']})"
                        )
                typer.echo(
                    f"  light model {report.light_model}; "
                    + ", ".join(
                        f"{kind.upper()} {paths[0]}"
                        for kind, paths in report.outputs.items()
                        if kind in ("ies", "ldt", "tm25", "report")
                    )
                )
    if batch:
        _print_batch_summary(outcomes)
    failed = [error for *_, error in outcomes if error]
    for error in failed:
        typer.echo(f"error: {error}", err=True)
    if failed:
        raise typer.Exit(code=2)


# --- worker -------------------------------------------------------------------------------
@app.command("worker")
def worker_command(
    config: Annotated[
        Path | None,
        typer.Option("--config", help="daemon.toml: the worker uses its data_dir (the catalog and the runs)."),
    ] = None,
    data_dir: Annotated[
        Path | None,
        typer.Option("--data-dir", help="Where the catalog and the run files are (overrides the configuration)."),
    ] = None,
    scheduler: SchedulerOption = "local",
    workers: WorkersOption = None,
    once: Annotated[bool, typer.Option("--once", help="Process the jobs that can run now, then exit.")] = False,
    poll: Annotated[float, typer.Option(min=0.05, help="Seconds between looks at the queue when it is empty.")] = 2.0,
    heartbeat: Annotated[float, typer.Option(min=0.05, help="Seconds between heartbeats while a job runs.")] = 5.0,
    stale_after: Annotated[
        float,
        typer.Option(
            "--stale-after",
            min=0.1,
            help="A running job without a heartbeat for this long is requeued (its worker died).",
        ),
    ] = 60.0,
    wait: Annotated[
        float,
        typer.Option(min=0.0, help="Seconds a job whose run is still being acquired waits before it is tried again."),
    ] = 10.0,
    worker_id: Annotated[
        str | None, typer.Option("--id", help="This worker's name in the catalog (default HOST-PID).")
    ] = None,
) -> None:
    """Take queued processing jobs from the catalog and process their runs (results beside each run).

    Positions are processed on Dask: a local cluster sized to the machine, or the cluster
    of --scheduler tcp://HOST:8786. A job whose run is still being acquired waits (or, when
    it asked for partial, gets the positions complete so far); a failed job records its
    reason and the worker goes on; a job whose worker died is requeued by the next worker
    that looks at the queue. Stops on Ctrl-C or SIGTERM, after the job at hand.
    """
    import logging
    import signal
    import threading

    from acquisition.settings import SettingsError, load_settings
    from acquisition.worker import serve_jobs
    from processing.parallel import ComputeError, open_compute

    try:
        settings = load_settings(config, data_dir=data_dir) if data_dir is not None else load_settings(config)
    except (SettingsError, OSError) as exc:
        raise _fail(str(exc)) from None
    if not Path(settings.data_dir).is_dir():
        raise _fail(f"--data-dir: {settings.data_dir} is not a folder (the daemon's data folder, with catalog.sqlite)")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    from processing.pipeline import warm_up_worker

    try:
        compute = open_compute(scheduler, workers=workers, warm_up=warm_up_worker)
    except ComputeError as exc:
        raise _fail(str(exc)) from None
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())

    def report(job) -> None:
        if job.state == "complete":
            typer.echo(f"{job.id} complete ({job.run_id}): {job.message}")
            for kind, path in job.artifacts.items():
                typer.echo(f"  {kind}: {path}")
        elif job.state == "failed":
            typer.echo(f"{job.id} failed ({job.run_id}): {job.error}")
        else:
            typer.echo(f"{job.id} {job.state} ({job.run_id}): {job.message}")

    typer.echo(f"worker: jobs from {settings.catalog_path}, positions on {compute.description}")
    from acquisition.catalog import CatalogError

    try:
        with compute:
            serve_jobs(
                settings.catalog_path,
                compute,
                stop=stop,
                once=once,
                poll_s=poll,
                on_job=report,
                worker_id=worker_id,
                heartbeat_s=heartbeat,
                stale_after_s=stale_after,
                wait_s=wait,
            )
    except CatalogError as exc:
        raise _fail(str(exc)) from None


# --- import -------------------------------------------------------------------------------
@app.command("import")
def import_command(
    folder: Annotated[Path, typer.Argument(help="Folder of raw files (DNG, NEF, CR2, ARW, ...).")],
    csv_file: Annotated[
        Path, typer.Option("--csv", help="CSV giving each file's position: file, position[, exposure_s][, pose].")
    ],
    rig: Annotated[Path, typer.Option("--rig", help="Rig description (TOML) the frames were taken with.")],
    out: Annotated[Path, typer.Option("--out", help="Run file (HDF5) to create; it must not exist.")],
    run_id: Annotated[
        str | None, typer.Option("--run-id", help="The run's identifier (default: the output file's name).")
    ] = None,
    operator: Annotated[str, typer.Option(help="Who took the frames (stored in the run).")] = "",
    light_source: Annotated[str, typer.Option("--light-source", help="The light measured (stored in the run).")] = "",
    notes: Annotated[str, typer.Option(help="Free notes (stored in the run).")] = "",
) -> None:
    """Build a run file from raw files captured elsewhere (docs/import.md).

    Everything is checked before anything is written; on bad input nothing is left behind.
    Positions the CSV gives no frame for are left incomplete in the run file."""
    from rich.progress import Progress

    from acquisition.importer import RunImportError, format_ranges, import_run

    with Progress(transient=True) as bar:
        tasks: dict[str, int] = {}

        def progress(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = bar.add_task(
                    "checking raw files" if stage == "checking" else "writing the run", total=total
                )
            bar.update(tasks[stage], completed=done, total=total)

        try:
            report = import_run(
                folder,
                csv_file,
                rig,
                out,
                run_id=run_id,
                progress=progress,
                metadata={"operator": operator, "light_source": light_source, "notes": notes},
            )
        except (RunImportError, OSError) as exc:
            raise _fail(" ".join(str(exc).split())) from None
    height, width = report.frame_shape
    exposures = ", ".join(f"{t:g}" for t in report.exposures_s)
    typer.echo(
        f"imported {report.frames} frames into {report.run_file} (run {report.run_id}): "
        f"{len(report.positions_with_frames)} of {report.n_positions} positions, {width}x{height} "
        f"{report.cfa_pattern}, "
        f"exposures {exposures} s"
    )
    typer.echo(f"  camera: {'; '.join(report.cameras)}")
    if report.exposure_overrides:
        typer.echo(
            f"  exposure times from the CSV for {report.exposure_overrides} frames, from the files for the others"
        )
    if report.empty_positions:
        typer.echo(f"  positions without frames (left incomplete): {format_ranges(report.empty_positions)}")
    if report.ignored_files:
        shown = ", ".join(report.ignored_files[:5]) + (", ..." if len(report.ignored_files) > 5 else "")
        typer.echo(f"  not in the CSV, not imported: {len(report.ignored_files)} raw files in {folder} ({shown})")


# --- calibrate ----------------------------------------------------------------------------
@app.command("calibrate")
def calibrate(
    image: Annotated[Path, typer.Argument(help="A raw file of the ball lit by its surroundings (DNG, NEF, CR2, ...).")],
    rig: RigOption = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON only.")] = False,
) -> None:
    """Measure the ball's centre from its silhouette and compare it with the rig description.

    Feed the measured centre to ``process --ball-centre X,Y,Z`` to use it.
    """
    from drivers.contracts.rig import load_rig
    from drivers.raw_decode import decode_raw
    from processing.calibration import (
        CalibrationError,
        angle_sensitivity,
        calibrate_ball,
        compare_with_rig,
        mosaic_luminance,
    )

    try:
        rig_model = load_rig(rig or _default_rig())
        frame = decode_raw(image)
        fit = calibrate_ball(mosaic_luminance(frame.mosaic, frame.black_level.mean()), rig_model)
        comparison = compare_with_rig(fit, rig_model)
        poses = rig_model.light_poses()
        sensitivity = angle_sensitivity(rig_model, poses[len(poses) // 2])
    except (*_domain_errors(), CalibrationError) as exc:
        raise _fail(str(exc)) from None
    result = {
        "image": str(image),
        **{k: v for k, v in comparison.items() if not callable(v)},
        "angle_change_deg_per_mm": sensitivity,
    }
    text = json.dumps(result, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))
    if as_json:
        typer.echo(text)
        return
    measured = ",".join(f"{v / 1000:.6f}" for v in comparison["measured_mm"])
    typer.echo(
        f"ball centre measured {comparison['measured_mm']} mm, described {comparison['described_mm']} mm: "
        f"off by {comparison['distance_mm']:.3f} mm ({comparison['significance']:.1f} sigma)"
    )
    typer.echo(f"use it with: mirrorgonio process RUN.h5 --ball-centre {measured}")


# --- simulate -----------------------------------------------------------------------------
@simulate_app.command("arm")
def simulate_arm(
    port: Annotated[int, typer.Option(help="TCP port of the Modbus server.")] = 5020,
    host: Annotated[str, typer.Option(help="Address to listen on (loopback by default).")] = "127.0.0.1",
    speed: Annotated[
        float | None, typer.Option(help="Linear speed in m/s (inf: instantaneous moves); default 0.05.")
    ] = None,
    accel: Annotated[float | None, typer.Option(help="Linear acceleration in m/s^2; default 0.5.")] = None,
    angular_speed: Annotated[
        float | None, typer.Option("--angular-speed", help="Angular speed in rad/s; default 1.")
    ] = None,
) -> None:
    """Serve the simulated stage as a Modbus TCP server until interrupted (Ctrl-C or SIGTERM)."""
    import signal

    from sim_devices.modbus_server import serve
    from sim_devices.stage import StageConfig

    mechanics: dict = {}
    for name, value in (("speed", speed), ("accel", accel), ("angular-speed", angular_speed)):
        if value is not None and not value > 0:
            raise _fail(f"--{name}: must be positive, got {value}")
    if speed is not None:
        mechanics.update(speed_m_s=speed, accel_m_s2=math.inf if math.isinf(speed) else (accel or 10 * speed))
    elif accel is not None:
        mechanics.update(accel_m_s2=accel)
    if angular_speed is not None:
        mechanics.update(angular_speed_rad_s=angular_speed, angular_accel_rad_s2=10 * angular_speed)

    def _terminated(signum, frame):  # a container's stop: leave as on Ctrl-C, closing the server
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _terminated)
    typer.echo(f"simulated arm: Modbus TCP on {host}:{port} (Ctrl-C to stop)")
    try:
        serve(port=port, host=host, stage_config=StageConfig(**mechanics))
    except KeyboardInterrupt:
        pass
    except OSError as exc:
        raise _fail(f"simulated arm: cannot listen on {host}:{port}: {exc.strerror or exc}") from None


def _capture_one(
    rig_path: Path,
    position: int,
    exposure: float,
    output: Path,
    truth: str | None,
    noise: bool,
    diffraction: bool,
    seed: int | None,
):
    from drivers.contracts.rig import load_rig
    from drivers.pose import Pose
    from sim_devices.camera import SimulatedCamera
    from sim_devices.lights import load_truth
    from sim_devices.world import SimWorld

    rig = load_rig(rig_path)
    tool_poses = rig.tool_poses()
    if not 0 <= position < len(tool_poses):
        raise _fail(f"--position: {position} is outside the schedule (0..{len(tool_poses) - 1})")
    if not exposure > 0 or not math.isfinite(exposure):
        raise _fail(f"--exposure: must be a positive number of seconds, got {exposure}")
    tool: Pose = tool_poses[position]
    world = SimWorld(lambda: tool, rig.light.light_to_tool.to_pose())
    camera = SimulatedCamera(
        rig,
        world,
        output.parent,
        truth=load_truth(truth) if truth else None,
        noise=noise,
        diffraction=diffraction,
        seed=seed,
    )
    return camera.capture_to(output, exposure)


@simulate_app.command("capture")
def simulate_capture(
    output: Annotated[Path, typer.Option("-o", "--output", help="DNG file to write.")],
    rig: RigOption = None,
    position: Annotated[int, typer.Option(help="Schedule position index.")] = 0,
    exposure: Annotated[float, typer.Option(help="Exposure time in seconds.")] = 0.01,
    truth: Annotated[
        str | None, typer.Option(help="Truth light (shipped name or TOML path); default from the rig.")
    ] = None,
    noise: Annotated[bool, typer.Option(help="Photon and read noise.")] = True,
    diffraction: Annotated[bool, typer.Option(help="Airy diffraction of the aperture.")] = True,
    seed: Annotated[int | None, typer.Option(help="Random seed; default from the rig.")] = None,
) -> None:
    """Render one frame of the mirrored ball and write it as a DNG file."""
    try:
        frame = _capture_one(rig or _default_rig(), position, exposure, output, truth, noise, diffraction, seed)
    except _domain_errors() as exc:
        raise _fail(str(exc)) from None
    typer.echo(
        f"wrote {output} ({frame.mosaic.shape[1]}x{frame.mosaic.shape[0]}, {frame.cfa_pattern}, "
        f"exposure {frame.exposure_s:g} s, max {int(frame.mosaic.max())} DN)"
    )


# --- bench ----------------------------------------------------------------------------------
@bench_app.command("render")
def bench_render(
    rig: RigOption = None,
    repeat: Annotated[int, typer.Option(min=1, help="Timed repetitions (the median is reported).")] = 3,
    position: Annotated[int, typer.Option(help="Schedule position to render.")] = 33,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON only.")] = False,
) -> None:
    """Time the rendering of one full frame, next to a one-ray-per-pixel trace of it."""
    import numpy as np

    from drivers.contracts.rig import load_rig
    from sim_devices.lights import load_truth
    from sim_devices.optics import LightPlane, MirrorBallRenderer, trace

    try:
        rig_model = load_rig(rig or _default_rig())
        truth = load_truth(rig_model.simulation.truth)
    except _domain_errors() as exc:
        raise _fail(str(exc)) from None
    poses = rig_model.light_poses()
    pose = poses[min(max(position, 0), len(poses) - 1)]
    renderer = MirrorBallRenderer(rig_model, truth, diffraction=rig_model.simulation.diffraction)
    cam = renderer.camera
    rows, cols = np.mgrid[0 : cam.height, 0 : cam.width]
    cols, rows = cols.ravel().astype(float), rows.ravel().astype(float)
    zero = np.zeros_like(cols)
    plane = LightPlane.at(rig_model, pose)

    render_times, chief_times, stats = [], [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        trace(cam, renderer.mirror, plane, cols, rows, zero, zero)
        chief_times.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        stats = renderer.render(pose).stats
        render_times.append(time.perf_counter() - t0)
    render_s, chief_s = statistics.median(render_times), statistics.median(chief_times)
    result = {
        "benchmark": "render",
        "width": cam.width,
        "height": cam.height,
        "truth": truth.name,
        "diffraction": rig_model.simulation.diffraction,
        "repeat": repeat,
        "render_s_median": round(render_s, 4),
        "render_s_all": [round(t, 4) for t in render_times],
        "chief_ray_trace_s_median": round(chief_s, 4),
        "render_over_chief_trace": round(render_s / chief_s, 2),
        "rays_traced_per_frame": stats.rays_traced,
        "rays_per_s": round(stats.rays_traced / render_s),
        "target_s": 10.0,
        "meets_target": render_s <= 10.0,
    }
    _print_result(result, as_json)


@bench_app.command("acquire")
def bench_acquire_command(
    rig: RigOption = None,
    positions: Annotated[int, typer.Option(min=1, help="Schedule positions per run.")] = 20,
    exposures: Annotated[int, typer.Option(min=1, max=16, help="Frames per position.")] = 3,
    repeat: Annotated[int, typer.Option(min=1, help="Timed repetitions (medians reported).")] = 3,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON only.")] = False,
) -> None:
    """The daemon's overhead with zero-latency devices, next to a plain h5py write of the same frames."""
    from acquisition.benchmarks.acquire import bench_acquire

    try:
        result = bench_acquire(rig, positions=positions, exposures=exposures, repeat=repeat)
    except _domain_errors() as exc:
        raise _fail(str(exc)) from None
    _print_result(result, as_json)


@bench_app.command("hdr")
def bench_hdr_command(
    rig: RigOption = None,
    positions: Annotated[
        int, typer.Option(min=1, help="Brackets merged (a few rendered scenes cycled, fresh noise each).")
    ] = 66,
    exposures: Annotated[int, typer.Option(min=2, max=16, help="Frames per bracket.")] = 5,
    width: Annotated[int, typer.Option(min=4, help="Frame width in pixels (even).")] = 2000,
    height: Annotated[int, typer.Option(min=4, help="Frame height in pixels (even).")] = 1312,
    repeat: Annotated[int, typer.Option(min=1, help="Timed repetitions (medians reported).")] = 1,
    seed: Annotated[int, typer.Option(help="Seed of the sensor noise.")] = 0,
    peers: Annotated[bool, typer.Option(help="Also run HDRutils, colour-hdri and OpenCV (the bench extra).")] = True,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON only.")] = False,
) -> None:
    """This project's raw HDR merge next to HDRutils, colour-hdri and OpenCV on the same brackets: time and error."""
    from acquisition.benchmarks.hdr import BenchmarkError, bench_hdr
    from processing.hdr import HDRError

    try:
        result = bench_hdr(positions, exposures, width, height, repeat, seed, rig_path=rig, peers=peers)
    except (BenchmarkError, HDRError, *_domain_errors()) as exc:
        raise _fail(str(exc)) from None
    _print_result(result, as_json)


@bench_app.command("accuracy")
def bench_accuracy_command(
    noise: Annotated[bool, typer.Option(help="Photon, read and quantisation noise.")] = True,
    truth: Annotated[str, typer.Option(help="Shipped truth light.")] = "five-gaussians",
    positions: Annotated[int, typer.Option(min=3, help="Schedule positions (the first N of the sweep).")] = 66,
    fit: Annotated[str, typer.Option(help="Fit method: gaussian, polynomial, cos-power.")] = "gaussian",
    rig: RigOption = None,
    layout_from_data: Annotated[
        bool,
        typer.Option(
            "--layout-from-data",
            help="Find the sources in the data instead of "
            "giving the truth's layout; score each emitter against the nearest found.",
        ),
    ] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON only.")] = False,
) -> None:
    """The reference simulation through the whole chain, scored against the truth."""
    from acquisition.benchmarks.accuracy import bench_accuracy
    from processing.pipeline import ProcessingError

    try:
        result = bench_accuracy(
            noise=noise,
            truth=truth,
            positions=positions,
            rig_path=rig,
            fit_method=fit,
            layout_from_data=layout_from_data,
        )
    except (*_domain_errors(), ProcessingError) as exc:
        raise _fail(str(exc)) from None
    _print_result(result, as_json)


@bench_app.command("reflectance")
def bench_reflectance_command(
    object_rig: Annotated[
        str, typer.Option("--object", help="Object rig: object-vase, object-relief or a TOML path.")
    ] = "object-vase",
    truth: Annotated[str, typer.Option(help="Shipped truth light (the same lights both runs).")] = "five-gaussians",
    noise: Annotated[bool, typer.Option(help="Photon, read and quantisation noise.")] = True,
    light_positions: Annotated[int, typer.Option(min=3, help="Positions of the light sweep (the first N).")] = 66,
    workdir: Annotated[
        Path | None, typer.Option(help="Keep the runs and outputs here (default: a temporary folder).")
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON only.")] = False,
) -> None:
    """Measure the light, photograph an object, score ρ under three light models."""
    from acquisition.benchmarks.reflectance import bench_reflectance
    from processing.pipeline import ProcessingError
    from processing.reflectance import ReflectanceError

    try:
        result = bench_reflectance(
            object_rig=object_rig, truth=truth, noise=noise, light_positions=light_positions, workdir=workdir
        )
    except (*_domain_errors(), ProcessingError, ReflectanceError) as exc:
        raise _fail(str(exc)) from None
    _print_result(result, as_json)


def _rig_errors_help() -> str:
    from acquisition.benchmarks.tolerance import DEFAULT_ERRORS, ERROR_PARTS

    return (
        "Comma-separated errors of the rig description to try, each PART±SIZE: PART one of "
        f"{', '.join(ERROR_PARTS)}; SIZE in mm or um, or in % of the pinhole, the sensor distance or the "
        f"ball's radius (e.g. pinhole+1%, ball-x-20um). Default: {', '.join(DEFAULT_ERRORS)}."
    )


@bench_app.command("tolerance")
def bench_tolerance_command(
    rig: RigOption = None,
    truth: Annotated[str, typer.Option(help="Shipped truth light.")] = "five-gaussians",
    positions: Annotated[int, typer.Option(min=3, help="Schedule positions (the first N of the sweep).")] = 66,
    errors: Annotated[str | None, typer.Option(help=_rig_errors_help())] = None,
    layout_from_data: Annotated[
        bool, typer.Option("--layout-from-data", help="Also find the sources in the data with each description.")
    ] = False,
    fit_aperture: Annotated[
        bool,
        typer.Option(
            "--fit-aperture",
            help="Also process each way with the aperture fitted to the data (process --fit-aperture).",
        ),
    ] = False,
    fit_sensor_distance: Annotated[
        bool,
        typer.Option(
            "--fit-sensor-distance",
            help="Also process each way with the sensor distance fitted (process --fit-sensor-distance).",
        ),
    ] = False,
    noise: Annotated[bool, typer.Option(help="Photon, read and quantisation noise.")] = True,
    scheduler: SchedulerOption = "local",
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON only.")] = False,
) -> None:
    """How exact the rig description must be: one simulated run (the demo rig by default)
    processed with one number of its description wrong at a time, scored against the truth.
    Progress goes to standard error; the JSON, then (without --json) the markdown table, to
    standard output."""
    from acquisition.benchmarks.tolerance import bench_tolerance
    from processing.parallel import ComputeError
    from processing.pipeline import ProcessingError

    chosen = None if errors is None else [e.strip() for e in errors.split(",") if e.strip()]
    try:
        result = bench_tolerance(
            rig_path=rig,
            truth=truth,
            positions=positions,
            errors=chosen,
            layout_from_data=layout_from_data,
            fit_aperture=fit_aperture,
            fit_sensor_distance=fit_sensor_distance,
            noise=noise,
            scheduler=scheduler,
            log=lambda message: typer.echo(message, err=True),
        )
    except (ValueError, ComputeError, ProcessingError, *_domain_errors()) as exc:
        raise _fail(str(exc)) from None
    _print_result(result, as_json)
    if not as_json:
        typer.echo("")
        typer.echo(result["markdown"])


@bench_app.command("speed")
def bench_speed_command(
    rig: RigOption = None,
    sizes: Annotated[
        str, typer.Option(help="Sensor sizes, WIDTHxHEIGHT,... (the same field of view).")
    ] = "2000x1312,4000x2624",
    positions: Annotated[int, typer.Option(min=3, help="Positions of the sweep (the first N).")] = 66,
    exposures: Annotated[
        int, typer.Option(min=1, max=5, help="Frames per position (the first N of the reference bracket).")
    ] = 5,
    repeat: Annotated[int, typer.Option(min=1, help="Repetitions of the cheap measurements (medians reported).")] = 3,
    process_repeat: Annotated[
        int,
        typer.Option(
            "--process-repeat",
            min=1,
            help=(
                "Timed whole-run processings per size, after an untimed first one on the same cluster (median "
                "reported)."
            ),
        ),
    ] = 3,
    hdr_positions: Annotated[
        int, typer.Option("--hdr-positions", min=1, help="Brackets merged by every HDR method (spread over the sweep).")
    ] = 8,
    peers: Annotated[bool, typer.Option(help="Also time HDRutils and colour-hdri (the bench extra).")] = True,
    scheduler: SchedulerOption = "local",
    workers: WorkersOption = None,
    cache: Annotated[
        Path | None,
        typer.Option("--cache", help="Folder of the cached simulated runs (default ~/.cache/mirrorgonio/bench)."),
    ] = None,
    no_cache: Annotated[
        bool, typer.Option("--no-cache", help="Make the runs afresh in a temporary folder, keep nothing.")
    ] = False,
    as_json: Annotated[
        bool, typer.Option("--json", help="Print JSON only (one line; the table is its 'markdown' field).")
    ] = False,
) -> None:
    """Speed of the chain at two sensor sizes: acquisition overhead, HDR merge next to its peers,
    chief rays per second, whole-run processing time and peak memory, and the read floor.
    Progress goes to standard error; the JSON, then (without --json) the markdown table, to standard output."""
    from acquisition.benchmarks.speed import DEFAULT_CACHE, SpeedBenchError, bench_speed, parse_size
    from processing.hdr import HDRError
    from processing.parallel import ComputeError
    from processing.pipeline import ProcessingError

    try:
        size_list = [parse_size(s) for s in sizes.split(",") if s.strip()]
        if not size_list:
            raise SpeedBenchError("--sizes: give at least one WIDTHxHEIGHT")
        result = bench_speed(
            rig_path=rig,
            sizes=size_list,
            positions=positions,
            exposures=exposures,
            repeat=repeat,
            process_repeat=process_repeat,
            hdr_positions=hdr_positions,
            peers=peers,
            scheduler=scheduler,
            workers=workers,
            cache=None if no_cache else (cache or DEFAULT_CACHE),
            log=lambda message: typer.echo(message, err=True),
        )
    except (SpeedBenchError, ComputeError, ProcessingError, HDRError, *_domain_errors()) as exc:
        raise _fail(str(exc)) from None
    _print_result(result, as_json)
    if not as_json:
        typer.echo("")
        typer.echo(result["markdown"])


# --- demo -------------------------------------------------------------------------------------
@app.command("demo")
def demo(
    root: Annotated[
        Path, typer.Option("--data-root", help="Where the demo's folders go: one per demo, timestamped.")
    ] = Path("demo-data"),
    rig: Annotated[Path | None, typer.Option("--rig", help="Rig description (TOML); default rigs/demo.toml.")] = None,
    positions: Annotated[
        int | None, typer.Option(min=3, help="Take only the first positions of the sweep (default: all).")
    ] = None,
    workers: WorkersOption = None,
    keep: Annotated[
        int, typer.Option(min=0, help="Older demo folders kept under --data-root (the others are removed).")
    ] = 1,
    truth_layout: Annotated[
        bool,
        typer.Option(
            "--truth-layout",
            help=(
                "Give the worker the simulated truth's source layout instead of letting it find the sources "
                "in the data."
            ),
        ),
    ] = False,
) -> None:
    """The whole chain on simulated devices: the daemon and the worker as processes, the
    default light sweep through the REST API, the worker's processing (the sources found in
    the data, as for an unknown lamp), the result files and the accuracy against the
    simulated truth."""
    from rich.console import Console

    from acquisition.demo import DemoError, print_summary, run_demo

    console = Console()
    try:
        result = run_demo(
            root=root,
            rig=rig,
            positions=positions,
            workers=workers,
            keep=keep,
            truth_layout=truth_layout,
            console=console,
        )
    except KeyboardInterrupt:
        typer.echo("interrupted: the worker and the daemon are stopped", err=True)
        raise typer.Exit(code=130) from None
    except DemoError as exc:
        if exc.details:
            typer.echo("\n".join("  | " + line for line in exc.details.splitlines()), err=True)
        raise _fail(str(exc)) from None
    except _domain_errors() as exc:
        raise _fail(str(exc)) from None
    print_summary(result, console)


# --- reflectance ----------------------------------------------------------------------------
@app.command("reflectance")
def reflectance(
    object_run: Annotated[Path, typer.Argument(help="The object run (HDF5), object-arc on a rig with \\[object].")],
    light: Annotated[
        Path | None,
        typer.Option(
            "--light",
            help=(
                "Light model: RUN.light.json, or the light run's results folder or file (default: the one the "
                "run recorded)."
            ),
        ),
    ] = None,
    mesh: Annotated[
        Path | None, typer.Option("--mesh", help="The object's mesh, PLY/OBJ/STL (default: the rig's \\[object].mesh).")
    ] = None,
    out: Annotated[
        Path | None, typer.Option("--out", help="Folder for the outputs (default: RUN.reflectance beside the run).")
    ] = None,
    grazing_deg: Annotated[
        float, typer.Option(help="Exclude lights less than this elevation above the surface.")
    ] = 15.0,
    view_grazing_deg: Annotated[float, typer.Option(help="Exclude pixels seen at less than this elevation.")] = 15.0,
    specular_deg: Annotated[
        float, typer.Option(help="Exclude samples whose half vector is within this angle of the normal (0: off).")
    ] = 15.0,
    outlier: Annotated[
        float, typer.Option(help="Drop a light whose radiance exceeds the others' fit by this fraction (3+ lights).")
    ] = 0.05,
    edge_margin: Annotated[int, typer.Option(help="Superpixels excluded around silhouettes and depth steps.")] = 2,
    texture_size: Annotated[int, typer.Option(min=16, help="UV texture size in texels (meshes with UVs).")] = 1024,
) -> None:
    """The object's diffuse albedo under three light models (collimated, isotropic point, measured),
    with maps, a UV texture, profiles along its vertical axis and an HTML report (docs/reflectance.md)."""
    from rich.console import Console
    from rich.progress import Progress
    from rich.table import Table

    from processing.reflectance import ReflectanceError, ReflectanceSettings, reflectance_from_run

    try:
        settings = ReflectanceSettings(
            grazing_light_deg=grazing_deg,
            grazing_view_deg=view_grazing_deg,
            specular_deg=specular_deg,
            outlier=outlier,
            edge_margin=edge_margin,
        )
        with Progress(transient=True) as bar:
            tasks: dict[str, object] = {}

            def progress(stage: str, done: int, total: int) -> None:
                if stage not in tasks:
                    tasks[stage] = bar.add_task(stage, total=total)
                bar.update(tasks[stage], completed=done, total=total)

            result = reflectance_from_run(
                object_run, light, mesh, out, progress=progress, settings=settings, texture_size=texture_size
            )
    except (ReflectanceError, ValueError, OSError) as exc:  # every input error is a one-line ValueError
        raise _fail(" ".join(str(exc).split())) from None
    summary = result.summary()
    table = Table(
        title=f"albedo of {summary['valid']} of {summary['on_object']} superpixels on the object", title_justify="left"
    )
    for column in ("light model", "median ρ (R, G, B)", "CV", "robust CV"):
        table.add_column(column)
    for method, stats in summary["methods"].items():
        table.add_row(
            method,
            ", ".join(f"{v:.4f}" for v in stats.get("median", [])),
            f"{100 * stats.get('cv', float('nan')):.2f} %",
            f"{100 * stats.get('robust_cv', float('nan')):.2f} %",
        )
    console = Console()
    console.print(table)
    left_out = {k: v for k, v in summary["pixel_reasons"].items() if v and k not in ("valid", "background")}
    console.print("left out: " + (", ".join(f"{k} {v}" for k, v in left_out.items()) or "none"), highlight=False)
    for warning in result.warnings:
        typer.echo(f"warning: {warning}", err=True)
    folder = result.outputs["report.html"].parent
    typer.echo(f"outputs in {folder}: report.html, reflectance.json, reflectance.h5, albedo-*.exr/png, profiles.png")


def main() -> None:  # pragma: no cover - console entry
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(app())
