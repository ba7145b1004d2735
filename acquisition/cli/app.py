"""The command line's program, its options shared by several commands, and its one-line errors.

Bad input ends with a one-line ``error: ...`` on standard error and exit status 2, before
any work is done: an option outside its fixed set of values is refused by typer (the
options are enums), and :func:`main` prints typer's usage errors on one line too. The
message names the option, the file or the field.
"""

from __future__ import annotations

import inspect
import json
import logging
import sys
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Annotated, Any

import typer

from drivers.contracts.rig import DEFAULT_RIG_PATH, RigError
from drivers.contracts.version import __version__
from drivers.errors import DeviceError
from processing import FLAG_CHOICE, FitChoice, Option

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


def cli_spelling(public: str) -> str:
    """An option's name as the command line spells it (``lamp_lumens``: ``--lamp-lumens``)."""
    return "--" + public.replace("_", "-")


def cli_help(option: Option) -> str:
    """The option's help text as the command line shows it (a :class:`FitChoice` is a flag)."""
    text = option.help_as(cli_spelling)
    if option.choices is FitChoice:
        negative = f"--no-{option.flag[2:]}: never; neither" if option.default is FitChoice.AUTO else "without it"
        text += f" {option.flag}: always; {negative}: {option.default}."
    return text


def typer_option(option: Option) -> tuple[Any, Any]:
    """The annotation and the default that make ``option`` a typer option.

    A :class:`FitChoice` is a flag: ``--FLAG/--no-FLAG`` (neither given: ``auto``) for an option
    whose default is ``auto``, ``--FLAG`` alone for one whose default is ``never``
    (:data:`processing.options.FLAG_CHOICE`); a boolean is ``--FLAG/--no-FLAG`` when it is on
    by default, ``--FLAG`` alone otherwise.
    """
    default = option.given_default
    negative = f"{option.flag}/--no-{option.flag[2:]}"
    if option.choices is FitChoice:
        if default not in (FitChoice.AUTO, FitChoice.NEVER):
            raise ValueError(f"{option.name}: a flag's default is auto or never, not {default}")
        declared, kind = (negative, bool | None) if default is FitChoice.AUTO else (option.flag, bool)
        default = None if default is FitChoice.AUTO else False
    elif option.kind is bool:
        declared, kind = (negative if default else option.flag), bool
    else:
        declared, kind = option.flag, option.kind if default is not None else option.kind | None
    info = typer.Option(declared, help=cli_help(option), show_default=default is not None)
    return Annotated[kind, info], default


def with_declared_options(command: Callable, options: Iterable[Option], after: str) -> Callable:
    """``command`` taking the declared ``options`` the command line takes, after its parameter ``after``.

    ``command`` takes them as ``**given`` (by their public names): :func:`declared_values`
    turns them into the record's values. Typer reads the options from the signature this sets.
    """
    own = [p for p in inspect.signature(command, eval_str=True).parameters.values() if p.kind != p.VAR_KEYWORD]
    cut = [p.name for p in own].index(after) + 1
    built = []
    for option in options:
        if option.cli:
            annotation, default = typer_option(option)
            built.append(
                inspect.Parameter(option.public, inspect.Parameter.KEYWORD_ONLY, default=default, annotation=annotation)
            )
    rest = [p.replace(kind=inspect.Parameter.KEYWORD_ONLY) for p in own[cut:]]
    command.__signature__ = inspect.Signature([*own[:cut], *built, *rest])  # type: ignore[attr-defined]  # typer reads it
    return command


def declared_values(options: Iterable[Option], given: dict[str, Any]) -> dict[str, Any]:
    """What the command line gave for the declared options, by the record's field names."""
    values = {}
    for option in options:
        if option.public in given:
            value = given[option.public]
            values[option.name] = FLAG_CHOICE[value] if option.choices is FitChoice else value
    return values


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
