"""``mirrorgonio verify``: every frame of a run file read back through its checksum."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from acquisition.cli.app import app

if TYPE_CHECKING:
    from drivers.contracts.runfile import RunFile

#: Exit statuses: every file sound; a file with corrupt frames or structure; a file that is not
#: a readable run file (the worst of the files given).
SOUND, CORRUPT, UNREADABLE = 0, 1, 2


@app.command("verify")
def verify(
    runs: Annotated[list[Path], typer.Argument(help="Run files (HDF5) to check.")],
) -> None:
    """Read every frame of each run file through its checksum, and check the file's structure.

    Prints a summary per file (positions, frames, and every corrupt frame by position and
    exposure index). Exit status: 0 when every file is sound, 1 when a file has corrupt frames or
    a broken structure, 2 when a file is not a readable run file (one line, naming it)."""
    from drivers.contracts.runfile import RunFile, RunFileError  # noqa: PLC0415 - h5py, once the arguments are parsed

    status = SOUND
    for path in runs:
        try:
            with RunFile.open(path) as run:
                status = max(status, _verify_one(run))
        except RunFileError as exc:
            typer.echo(f"error: {' '.join(str(exc).split())}", err=True)
            status = UNREADABLE
    raise typer.Exit(code=status)


def _verify_one(run: RunFile) -> int:
    """Check one open run file and print what was found; its exit status."""
    from rich.console import Console  # noqa: PLC0415 - rich's progress, only for a check
    from rich.progress import Progress  # noqa: PLC0415

    positions, sets = run.completed_positions(), run.calibration_sets()
    problems = run.structure_problems()
    slots = [("position", i) for i in positions if not any(p.startswith(f"position {i} ") for p in problems)]
    with Progress(console=Console(stderr=True), transient=True) as bar:  # stdout: the summary alone
        task = bar.add_task(run.path.name, total=None)
        corrupt = run.corrupt_frames(
            positions=[i for _, i in slots],
            sets=[s for s in sets if not any(p.startswith(f"calibration {' '.join(s)} ") for p in problems)],
            progress=lambda done, total: bar.update(task, completed=done, total=total),
        )
    frames = sum(run.frame_count(int(i)) for _, i in slots)
    checksums = "frames checksummed (Fletcher32)" if run.checksummed else "frames carry NO checksums"
    typer.echo(
        f"{run.path}: run {run.header.run_id}, {run.status}; {len(positions)} of {run.n_positions} positions "
        f"complete, {frames} frames; calibration sets: {', '.join(' '.join(s) for s in sets) or 'none'}; {checksums}"
    )
    for problem in problems:
        typer.echo(f"  broken: {problem}")
    for frame in corrupt:
        typer.echo(f"  corrupt: {frame.describe()}")
    if problems or corrupt:
        where = sorted({f.slot for f in corrupt}, key=lambda s: (not s.startswith("position"), len(s), s))
        typer.echo(
            f"{run.path}: CORRUPT: {len(corrupt)} corrupt frames ({', '.join(where) or 'none'}), "
            f"{len(problems)} structure problems"
        )
        return CORRUPT
    if not run.checksummed:
        typer.echo(
            f"{run.path}: every frame decodes, but the file carries no frame checksums: "
            "a changed bit may decode to other pixels unnoticed"
        )
    else:
        typer.echo(f"{run.path}: ok: every frame reads back through its checksum")
    return SOUND
