"""Commands on raw files captured elsewhere: ``import`` (a run file made of them) and
``calibrate`` (the ball's centre from its silhouette)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from acquisition.cli.app import (
    RigOption,
    app,
    default_rig,
    domain_errors,
    fail,
)


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
    from rich.progress import Progress, TaskID

    from acquisition.importer import RunImportError, format_ranges, import_run

    with Progress(transient=True) as bar:
        tasks: dict[str, TaskID] = {}

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
            raise fail(" ".join(str(exc).split())) from None
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
    from processing import CalibrationError, angle_sensitivity, calibrate_ball, compare_with_rig, mosaic_luminance

    try:
        rig_model = load_rig(rig or default_rig())
        frame = decode_raw(image)
        fit = calibrate_ball(mosaic_luminance(frame.mosaic, frame.black_level.mean()), rig_model)
        comparison = compare_with_rig(fit, rig_model)
        poses = rig_model.light_poses()
        sensitivity = angle_sensitivity(rig_model, poses[len(poses) // 2])
    except domain_errors(CalibrationError) as exc:
        raise fail(str(exc)) from None
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
