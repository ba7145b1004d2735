"""``mirrorgonio bench``: benchmarks that print what they measured."""

from __future__ import annotations

import shlex
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from acquisition.cli.app import (
    RigOption,
    SchedulerOption,
    WorkersOption,
    bench_app,
    default_rig,
    domain_errors,
    fail,
    print_result,
)
from processing import FitMethod

if TYPE_CHECKING:
    from acquisition.benchmarks.record import Recording

RecordOption = Annotated[
    Path | None,
    typer.Option(
        "--record",
        metavar="PATH",
        help="Also write the result as this benchmark's section of a markdown file (e.g. docs/benchmarks.md); "
        "the other benchmarks' sections stay as they are.",
    ),
]


def _command_line(ctx: typer.Context) -> str:
    """The running command as a shell line: its path and the options given (on the command
    line or in the environment), in the order the command declares them."""
    words = ctx.command_path.split()
    for param in ctx.command.params:
        source = ctx.get_parameter_source(param.name)
        if source is None or source.name == "DEFAULT":
            continue
        value = ctx.params[param.name]
        is_flag = getattr(param, "is_flag", False)  # an option's (click.Option)
        if param.param_type_name != "option":
            words.append(str(value))
        elif is_flag and param.secondary_opts:
            words.append(param.opts[0] if value else param.secondary_opts[0])
        elif is_flag:
            words += [param.opts[0]] if value else []
        else:
            words += [param.opts[0], str(value)]
    return shlex.join(words)


def _start_recording(ctx: typer.Context, path: Path | None) -> Recording | None:
    """With ``--record``: the file checked and the start noted (a one-line error before the
    benchmark runs if the file cannot take the section); else None."""
    if path is None:
        return None
    from acquisition.benchmarks.record import RecordError, start_recording

    try:
        return start_recording(path, _command_line(ctx))
    except RecordError as exc:
        raise fail(f"--record: {exc}") from None


def _record(recording: Recording | None, name: str, result: dict) -> None:
    """With ``--record``: the result written as the benchmark's section (said on standard error)."""
    if recording is None:
        return
    from acquisition.benchmarks.record import RecordError, record_result

    try:
        record_result(recording, name, result)
    except (RecordError, OSError) as exc:
        raise fail(f"--record: {exc}") from None
    typer.echo(f"recorded in {recording.path} (section bench:{name})", err=True)


# --- bench ----------------------------------------------------------------------------------
@bench_app.command("render")
def bench_render(
    ctx: typer.Context,
    rig: RigOption = None,
    repeat: Annotated[int, typer.Option(min=1, help="Timed repetitions (the median is reported).")] = 3,
    position: Annotated[int, typer.Option(help="Schedule position to render.")] = 33,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON only.")] = False,
    record: RecordOption = None,
) -> None:
    """Time the rendering of one full frame, next to a one-ray-per-pixel trace of it."""
    from acquisition.benchmarks.render import bench_render as run_bench_render

    recording = _start_recording(ctx, record)
    try:
        result = run_bench_render(rig or default_rig(), repeat=repeat, position=position)
    except domain_errors() as exc:
        raise fail(str(exc)) from None
    print_result(result, as_json)
    _record(recording, "render", result)


@bench_app.command("acquire")
def bench_acquire_command(
    ctx: typer.Context,
    rig: RigOption = None,
    positions: Annotated[int, typer.Option(min=1, help="Schedule positions per run.")] = 20,
    exposures: Annotated[int, typer.Option(min=1, max=16, help="Frames per position.")] = 3,
    repeat: Annotated[int, typer.Option(min=1, help="Timed repetitions (medians reported).")] = 3,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON only.")] = False,
    record: RecordOption = None,
) -> None:
    """The daemon's overhead with zero-latency devices, next to a plain h5py write of the same frames."""
    from acquisition.benchmarks.acquire import bench_acquire

    recording = _start_recording(ctx, record)
    try:
        result = bench_acquire(rig, positions=positions, exposures=exposures, repeat=repeat)
    except domain_errors() as exc:
        raise fail(str(exc)) from None
    print_result(result, as_json)
    _record(recording, "acquire", result)


@bench_app.command("hdr")
def bench_hdr_command(
    ctx: typer.Context,
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
    record: RecordOption = None,
) -> None:
    """This project's raw HDR merge next to HDRutils, colour-hdri and OpenCV on the same brackets: time and error."""
    from acquisition.benchmarks.hdr import BenchmarkError, bench_hdr
    from processing import HDRError

    recording = _start_recording(ctx, record)
    try:
        result = bench_hdr(positions, exposures, width, height, repeat, seed, rig_path=rig, peers=peers)
    except domain_errors(BenchmarkError, HDRError) as exc:
        raise fail(str(exc)) from None
    print_result(result, as_json)
    _record(recording, "hdr", result)


@bench_app.command("accuracy")
def bench_accuracy_command(
    ctx: typer.Context,
    noise: Annotated[bool, typer.Option(help="Photon, read and quantisation noise.")] = True,
    truth: Annotated[str, typer.Option(help="Shipped truth light.")] = "five-gaussians",
    positions: Annotated[int, typer.Option(min=3, help="Schedule positions (the first N of the sweep).")] = 66,
    fit: Annotated[FitMethod, typer.Option(help="The model every source's I(θ) is fitted to.")] = FitMethod.GAUSSIAN,
    rig: RigOption = None,
    layout_from_data: Annotated[
        bool,
        typer.Option(
            "--layout-from-data",
            help="Find the sources in the data instead of "
            "giving the truth's layout; score each emitter against the nearest found.",
        ),
    ] = False,
    templates: Annotated[
        str | None,
        typer.Option(
            help="The point spread the templates model, geometric-airy or fresnel, where not the camera's "
            "(the rig's camera.point_spread): what the other model costs.",
        ),
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON only.")] = False,
    record: RecordOption = None,
) -> None:
    """The reference simulation through the whole chain, scored against the truth."""
    from acquisition.benchmarks.accuracy import bench_accuracy
    from processing import ProcessingError

    if templates not in (None, "geometric-airy", "fresnel"):
        raise fail(f"--templates: {templates!r} is not geometric-airy or fresnel")
    recording = _start_recording(ctx, record)
    try:
        result = bench_accuracy(
            noise=noise,
            truth=truth,
            positions=positions,
            rig_path=rig,
            fit_method=fit,
            layout_from_data=layout_from_data,
            templates=templates,
        )
    except domain_errors(ProcessingError) as exc:
        raise fail(str(exc)) from None
    print_result(result, as_json)
    _record(recording, "accuracy", result)


# The options the two object benchmarks share: the light measured first, then the object.
ObjectTruthOption = Annotated[str, typer.Option("--truth", help="Shipped truth light (the same lights both runs).")]
NoiseOption = Annotated[bool, typer.Option("--noise/--no-noise", help="Photon, read and quantisation noise.")]
LightPositionsOption = Annotated[
    int, typer.Option("--light-positions", min=3, help="Positions of the light sweep (the first N).")
]
WorkdirOption = Annotated[
    Path | None, typer.Option("--workdir", help="Keep the runs and outputs here (default: a temporary folder).")
]


@bench_app.command("reflectance")
def bench_reflectance_command(
    ctx: typer.Context,
    object_rig: Annotated[
        str, typer.Option("--object", help="Object rig: object-vase, object-relief or a TOML path.")
    ] = "object-vase",
    truth: ObjectTruthOption = "five-gaussians",
    noise: NoiseOption = True,
    light_positions: LightPositionsOption = 66,
    workdir: WorkdirOption = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON only.")] = False,
    record: RecordOption = None,
) -> None:
    """Measure the light, photograph an object, score ρ under three light models."""
    from acquisition.benchmarks.reflectance import bench_reflectance
    from processing import ProcessingError, ReflectanceError

    recording = _start_recording(ctx, record)
    try:
        result = bench_reflectance(
            object_rig=object_rig, truth=truth, noise=noise, light_positions=light_positions, workdir=workdir
        )
    except domain_errors(ProcessingError, ReflectanceError) as exc:
        raise fail(str(exc)) from None
    print_result(result, as_json)
    _record(recording, "reflectance", result)


@bench_app.command("brdf")
def bench_brdf_command(
    ctx: typer.Context,
    object_rig: Annotated[
        str, typer.Option("--object", help="Object rig with a glossy surface and a dome schedule, or a TOML path.")
    ] = "object-vase-glazed",
    truth: ObjectTruthOption = "five-gaussians",
    noise: NoiseOption = True,
    light_positions: LightPositionsOption = 66,
    workdir: WorkdirOption = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON only.")] = False,
    record: RecordOption = None,
) -> None:
    """Measure the light, photograph a glossy object on a dome of lights, score its BRDF (diffuse,
    specular, roughness, error bars, relighting) under three light models."""
    from acquisition.benchmarks.brdf import bench_brdf
    from processing import ProcessingError, ReflectanceError

    recording = _start_recording(ctx, record)
    try:
        result = bench_brdf(
            object_rig=object_rig, truth=truth, noise=noise, light_positions=light_positions, workdir=workdir
        )
    except domain_errors(ProcessingError, ReflectanceError) as exc:
        raise fail(str(exc)) from None
    print_result(result, as_json)
    _record(recording, "brdf", result)


@bench_app.command("repeatability")
def bench_repeatability_command(
    ctx: typer.Context,
    seeds: Annotated[int, typer.Option(min=1, max=100, help="Seeds (noise realisations) to take and process.")] = 10,
    truth: Annotated[str, typer.Option(help="Shipped truth light.")] = "five-gaussians",
    rig: RigOption = None,
    workdir: WorkdirOption = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON only.")] = False,
    record: RecordOption = None,
) -> None:
    """The reference simulation once per seed, the sources found in the data: each source's
    place and intensity over the seeds (spread, worst), and the first seed taken twice (the same?)."""
    from acquisition.benchmarks.repeatability import bench_repeatability
    from processing import ProcessingError

    recording = _start_recording(ctx, record)
    try:
        result = bench_repeatability(seeds=seeds, truth=truth, rig_path=rig, workdir=workdir)
    except domain_errors(ProcessingError) as exc:
        raise fail(str(exc)) from None
    print_result(result, as_json)
    _record(recording, "repeatability", result)


def _rig_errors_help() -> str:
    from acquisition.benchmarks.description_errors import DEFAULT_ERRORS, ERROR_PARTS

    return (
        "Comma-separated errors of the rig description to try, each PART±SIZE: PART one of "
        f"{', '.join(ERROR_PARTS)}; SIZE in mm or um (lengths), deg (turns), px (the principal point) or % "
        "(of the pinhole, the sensor distance or the ball's radius), e.g. pinhole+1%, ball-x-20um, "
        f"camera-yaw+0.05deg. Default: {', '.join(DEFAULT_ERRORS)}."
    )


@bench_app.command("tolerance")
def bench_tolerance_command(
    ctx: typer.Context,
    rig: RigOption = None,
    truth: Annotated[str, typer.Option(help="Shipped truth light.")] = "five-gaussians",
    positions: Annotated[int, typer.Option(min=3, help="Schedule positions (the first N of the sweep).")] = 66,
    errors: Annotated[str | None, typer.Option(help=_rig_errors_help())] = None,
    preset: Annotated[
        str | None,
        typer.Option(
            help="Many errors at once instead of --errors, as a lab makes them, in directions drawn from each seed: "
            "typical-lab (the camera's axis 0.3° and roll 0.3°, the principal point 10 px, the camera 2 mm along "
            "and 1 mm across, the ball's radius 10 µm, the arm's base 0.5° and 1 mm, the light's tilt 1° and "
            "mount 0.5 mm, the pinhole 10 %, the sensor distance 1 %)."
        ),
    ] = None,
    seeds: Annotated[int, typer.Option(min=1, help="With --preset: the seeds 0 .. N-1, one case each.")] = 5,
    ways: Annotated[
        str | None,
        typer.Option(
            help="Comma-separated ways to process each description, instead of the flags' choice: given; given, "
            "aperture fitted; given, sensor distance fitted; given, self-calibrated; found; found, aperture "
            "fitted; found, sensor distance fitted; found, self-calibrated (as `process` does by default). Give "
            "them separated by commas, e.g. 'found,found, self-calibrated'.",
        ),
    ] = None,
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
    record: RecordOption = None,
) -> None:
    """How exact the rig description must be: one simulated run (the demo rig by default)
    processed with one number of its description wrong at a time (or a preset's many at once),
    in each way (held as described, or self-calibrated), scored against the truth.
    Progress goes to standard error; the JSON, then (without --json) the markdown table, to
    standard output."""
    from acquisition.benchmarks.tolerance import bench_tolerance
    from processing import ComputeError, ProcessingError

    chosen = None if errors is None else [e.strip() for e in errors.split(",") if e.strip()]
    recording = _start_recording(ctx, record)
    try:
        result = bench_tolerance(
            rig_path=rig,
            truth=truth,
            positions=positions,
            errors=chosen,
            preset=preset,
            seeds=seeds,
            ways=_way_names(ways),
            layout_from_data=layout_from_data,
            fit_aperture=fit_aperture,
            fit_sensor_distance=fit_sensor_distance,
            noise=noise,
            scheduler=scheduler,
            log=lambda message: typer.echo(message, err=True),
        )
    except domain_errors(ValueError, ComputeError, ProcessingError) as exc:
        raise fail(str(exc)) from None
    print_result(result, as_json)
    if not as_json:
        typer.echo("")
        typer.echo(result["markdown"])
    _record(recording, "tolerance", result)


def _way_names(text: str | None) -> list[str] | None:
    """``--ways``: names split at commas, a name's own ", " kept (``found, self-calibrated``)."""
    if text is None:
        return None
    names: list[str] = []
    for piece in (p.strip() for p in text.split(",")):
        if names and piece and piece.split()[0] in ("aperture", "sensor", "self-calibrated"):
            names[-1] = f"{names[-1]}, {piece}"
        elif piece:
            names.append(piece)
    return names


@bench_app.command("speed")
def bench_speed_command(
    ctx: typer.Context,
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
    record: RecordOption = None,
) -> None:
    """Speed of the chain at two sensor sizes: acquisition overhead, HDR merge next to its peers,
    chief rays per second, whole-run processing time and peak memory, and the read floor.
    Progress goes to standard error; the JSON, then (without --json) the markdown table, to standard output."""
    from acquisition.benchmarks.speed import bench_speed, parse_size
    from acquisition.benchmarks.speed_runs import DEFAULT_CACHE, SpeedBenchError
    from processing import ComputeError, HDRError, ProcessingError

    recording = _start_recording(ctx, record)
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
    except domain_errors(SpeedBenchError, ComputeError, ProcessingError, HDRError) as exc:
        raise fail(str(exc)) from None
    print_result(result, as_json)
    if not as_json:
        typer.echo("")
        typer.echo(result["markdown"])
    _record(recording, "speed", result)


@bench_app.command("lab")
def bench_lab_command(
    ctx: typer.Context,
    rigs: Annotated[int, typer.Option(min=2, max=9, help="Rigs: daemons, each in a network namespace of its own.")] = 3,
    workers: Annotated[int, typer.Option(min=1, max=16, help="Workers without the rigs' disks.")] = 3,
    runs: Annotated[int, typer.Option(min=3, max=300, help="Runs, shared among the rigs, one job each.")] = 30,
    cut: Annotated[float, typer.Option(min=1.0, max=600.0, help="Seconds one rig's network stays cut.")] = 30.0,
    workdir: WorkdirOption = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON only.")] = False,
    record: RecordOption = None,
) -> None:
    """A lab on one PostgreSQL catalog (needs root): daemons, workers that fetch the run files
    and send the results back, a worker killed mid-job, PostgreSQL restarted and a rig's network
    cut meanwhile; jobs lost or recorded twice, results against one machine's, recovery times,
    the catalog's latency."""
    from acquisition.benchmarks.lab import LabBenchError, bench_lab
    from acquisition.daemon.catalog.throwaway_server import PostgresNotFoundError

    recording = _start_recording(ctx, record)
    try:
        result = bench_lab(rigs=rigs, workers=workers, runs=runs, cut_s=cut, workdir=workdir)
    except domain_errors(LabBenchError, PostgresNotFoundError) as exc:
        raise fail(str(exc)) from None
    print_result(result, as_json)
    _record(recording, "lab", result)
