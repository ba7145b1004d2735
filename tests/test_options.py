"""Every processing option is declared once (``processing.options``), and the Python API, the
command line and the daemon's job request say what that declaration says.

Each check below lists the disagreements between one surface and the declarations: the real
surfaces have none, and a surface that drifts (an option added by hand, a help text changed in
one place, another default or bound) is caught (the last tests change one on purpose).
"""

from __future__ import annotations

import string
from dataclasses import fields

import typer
from pydantic import Field, create_model

from acquisition.cli import app
from acquisition.cli.app import cli_help, cli_spelling, declared_values
from acquisition.daemon.models import JOB_OPTIONS, JobRequest
from processing.options import (
    FitChoice,
    Option,
    ProcessingOptions,
    ReflectanceThresholds,
    declared_options,
)
from processing.reflectance.codes import ReflectanceSettings

PROCESSING = declared_options(ProcessingOptions)
THRESHOLDS = declared_options(ReflectanceThresholds)
#: The command line's names as README.md, docs/ and the tests use them: they stay.
PROCESS_FLAGS = {
    "--steps", "--method", "--noise", "--layout", "--estimator", "--fit", "--ball-centre", "--images",
    "--no-images", "--fit-aperture", "--no-fit-aperture", "--fit-sensor-distance", "--calibrate-rig",
    "--no-calibrate-rig", "--refine-point-spread", "--no-refine-point-spread", "--ignore-corrupt", "--overwrite",
    "--extrapolation", "--lamp-lumens",
    "--candela-per-unit", "--photometric-calibration", "--manufacturer", "--luminaire", "--lamp", "--rays",
}  # fmt: skip
#: The options only the command itself takes (not the processing's).
PROCESS_OWN = {"runs", "out", "scheduler", "workers"}
REFLECTANCE_FLAGS = {"--grazing-deg", "--view-grazing-deg", "--specular-deg", "--outlier", "--edge-margin"}
REFLECTANCE_OWN = {"object_run", "light", "mesh", "out", "texture_size", "ignore_corrupt", "overwrite"}
#: The job request's fields as the page (acquisition/daemon/web/app.js) and the API's clients send them.
JOB_FIELDS = {
    "steps", "partial", "ignore_corrupt", "estimator", "fit", "layout", "noise", "fit_aperture",
    "fit_sensor_distance", "calibrate_rig", "refine_point_spread", "extrapolation", "lamp_lumens", "candela_per_unit",
    "photometric_calibration", "manufacturer", "luminaire", "lamp", "rays",
}  # fmt: skip


def command(name: str):
    return typer.main.get_command(app).commands[name]


def api_disagreements(record: type, declared: tuple[Option, ...]) -> list[str]:
    """Where the record's fields are not the declared options (names, order, defaults)."""
    said = [(f.name, f.default) for f in fields(record)]
    wanted = [(option.name, option.default) for option in declared]
    return [] if said == wanted else [f"{record.__name__}: fields {said}, declared {wanted}"]


def cli_disagreements(click_command, declared: tuple[Option, ...], own: set[str]) -> list[str]:
    """Where the command's options are not the declared ones (name, default, help, choices), or
    where it has an option that is neither declared nor its own."""
    params = {param.name: param for param in click_command.params if param.name != "help"}
    on_cli = {option.public: option for option in declared if option.cli}
    problems = [f"{name}: neither declared nor the command's own" for name in set(params) - set(on_cli) - own]
    problems += [f"{name}: declared, not on the command line" for name in set(on_cli) - set(params)]
    for name, option in on_cli.items():
        param = params.get(name)
        if param is None:
            continue
        flag = option.choices is FitChoice
        default = (None if option.given_default is FitChoice.AUTO else False) if flag else option.given_default
        if param.opts != [option.flag]:
            problems.append(f"{name}: spelt {param.opts}, declared {option.flag}")
        if param.default != default:
            problems.append(f"{name}: default {param.default!r}, declared {default!r}")
        if param.help != cli_help(option) or option.help_as(cli_spelling) not in param.help:
            problems.append(f"{name}: help {param.help!r}, declared {option.help!r}")
        choices = param.type_descriptor.choices if param.type_descriptor.is_choice else None
        wanted = [member.value for member in option.choices] if option.choices and not flag else None
        if (list(choices) if choices else None) != wanted:
            problems.append(f"{name}: choices {choices}, declared {wanted}")
    return problems


def _bounds(schema: dict) -> dict:
    keys = ("minimum", "exclusiveMinimum", "maximum", "exclusiveMaximum", "minLength", "maxLength", "pattern")
    return {key: schema[key] for key in keys if key in schema}


def job_disagreements(model, declared: tuple[Option, ...]) -> list[str]:
    """Where the job request's JSON schema is not the declared options (type, default, bounds,
    enum, description), or has a field that is neither declared nor the job's own."""
    schema = model.model_json_schema()
    properties, defs = schema["properties"], schema.get("$defs", {})
    on_job = {option.public: option for option in declared if option.job}
    problems = [f"{name}: neither declared nor the job's own" for name in set(properties) - set(on_job) - {"partial"}]
    for name, option in on_job.items():
        prop = properties.get(name)
        if prop is None:
            problems.append(f"{name}: declared, not in the job request")
            continue
        default = option.given_default
        json_default = default.value if option.choices else default
        if prop.get("default") != json_default:
            problems.append(f"{name}: default {prop.get('default')!r}, declared {json_default!r}")
        if prop.get("description") != option.help_as(str):
            problems.append(f"{name}: description {prop.get('description')!r}, declared {option.help!r}")
        branches = prop.get("anyOf", [prop])
        value = next(branch for branch in branches if branch.get("type") != "null")
        value = defs[value["$ref"].rsplit("/", 1)[-1]] if "$ref" in value else value
        nullable = any(branch.get("type") == "null" for branch in branches)
        if nullable != (default is None):
            problems.append(f"{name}: nullable {nullable}, declared default {default!r}")
        kind = option.choices or option.kind
        wanted_type = {bool: "boolean", int: "integer", float: "number"}.get(kind, "string")
        if value.get("type") != wanted_type:
            problems.append(f"{name}: type {value.get('type')}, declared {kind}")
        enum = [member.value for member in option.choices] if option.choices else None
        if value.get("enum") != enum:
            problems.append(f"{name}: enum {value.get('enum')}, declared {enum}")
        bounds = {
            "exclusiveMinimum" if option.exclusive_minimum else "minimum": option.minimum,
            "exclusiveMaximum" if option.exclusive_maximum else "maximum": option.maximum,
            "minLength": option.min_length,
            "maxLength": option.max_length,
            "pattern": option.pattern,
        }
        bounds = {key: bound for key, bound in bounds.items() if bound is not None}
        if _bounds(value) != bounds:
            problems.append(f"{name}: bounds {_bounds(value)}, declared {bounds}")
    return problems


def test_the_python_api_is_the_declarations():
    assert api_disagreements(ProcessingOptions, PROCESSING) == []
    assert api_disagreements(ReflectanceSettings, THRESHOLDS) == []
    assert len(PROCESSING) == 23 and len(THRESHOLDS) == 10  # --refine-point-spread; --hold-out, --basis


def test_the_process_command_takes_the_declared_options_by_their_names():
    process = command("process")
    assert cli_disagreements(process, PROCESSING, PROCESS_OWN) == []
    flags = {flag for param in process.params for flag in (*param.opts, *param.secondary_opts)}
    assert PROCESS_FLAGS <= flags
    assert flags - PROCESS_FLAGS == {"runs", "--out", "--scheduler", "--workers"}


def test_the_reflectance_command_takes_the_declared_thresholds_by_their_names():
    reflectance = command("reflectance")
    assert cli_disagreements(reflectance, THRESHOLDS, REFLECTANCE_OWN) == []
    flags = {flag for param in reflectance.params for flag in param.opts}
    assert REFLECTANCE_FLAGS <= flags


def test_the_job_request_is_the_declared_options():
    assert job_disagreements(JobRequest, PROCESSING) == []
    assert set(JobRequest.model_json_schema()["properties"]) == JOB_FIELDS
    assert {option.public for option in JOB_OPTIONS} == JOB_FIELDS - {"partial"}


def test_a_help_text_names_only_declared_options():
    for declared in (PROCESSING, THRESHOLDS):
        public = {option.public for option in declared}
        for option in declared:
            named = {name for _, name, _, _ in string.Formatter().parse(option.help) if name is not None}
            assert named <= public, (option.name, named - public)


def test_the_command_lines_flags_are_the_fit_choices():
    options = {option.name: option for option in PROCESSING}
    given = {"fit_aperture": None, "fit_sensor_distance": True, "calibrate_rig": False, "fit": "polynomial"}
    values = declared_values(PROCESSING, given)
    assert values == {
        "fit_aperture": FitChoice.AUTO,
        "fit_sensor_distance": FitChoice.ALWAYS,
        "calibrate_rig": FitChoice.NEVER,
        "fit_method": "polynomial",
    }
    checked = ProcessingOptions.checked(**values)
    assert (checked.fit_aperture, checked.fit_method.value) == (FitChoice.AUTO, "polynomial")
    assert "--fit-aperture: always; --no-fit-aperture: never; neither: auto." in cli_help(options["fit_aperture"])
    assert "--fit-sensor-distance: always; without it: never." in cli_help(options["fit_sensor_distance"])


def test_a_drifted_surface_is_caught():
    """What the checks above would say if someone declared an option again by hand."""
    rays = next(option for option in PROCESSING if option.name == "rays")
    by_hand = create_model(
        "Drifted",
        __base__=JobRequest,
        rays=(int, Field(default=rays.default, ge=rays.minimum, le=rays.maximum, description="rays in the file")),
        units=(str, Field(default="relative")),
    )
    said = job_disagreements(by_hand, PROCESSING)
    assert any(line.startswith("rays: description 'rays in the file'") for line in said), said
    assert "units: neither declared nor the job's own" in said
    process = command("process")
    lamp = next(param for param in process.params if param.name == "lamp")
    lamp.help = "The lamp."  # changed here, not in the declaration
    lamp.default = "LED"
    said = cli_disagreements(process, PROCESSING, PROCESS_OWN - {"workers"})
    assert any(line.startswith("lamp: help 'The lamp.'") for line in said), said
    assert "lamp: default 'LED', declared None" in said and "workers: neither declared nor the command's own" in said
    assert api_disagreements(ReflectanceSettings, PROCESSING) != []
