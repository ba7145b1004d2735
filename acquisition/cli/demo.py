"""``mirrorgonio demo``: the whole chain on simulated devices."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from acquisition.cli.app import (
    WorkersOption,
    app,
    domain_errors,
    fail,
)


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
        raise fail(str(exc)) from None
    except domain_errors() as exc:
        raise fail(str(exc)) from None
    print_summary(result, console)
