"""``mirrorgonio process``: run files to results, one run after the other."""

from __future__ import annotations

import hashlib
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from acquisition.cli.app import (
    SchedulerOption,
    WorkersOption,
    app,
    declared_values,
    fail,
    with_declared_options,
)
from processing import ComputeError, OptionsError, ProcessingOptions, check_scheduler, declared_options

if TYPE_CHECKING:
    from rich.progress import Progress, TaskID

    from processing import ProcessReport


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
    if out is None:
        return {run: None for run in runs}
    from processing import run_name  # noqa: PLC0415 - the processing, once the options are checked

    by_stem: dict[str, list[Path]] = {}
    for run in runs:
        by_stem.setdefault(run_name(run), []).append(run)
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
    from rich.console import Console  # noqa: PLC0415 - rich's tables, only for a batch
    from rich.table import Table  # noqa: PLC0415

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


def process(
    runs: Annotated[list[Path], typer.Argument(help="Run files (HDF5) to process.")],
    out: Annotated[
        Path | None, typer.Option("--out", help="Folder for the results (default: beside each run).")
    ] = None,
    *,
    scheduler: SchedulerOption = "local",
    workers: WorkersOption = None,
    **given: Any,
) -> None:
    """Turn run files into results: HDR radiance per position (OpenEXR, PNG), the light model,
    and the IES, LDT and TM-25 files.

    Several runs in one call: each is processed in turn, a failed run does not stop the
    others, a summary table ends the output and the exit status is 2 if any run failed.
    With --out, each run's results are named after the run's whole name (a.1.h5 gives a.1.results.h5,
    a.1.hdr/, a.1.ies, ...); runs of the same name from different folders go to a subfolder each
    (docs/import.md). Outputs of another run already at those names stop that run before any work
    (--overwrite replaces them)."""
    try:
        options = ProcessingOptions.checked(**declared_values(PROCESSING_OPTIONS, given))
        check_scheduler(scheduler, workers)
    except (OptionsError, ComputeError) as exc:
        raise fail(str(exc)) from None
    _check_files(runs, options)
    distinct = _distinct_runs(runs)
    folders = _output_folders(distinct, out)
    _check_outputs(folders, options.overwrite)
    _finish(_process_all(distinct, folders, options, scheduler, workers))


#: The processing's options, as ``processing.options`` declares them: the command's options between --out and
#: --scheduler.
PROCESSING_OPTIONS = declared_options(ProcessingOptions)
app.command("process")(with_declared_options(process, PROCESSING_OPTIONS, after="out"))


def _finish(outcomes: list) -> None:
    """The batch's summary table (for more than one run), its errors, and its exit status."""
    if len(outcomes) > 1:
        _print_batch_summary(outcomes)
    failed = [error for *_, error in outcomes if error]
    for error in failed:
        typer.echo(f"error: {error}", err=True)
    if failed:
        raise typer.Exit(code=2)


def _check_files(runs: list[Path], options: ProcessingOptions) -> None:
    """Every run file exists and the layout can be read (one line naming the first that cannot)."""
    missing = [run for run in runs if not run.is_file()]
    if missing:
        raise fail(f"{missing[0]}: no such run file")
    if options.layout is not None:
        from processing import SourcesError, load_layout

        try:
            load_layout(options.layout, field="--layout")
        except SourcesError as exc:
            raise fail(str(exc)) from None


def _check_outputs(folders: dict[Path, Path | None], overwrite: bool) -> None:
    """No run's outputs would write over another run's (one line naming the first in the way),
    unless ``overwrite``."""
    if overwrite:
        return
    from drivers.contracts.runfile import RunFile, RunFileError  # noqa: PLC0415 - h5py, once the options are checked
    from processing import ProcessingError, check_outputs

    for run, folder in folders.items():
        try:
            with RunFile.open(run) as opened:
                run_id = opened.header.run_id
        except RunFileError:
            continue  # the processing says what is wrong with the file, in its turn
        try:
            check_outputs(run, run_id, folder if folder is not None else run.parent)
        except ProcessingError as exc:
            raise fail(str(exc)) from None


def _process_all(
    runs: list[Path], folders: dict, options: ProcessingOptions, scheduler: str, workers: int | None
) -> list:
    """Every run processed in turn on one cluster: (run, report or None, seconds, error) each."""
    from rich.progress import (  # noqa: PLC0415 - rich's progress, once options are checked
        Progress,
        TextColumn,
        TimeElapsedColumn,
    )

    from processing import ProcessingError, open_compute, process_run, warm_up_worker

    batch = len(runs) > 1
    outcomes: list[tuple[Path, object, float, str]] = []
    try:
        compute = open_compute(scheduler, workers=workers, warm_up=warm_up_worker)
    except ComputeError as exc:
        raise fail(str(exc)) from None
    columns = (*Progress.get_default_columns(), TextColumn("{task.fields[note]}"), TimeElapsedColumn())
    with compute, Progress(*columns, transient=True) as bar:
        overall = bar.add_task("runs", total=len(runs), note="") if batch else None
        for number, run in enumerate(runs, 1):
            label = f"[{number}/{len(runs)}] {run.name}" if batch else run.name
            steps = StepBars(bar, label)
            started = time.perf_counter()
            try:
                report = process_run(run, folders[run], options, compute=compute, progress=steps)
            except (ProcessingError, ValueError, OSError) as exc:
                if not batch:
                    raise fail(str(exc)) from None
                outcomes.append((run, None, time.perf_counter() - started, _naming(run, str(exc))))
                continue
            except Exception as exc:  # noqa: BLE001 - one run's failure must not stop the batch
                if not batch:
                    raise
                unexpected = _naming(run, f"unexpected {type(exc).__name__}: {exc}")
                outcomes.append((run, None, time.perf_counter() - started, unexpected))
                continue
            finally:
                steps.close()
                if overall is not None:
                    bar.advance(overall)
            outcomes.append((run, report, time.perf_counter() - started, ""))
            _say_processed(run, report)
    return outcomes


class StepBars:
    """``process_run``'s ``progress(step, done, total)`` as one rich bar per step: the run and
    the step's name, its positions (or done / to do) and its time; the steps stay listed as
    they end, until the run is done (:meth:`close`)."""

    def __init__(self, bar: Progress, run_label: str) -> None:
        self.bar, self.run_label = bar, run_label
        self.tasks: dict[str, TaskID] = {}
        self.seen: list[str] = []  # the steps in the order they started

    def __call__(self, step: str, done: int, total: int) -> None:
        from processing import STEP_BY_NAME

        unit = STEP_BY_NAME[step].unit  # the positions, counted; the other steps pulse until they end
        shown = total if unit or done >= total else None
        note = f"{done}/{total} {unit}" if unit else ""
        task = self.tasks.get(step)
        if task is None:
            self.seen.append(step)
            label = f"{self.run_label} {len(self.seen)}. {STEP_BY_NAME[step].label}"
            task = self.tasks[step] = self.bar.add_task(label, total=shown, note=note)
        self.bar.update(task, completed=done, total=shown, note=note)
        if total and done >= total:
            self.bar.stop_task(task)

    def close(self) -> None:
        for task in self.tasks.values():
            self.bar.remove_task(task)


def _say_processed(run: Path, report: ProcessReport) -> None:
    """What one run's processing wrote, and the camera's numbers it fitted."""
    from processing import run_name, skipped_line

    if report.skipped_corrupt:
        typer.echo(f"warning: {run}: {skipped_line(report.skipped_corrupt)}", err=True)
    noise = report.noise
    typer.echo(
        f"{run}: {report.positions} positions -> {report.results_file} "
        f"(noise {noise.source}: gain {noise.gain_e_per_dn:.3f} e-/DN, read noise {noise.read_noise_dn:.3f} DN; "
        f"EXR and PNG in {report.results_file.parent / (run_name(run) + '.hdr')})"
    )
    if not report.light_model:
        return
    typer.echo(f"  sources: {report.estimator_reason}")
    for label, fitted, digits in (
        ("aperture", report.aperture_fit, ".4g"),
        ("sensor distance", report.sensor_distance_fit, ".3f"),
    ):
        if fitted is not None and fitted.fitted_m is not None:
            later = f" (a later fit failed: {fitted.failed})" if fitted.failed else ""
            typer.echo(f"  {label}: {fitted.describe(digits)}{later}")
        elif fitted is not None and fitted.failed:
            typer.echo(f"  {label}: as the rig describes it (the fit to the data failed: {fitted.failed})")
    calibration = report.rig_calibration
    if calibration is not None:
        fit = calibration.fit
        typer.echo(
            f"  rig: fitted to the data (χ²/pixel {fit.chi2_described / fit.pixels:.4f} as described, "
            f"{fit.chi2 / fit.pixels:.4f} as fitted; the silhouette from {calibration.silhouette}): "
            f"{report.outputs['rig'][0]}"
        )
    if report.quality is not None:
        typer.echo(f"  {report.quality.line()}")
    files = ", ".join(
        f"{kind.upper()} {paths[0]}"
        for kind, paths in report.outputs.items()
        if kind in ("ies", "ldt", "tm25", "pbrt", "report")
    )
    typer.echo(f"  light model {report.light_model}; {files}")
