"""The command line's program, its options shared by several commands, and its one-line errors.

Bad input ends with a one-line ``error: ...`` on standard error and exit status 2, before
any work is done: an option outside its fixed set of values is refused by typer (the
options are enums), and :func:`main` prints typer's usage errors on one line too. The
message names the option, the file or the field.
"""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path
from typing import Annotated

import typer

from drivers.contracts.rig import DEFAULT_RIG_PATH, RigError
from drivers.contracts.version import __version__
from drivers.errors import DeviceError

app = typer.Typer(
    name="mirrorgonio",
    help="A mirror-ball goniophotometer: measure a near-field light source.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)
simulate_app = typer.Typer(
    help="Simulated devices: the arm's Modbus server, one rendered capture.", no_args_is_help=True
)
bench_app = typer.Typer(help="Benchmarks that print what they measured.", no_args_is_help=True)
app.add_typer(simulate_app, name="simulate")
app.add_typer(bench_app, name="bench")

RigOption = Annotated[Path | None, typer.Option("--rig", help="Rig description (TOML).")]
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


def _print_version(asked: bool) -> None:
    if asked:
        typer.echo(f"mirrorgonio {__version__}")
        raise typer.Exit()


@app.callback()
def main_options(
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log the libraries' own messages.")] = False,
    version: Annotated[
        bool,
        typer.Option("--version", callback=_print_version, is_eager=True, help="Print the version and exit."),
    ] = False,
) -> None:
    """A mirror-ball goniophotometer: measure a near-field light source."""
    # pymodbus logs connection failures straight to stderr; our errors already say it in one line.
    logging.getLogger("pymodbus").setLevel(logging.DEBUG if verbose else logging.CRITICAL)


def fail(message: str) -> typer.Exit:
    typer.echo(f"error: {message}", err=True)
    return typer.Exit(code=2)


def domain_errors(*extra: type[Exception]) -> tuple[type[Exception], ...]:
    """The errors of bad input and failing devices, each one line: a command ends with it
    (and the ``extra`` errors of the command's own work, first)."""
    from sim_devices.lights import TruthError  # noqa: PLC0415 - the simulation, only where a command uses it

    return (*extra, RigError, TruthError, DeviceError, OSError)


def print_result(result: dict, as_json: bool) -> None:
    """A benchmark's result: one JSON line with --json, indented for people otherwise."""
    typer.echo(json.dumps(result) if as_json else json.dumps(result, indent=2))


def default_rig() -> Path:
    return DEFAULT_RIG_PATH


def main(args: list[str] | None = None) -> None:
    """The console entry: the program, with every usage error on one line and exit status 2."""
    try:
        code = app(args=args, prog_name="mirrorgonio", standalone_mode=False)
    except typer.Abort:
        typer.echo("interrupted", err=True)
        sys.exit(130)
    except typer.TyperException as exc:  # typer's usage errors (click's, vendored)
        message = " ".join(exc.format_message().split()).replace("Value error, ", "")
        ctx = getattr(exc, "ctx", None)
        where = f"{ctx.command_path.removeprefix('mirrorgonio ')}: " if ctx is not None and ctx.parent else ""
        typer.echo(f"error: {where}{message}", err=True)
        sys.exit(getattr(exc, "exit_code", 2))
    sys.exit(code if isinstance(code, int) else 0)
