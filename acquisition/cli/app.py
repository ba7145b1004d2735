"""The command line's program, its options shared by several commands, and its one-line errors.

Bad input ends with a one-line ``error: ...`` on standard error and exit status 2; the
message names the file or the field.
"""

from __future__ import annotations

import json
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


def fail(message: str) -> typer.Exit:
    typer.echo(f"error: {message}", err=True)
    return typer.Exit(code=2)


def domain_errors():
    from drivers.contracts.rig import RigError
    from drivers.errors import DeviceError
    from sim_devices.lights import TruthError

    return (RigError, TruthError, DeviceError, OSError)


def print_result(result: dict, as_json: bool) -> None:
    """A benchmark's result: one JSON line with --json, indented for people otherwise."""
    typer.echo(json.dumps(result) if as_json else json.dumps(result, indent=2))


def default_rig() -> Path:
    from drivers.contracts.rig import DEFAULT_RIG_PATH

    return DEFAULT_RIG_PATH


def main() -> None:  # pragma: no cover - console entry
    app()
