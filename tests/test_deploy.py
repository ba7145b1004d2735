"""The deployment files (docker-compose.yml, Dockerfile, .dockerignore), checked without Docker.

No engine runs here, so nothing is built or started. Instead:

- the compose file is resolved by Debian's ``docker-compose config`` when it is installed
  (``make test`` installs it), else parsed here with the same interpolation rules;
- every service's command line is parsed by the real command it runs (``mirrorgonio`` via
  its click command, ``dask scheduler`` / ``dask worker`` via theirs) without running it, so
  an unknown option, a bad value or a missing argument is a failure;
- the addresses, ports and paths the services give each other agree;
- the Dockerfile installs this project and copies only what exists and is not ignored.

``compose_problems`` returns every problem it finds; a copy of the compose file with one
planted mistake must give at least one (so the checks can fail).
"""

from __future__ import annotations

import ast
import fnmatch
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path
from urllib.parse import urlparse

import click
import pytest
import typer.main
import yaml

ROOT = Path(__file__).resolve().parent.parent
COMPOSE = ROOT / "docker-compose.yml"
RIG_COMPOSE = ROOT / "docker-compose.rig.yml"
RIG_FILE_MESSAGE = "set MG_RIG_FILE to the rig description (TOML) of this rig"
DOCKERFILE = ROOT / "Dockerfile"
DOCKERIGNORE = ROOT / ".dockerignore"
TOKEN_MESSAGE = "set MG_TOKEN to the API token"
DOCKER_COMPOSE = shutil.which("docker-compose")
#: The services the issue asks for, by profile (None: always on).
EXPECTED = {
    "daemon": None,
    "worker": None,
    "sim-arm": None,
    "dask-scheduler": "scale",
    "dask-worker": "scale",
    "catalog-db": "lab",
    "lab-daemon": "lab",
    "lab-worker": "lab",
}
#: The services that run another project's image: the lab's catalog, on PostgreSQL's own.
EXTERNAL_IMAGES = {"catalog-db": "postgres:"}


# --- resolving the compose file ---------------------------------------------------------------
class ComposeError(Exception):
    pass


_VARIABLE = re.compile(
    r"\$\{(?P<name>[A-Za-z_][A-Za-z0-9_]*)(?:(?P<op>:?[-?])(?P<arg>[^}]*))?\}|\$(?P<bare>[A-Za-z_][A-Za-z0-9_]*)"
)


def _interpolate(value, env: dict[str, str], where: str):
    """Compose's ``${VAR}``, ``${VAR:-default}``, ``${VAR-default}``, ``${VAR:?message}``, ``$$``."""
    if isinstance(value, dict):
        return {k: _interpolate(v, env, f"{where}.{k}") for k, v in value.items()}
    if isinstance(value, list):
        return [_interpolate(v, env, where) for v in value]
    if not isinstance(value, str):
        return value

    def one(match: re.Match) -> str:
        name = match["name"] or match["bare"]
        op, arg = match["op"], match["arg"] or ""
        present = name in env
        empty = not env.get(name)
        if op in (":?", "?") and (not present or (op == ":?" and empty)):
            raise ComposeError(f'Missing mandatory value for "{where}": {arg or name}')
        if op in (":-", "-") and (not present or (op == ":-" and empty)):
            return arg
        return env.get(name, "")

    parts = value.split("$$")
    return "$".join(_VARIABLE.sub(one, part) for part in parts)


def _parse_compose(path: Path, env: dict[str, str]) -> dict:
    """What ``docker-compose config`` does, as far as these tests need (YAML merge keys included)."""
    data = yaml.safe_load(path.read_text())
    data = {k: v for k, v in data.items() if not k.startswith("x-")}
    return _interpolate(data, env, "compose")


def resolve_compose(path: Path, env: dict[str, str], tool: str | None = DOCKER_COMPOSE) -> dict:
    """The resolved compose file: by ``docker-compose config`` if available, else parsed here."""
    if tool is None:
        return _parse_compose(path, env)
    base = {k: v for k, v in os.environ.items() if not k.startswith(("MG_", "COMPOSE_"))}
    result = subprocess.run(
        [tool, "-f", str(path), "config"],
        capture_output=True,
        text=True,
        env={**base, **env},
        cwd=path.parent,
        timeout=60,
    )
    if result.returncode != 0:
        raise ComposeError(result.stderr.strip() or result.stdout.strip())
    return yaml.safe_load(result.stdout)


# --- the image's defaults (Dockerfile) ---------------------------------------------------------
def dockerfile_instructions(path: Path = DOCKERFILE) -> list[tuple[str, str]]:
    """``(INSTRUCTION, arguments)`` pairs, continuation lines joined, comments dropped."""
    instructions, pending = [], ""
    for line in path.read_text().splitlines():
        stripped = line.strip()
        if not pending and (not stripped or stripped.startswith("#")):
            continue
        if pending and stripped.startswith("#"):
            continue
        pending += " " + stripped[:-1] if stripped.endswith("\\") else " " + stripped
        if not stripped.endswith("\\"):
            keyword, _, rest = pending.strip().partition(" ")
            instructions.append((keyword.upper(), rest.strip()))
            pending = ""
    return instructions


def _exec_form(arguments: str) -> list[str]:
    value = json.loads(arguments) if arguments.startswith("[") else shlex.split(arguments)
    assert isinstance(value, list)
    return [str(v) for v in value]


def image_defaults() -> tuple[list[str], list[str]]:
    entrypoint: list[str] = []
    cmd: list[str] = []
    for keyword, arguments in dockerfile_instructions():
        if keyword == "ENTRYPOINT":
            entrypoint = _exec_form(arguments)
        elif keyword == "CMD":
            cmd = _exec_form(arguments)
    return entrypoint, cmd


def service_argv(service: dict) -> list[str]:
    """What the container runs: entrypoint + command, each from the service or the image."""
    entrypoint, cmd = image_defaults()
    if "entrypoint" in service:
        entrypoint = (
            service["entrypoint"] if isinstance(service["entrypoint"], list) else shlex.split(service["entrypoint"])
        )
        cmd = []  # a service's entrypoint resets the image's CMD
    if "command" in service:
        cmd = service["command"] if isinstance(service["command"], list) else shlex.split(service["command"])
    return [str(a) for a in [*entrypoint, *cmd]]


# --- parsing a command line with the real command, without running it --------------------------
def _mirrorgonio_command() -> click.Command:
    from acquisition.cli import app

    return typer.main.get_command(app)


def _dask_command() -> click.Group:
    """The ``dask`` program's group with the subcommands its entry points register."""
    from importlib.metadata import entry_points

    group = click.Group("dask")
    for ep in entry_points(group="dask_cli"):
        group.add_command(ep.load(), ep.name)
    return group


PROGRAMS = {"mirrorgonio": _mirrorgonio_command, "dask": _dask_command}


def _usage_errors() -> tuple[type[Exception], ...]:
    """click's errors, and those of the copy of click that newer typer carries inside."""
    errors: list[type[Exception]] = [click.ClickException]
    try:
        from typer._click.exceptions import ClickException
    except ImportError:  # an older typer on the real click
        pass
    else:
        errors.append(ClickException)
    return tuple(errors)


USAGE_ERRORS = _usage_errors()


def parse_command_line(argv: list[str]) -> list[click.Context]:
    """Parse ``argv`` as its program would, down to the leaf subcommand; raise click's error
    on an unknown program, subcommand or option, a bad value or a missing argument."""
    if not argv or argv[0] not in PROGRAMS:
        raise click.UsageError(f"not a program of this image: {argv[:1]}")
    command = PROGRAMS[argv[0]]()
    contexts = [command.make_context(argv[0], list(argv[1:]), resilient_parsing=False)]
    while hasattr(contexts[-1].command, "resolve_command"):  # a group: on to its subcommand
        ctx = contexts[-1]
        protected = ctx._protected_args if hasattr(ctx, "_protected_args") else ctx.protected_args
        args = [*protected, *ctx.args]
        if not args:
            raise click.UsageError("no subcommand", ctx)
        name, sub, rest = ctx.command.resolve_command(ctx, args)
        contexts.append(sub.make_context(name, rest, parent=ctx))
    if contexts[-1].args:
        raise click.UsageError(f"unexpected arguments {contexts[-1].args}", contexts[-1])
    return contexts


def _option(argv: list[str], name: str) -> str | None:
    for i, token in enumerate(argv):
        if token == name and i + 1 < len(argv):
            return argv[i + 1]
        if token.startswith(name + "="):
            return token.split("=", 1)[1]
    return None


def _healthcheck_code(service: dict) -> str | None:
    test = (service.get("healthcheck") or {}).get("test")
    if not test or test[0] not in ("CMD", "CMD-SHELL"):
        return None
    if test[1:3] == ["python", "-c"]:
        return test[3]
    return None


def _profiles(service: dict) -> set[str]:
    return set(service.get("profiles") or [])


# --- all the checks, as a list of problems ---------------------------------------------------------
def compose_problems(
    path: Path = COMPOSE, env: dict[str, str] | None = None, tool: str | None = DOCKER_COMPOSE
) -> list[str]:
    env = {"MG_TOKEN": "test-token-0123456789"} if env is None else env
    try:
        config = resolve_compose(path, env, tool)
    except ComposeError as exc:
        return [f"compose file does not resolve: {exc}"]
    problems: list[str] = []
    services: dict = config.get("services") or {}
    for name, prefix in EXTERNAL_IMAGES.items():
        if name in services and not str(services[name].get("image", "")).startswith(prefix):
            problems.append(f"{name}: image {services[name].get('image')}, expected {prefix}...")
    external = {name: services.pop(name) for name in EXTERNAL_IMAGES if name in services}
    argv = {name: service_argv(svc) for name, svc in services.items()}

    everything = {**services, **external}
    for name, profile in EXPECTED.items():
        if name not in everything:
            problems.append(f"{name}: missing")
        elif _profiles(everything[name]) != ({profile} if profile else set()):
            problems.append(f"{name}: profiles {sorted(_profiles(everything[name]))}, expected {profile or 'none'}")

    # One image for all.
    images = {(svc.get("image"), json.dumps(svc.get("build"), sort_keys=True)) for svc in services.values()}
    if len(images) != 1 or any(image is None or build == "null" for image, build in images):
        problems.append(f"services do not share one built image: {sorted(map(str, images))}")

    # Every command is a real command line of this image.
    for name, args in argv.items():
        try:
            parse_command_line(args)
        except USAGE_ERRORS as exc:
            problems.append(f"{name}: {shlex.join(args)}: {exc.format_message()}")

    # Healthchecks: present where promised, valid Python, on the port the service listens on.
    for name, svc in services.items():
        code = _healthcheck_code(svc)
        if code is None:
            if argv[name][:2] != ["mirrorgonio", "worker"]:  # the processing workers have none
                problems.append(f"{name}: no healthcheck")
            continue
        try:
            ast.parse(code)
        except SyntaxError as exc:
            problems.append(f"{name}: healthcheck is not valid Python: {exc}")
        ports = set(re.findall(r"(?:127\.0\.0\.1|localhost)['\"]?\s*[,:]\s*(\d+)", code))
        listening = {
            _option(argv[name], "--port"),
            (_option(argv[name], "--dashboard-address") or "").rpartition(":")[2],
        }
        if not ports or not ports <= listening:
            problems.append(
                f"{name}: healthcheck checks port(s) {sorted(ports)}, the service listens on "
                f"{sorted(p for p in listening if p)}"
            )

    # depends_on: the long form, waiting for health where there is one; no service that is
    # always on may depend on one that only a profile starts.
    for name, svc in services.items():
        for dep, spec in (svc.get("depends_on") or {}).items():
            if dep not in everything:
                problems.append(f"{name}: depends on unknown service {dep}")
                continue
            wanted = "service_healthy" if "healthcheck" in everything[dep] else "service_started"
            if not isinstance(spec, dict) or spec.get("condition") != wanted:
                problems.append(f"{name}: depends_on {dep} should have condition {wanted}")
            if not _profiles(svc) and _profiles(everything[dep]):
                problems.append(
                    f"{name}: always on, but depends on {dep} of profile(s) {sorted(_profiles(everything[dep]))}"
                )

    # Data on the named volume, at the same path everywhere (the catalog records run paths).
    declared = set((config.get("volumes") or {}).keys())
    for name in ("daemon", "worker", "worker-scale", "dask-worker"):
        if name not in services:
            continue
        mounts = [
            str(v) if isinstance(v, str) else f"{v.get('source')}:{v.get('target')}"
            for v in services[name].get("volumes") or []
        ]
        named = [m.split(":")[0] for m in mounts if m.split(":")[1:2] == ["/data"]]
        if not named or named[0] not in declared:
            problems.append(f"{name}: /data is not on a named volume declared under volumes: ({mounts})")

    daemon_problems, data_dir = _daemon_problems(services, argv)
    return (
        problems
        + daemon_problems
        + _links_problems(services, argv, data_dir)
        + _lab_problems(services, external, argv, declared)
    )


def _lab_problems(services: dict, external: dict, argv: dict, declared: set[str]) -> list[str]:
    """The lab profile: the daemon and the workers on the catalog-db service's database, the
    workers told where the daemon answers and sharing no volume with it."""
    if "lab-daemon" not in services:
        return []
    from acquisition.daemon.settings import SettingsError

    problems = []
    db = external.get("catalog-db") or {}
    db_env = db.get("environment") or {}
    try:
        daemon = daemon_settings(services["lab-daemon"], argv["lab-daemon"])
    except (SettingsError, ValueError) as exc:
        return [f"lab-daemon: its configuration is refused: {exc}"]
    catalogs = {"lab-daemon": daemon.catalog}
    for name, args in argv.items():
        if args[:2] == ["mirrorgonio", "worker"] and "lab" in _profiles(services[name]):
            catalogs[name] = _option(args, "--catalog") or (services[name].get("environment") or {}).get("MG_CATALOG")
            shared = {str(v).split(":")[0] for v in services[name].get("volumes") or []} & {
                str(v).split(":")[0] for v in services["lab-daemon"].get("volumes") or []
            }
            if shared:
                problems.append(f"{name}: shares volume(s) {sorted(shared)} with lab-daemon")
            if not (services[name].get("environment") or {}).get("MG_TOKEN"):
                problems.append(f"{name}: no MG_TOKEN to fetch run files from the daemons with")
    for name, url in catalogs.items():
        parts = urlparse(url or "")
        if (
            parts.scheme != "postgresql"
            or parts.hostname != "catalog-db"
            or str(parts.port) not in db.get("expose", [])
        ):
            problems.append(f"{name}: catalog {url!r} is not the catalog-db service's PostgreSQL")
        elif (parts.username, parts.path.lstrip("/")) != (db_env.get("POSTGRES_USER"), db_env.get("POSTGRES_DB")):
            problems.append(f"{name}: catalog {url!r} names another user or database than catalog-db creates")
    told = urlparse(daemon.daemon_url())
    if told.hostname != "lab-daemon" or str(told.port) != str(daemon.port):
        problems.append(f"lab-daemon: workers are told {daemon.daemon_url()}, not where it listens")
    volumes = [str(v).split(":")[0] for v in services["lab-daemon"].get("volumes") or []]
    if not volumes or volumes[0] not in declared or volumes[0] == "mg-data":
        problems.append(f"lab-daemon: its runs are not on a volume of its own ({volumes})")
    return problems


def daemon_settings(service: dict, args: list[str]):
    """The settings ``mirrorgonio serve`` builds in the container from the service's
    environment and command line (``SettingsError`` if it refuses them)."""
    from acquisition.daemon.settings import load_settings

    env = {k: str(v) for k, v in (service.get("environment") or {}).items()}
    saved = {k: v for k, v in os.environ.items() if k.startswith("MG_")}
    try:
        for key in saved:
            del os.environ[key]
        os.environ.update(env)
        port = _option(args, "--port")
        settings = load_settings(
            _option(args, "--config"),
            host=_option(args, "--host"),
            port=int(port) if port else None,
            data_dir=_option(args, "--data-dir"),
        )
        settings.require_token_off_loopback()
        return settings
    finally:
        for key in env:
            os.environ.pop(key, None)
        os.environ.update(saved)


def published_ports(service: dict) -> list[tuple[str, str, str]]:
    """``(host address, host port, container port)`` of each published port, in either of
    the forms a resolved file has (``{published, target, host_ip}`` or ``[IP:]HOST:TARGET[/tcp]``)."""
    out = []
    for port in service.get("ports") or []:
        if isinstance(port, dict):
            out.append((str(port.get("host_ip", "")), str(port.get("published", "")), str(port.get("target"))))
        else:
            parts = str(port).split("/")[0].split(":")
            parts = [""] * (3 - len(parts)) + parts
            out.append((parts[0], parts[1], parts[2]))
    return out


def _daemon_problems(services: dict, argv: dict) -> tuple[list[str], str | None]:
    """The daemon's environment and options are a valid configuration that reaches the arm;
    and its data folder (the catalog and the runs)."""
    from acquisition.daemon.settings import SettingsError

    if "daemon" not in services:
        return [], None
    if not (services["daemon"].get("environment") or {}).get("MG_TOKEN"):
        return ["daemon: MG_TOKEN is not passed to the daemon"], None
    try:
        settings = daemon_settings(services["daemon"], argv["daemon"])
    except (SettingsError, ValueError) as exc:
        return [f"daemon: its configuration is refused: {exc}"], None
    problems = []
    from acquisition.daemon.api.guard import RequestGuard

    for netloc in re.findall(r"https?://([^/'\"]+)", _healthcheck_code(services["daemon"]) or ""):
        if not RequestGuard(None, settings).allowed(netloc):  # the Host check would refuse it: 400
            problems.append(f"daemon: its healthcheck's host {netloc} is not one it answers to (MG_ALLOWED_HOSTS)")
    if str(settings.data_dir) != "/data":
        problems.append(f"daemon: data in {settings.data_dir}, not on the /data volume")
    if settings.host != "0.0.0.0":
        problems.append(f"daemon: listens on {settings.host}; other containers cannot reach it")
    published = published_ports(services["daemon"])
    if str(settings.port) not in [target for *_, target in published]:
        problems.append(f"daemon: port {settings.port} is not published ({published})")
    if settings.arm.kind != "simulated":
        if settings.arm.profile is None or not Path(settings.arm.profile).is_file():
            problems.append(f"daemon: arm profile {settings.arm.profile} does not exist")
        if settings.arm.host not in services:
            problems.append(f"daemon: arm host {settings.arm.host} is not a service")
        elif _option(argv[settings.arm.host], "--port") != str(settings.arm.port):
            problems.append(f"daemon: arm port {settings.arm.port} is not where {settings.arm.host} listens")
        elif _option(argv[settings.arm.host], "--host") != "0.0.0.0":
            problems.append(f"{settings.arm.host}: listens on loopback only; the daemon cannot reach it")
    if settings.camera.kind != "simulated":
        problems.append(f"daemon: camera {settings.camera.kind}: the deployment has no camera device")
    return problems, str(settings.data_dir)


def _links_problems(services: dict, argv: dict, data_dir: str | None) -> list[str]:
    """Data folders (the catalog is in it) and scheduler addresses the services give each other agree."""
    problems = []
    scheduler = services.get("dask-scheduler")
    scheduler_at = None
    if scheduler is not None:
        scheduler_at = ("dask-scheduler", _option(argv["dask-scheduler"], "--port") or "8786")
    for name, args in argv.items():
        if args[:2] == ["mirrorgonio", "worker"]:
            catalog = _option(args, "--catalog") or (services[name].get("environment") or {}).get("MG_CATALOG")
            on_server = (catalog or "").startswith("postgresql://")  # its data folder is its own (_lab_problems)
            if data_dir and not on_server and _option(args, "--data-dir") != data_dir:
                problems.append(f"{name}: --data-dir {_option(args, '--data-dir')}, the daemon's is {data_dir}")
            address = _option(args, "--scheduler") or (services[name].get("environment") or {}).get("MG_SCHEDULER")
            if address not in (None, "local", "none"):
                if "scale" not in _profiles(services[name]):
                    problems.append(f"{name}: uses a Dask scheduler outside the scale profile")
                url = urlparse(address)
                if (url.hostname, str(url.port)) != scheduler_at:
                    problems.append(f"{name}: --scheduler {address} is not the dask-scheduler service {scheduler_at}")
        if args[:2] == ["dask", "worker"]:
            url = urlparse(args[2] if len(args) > 2 else "")
            if (url.hostname, str(url.port)) != scheduler_at:
                problems.append(f"{name}: scheduler {args[2:3]} is not the dask-scheduler service {scheduler_at}")
    if scheduler is not None and not any(
        (_option(a, "--scheduler") or "").startswith("tcp://") and "scale" in _profiles(services[n])
        for n, a in argv.items()
        if a[:2] == ["mirrorgonio", "worker"]
    ):
        problems.append("profile scale: no mirrorgonio worker is pointed at the Dask scheduler")
    return problems


# --- .dockerignore ------------------------------------------------------------------------------
def dockerignored(relative: str, patterns: list[str]) -> bool:
    """Docker's rule: the last matching pattern wins; ``!`` re-includes; a folder's match
    covers what is inside; ``**`` matches any number of folders."""
    parts = relative.strip("/").split("/")
    candidates = ["/".join(parts[: i + 1]) for i in range(len(parts))]
    ignored = False
    for raw in patterns:
        negate = raw.startswith("!")
        pattern = raw[1:] if negate else raw
        pattern = pattern.strip("/")
        variants = {pattern}
        while pattern.startswith("**/"):
            pattern = pattern[3:]
            variants.add(pattern)
        if any(
            fnmatch.fnmatchcase(c, v) and (v.count("/") == c.count("/") or "**" in v)
            for c in candidates
            for v in variants
        ):
            ignored = not negate
    return ignored


def dockerignore_patterns() -> list[str]:
    lines = DOCKERIGNORE.read_text().splitlines() if DOCKERIGNORE.exists() else []
    return [line.strip() for line in lines if line.strip() and not line.strip().startswith("#")]


# --- tests ---------------------------------------------------------------------------------------
def test_compose_file_is_valid_and_consistent():
    assert compose_problems() == []


@pytest.mark.skipif(DOCKER_COMPOSE is None, reason="docker-compose is not installed (make test installs it)")
def test_docker_compose_config_needs_the_token_and_says_so():
    resolved = resolve_compose(COMPOSE, {"MG_TOKEN": "x"})
    assert resolved["services"]["daemon"]["environment"]["MG_TOKEN"] == "x"
    for env in ({}, {"MG_TOKEN": ""}):
        result = subprocess.run(
            [DOCKER_COMPOSE, "-f", str(COMPOSE), "config"],
            capture_output=True,
            text=True,
            env={k: v for k, v in os.environ.items() if k != "MG_TOKEN"} | env,
            timeout=60,
        )
        assert result.returncode != 0
        assert TOKEN_MESSAGE in result.stderr


def test_the_fallback_parser_needs_the_token_too():
    with pytest.raises(ComposeError, match=TOKEN_MESSAGE):
        _parse_compose(COMPOSE, {})
    assert compose_problems(env={}, tool=None) == [
        f"compose file does not resolve: Missing mandatory value for "
        f'"compose.services.daemon.environment.MG_TOKEN": {TOKEN_MESSAGE}'
    ]


def _without_docker_compose(why: str) -> None:
    """`make test` installs docker-compose (apt, with chromium): under CI its absence is a failure."""
    if os.environ.get("CI"):
        pytest.fail("docker-compose is missing under CI: `make test`'s apt step should have installed it")
    pytest.skip(f"docker-compose is not installed: {why}")


def test_the_fallback_parser_resolves_the_file_as_docker_compose_does():
    parsed = _parse_compose(COMPOSE, {"MG_TOKEN": "x"})
    assert compose_problems(tool=None) == []
    if DOCKER_COMPOSE is None:
        _without_docker_compose("nothing to compare with")
    resolved = resolve_compose(COMPOSE, {"MG_TOKEN": "x"})
    assert set(parsed["services"]) == set(resolved["services"])
    for name, svc in parsed["services"].items():
        assert service_argv(svc) == service_argv(resolved["services"][name]), name
        assert svc.get("profiles") == resolved["services"][name].get("profiles"), name
        assert set(svc.get("depends_on") or {}) == set(resolved["services"][name].get("depends_on") or {}), name
        env = {k: str(v) for k, v in (svc.get("environment") or {}).items()}
        assert env == {k: str(v) for k, v in (resolved["services"][name].get("environment") or {}).items()}, name


def test_every_service_runs_a_real_command_line():
    """The same check as in compose_problems, spelled out: each argv parses to a leaf command."""
    services = _parse_compose(COMPOSE, {"MG_TOKEN": "x"})["services"]
    leaves = {}
    for name, svc in services.items():
        if name in EXTERNAL_IMAGES:
            continue
        contexts = parse_command_line(service_argv(svc))
        leaves[name] = " ".join(c.info_name for c in contexts)
    assert leaves == {
        "lab-daemon": "mirrorgonio serve",
        "lab-worker": "mirrorgonio worker",
        "sim-arm": "mirrorgonio simulate arm",
        "daemon": "mirrorgonio serve",
        "worker": "mirrorgonio worker",
        "worker-scale": "mirrorgonio worker",
        "dask-scheduler": "dask scheduler",
        "dask-worker": "dask worker",
    }


def test_the_dask_workers_get_the_environment_a_local_cluster_gives_its_workers():
    """What ``LOCAL_CLUSTER_CONFIG`` sets in a local cluster's workers before they start (one
    malloc arena) the compose file's Dask workers have too: a ``tcp://`` cluster processes
    the same tasks."""
    from processing.parallel import LOCAL_CLUSTER_CONFIG

    prefix = "distributed.nanny.pre-spawn-environ."
    wanted = {k[len(prefix) :]: v for k, v in LOCAL_CLUSTER_CONFIG.items() if k.startswith(prefix) and v is not None}
    assert wanted == {"MALLOC_ARENA_MAX": "1"}
    env = _parse_compose(COMPOSE, {"MG_TOKEN": "x"})["services"]["dask-worker"].get("environment") or {}
    assert {k: str(env.get(k)) for k in wanted} == wanted


@pytest.mark.parametrize("sub", ["scheduler", "worker"])
def test_the_dask_program_lists_the_options_the_services_use(sub):
    """``dask scheduler --help`` / ``dask worker --help`` of this environment's dask program."""
    services = _parse_compose(COMPOSE, {"MG_TOKEN": "x"})["services"]
    used = {
        t.split("=")[0]
        for svc in services.values()
        for argv in [service_argv(svc)]
        if argv[:2] == ["dask", sub]
        for t in argv[2:]
        if t.startswith("--")
    }
    assert used
    exe = Path(sys.executable).with_name("dask")
    result = subprocess.run([str(exe), sub, "--help"], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    missing = {option for option in used if not re.search(rf"(^|[\s,/]){re.escape(option)}\b", result.stdout)}
    assert not missing, result.stdout


def test_the_image_default_command_is_valid_too():
    entrypoint, cmd = image_defaults()
    assert entrypoint == ["mirrorgonio"]
    assert [c.info_name for c in parse_command_line([*entrypoint, *cmd])] == ["mirrorgonio", "serve"]


PLANTED = [
    # (what is replaced, by what): each one a mistake a person could make.
    (
        'command: ["simulate", "arm", "--host", "0.0.0.0", "--port", "5020"]',
        'command: ["simulate", "arm", "--host", "0.0.0.0", "--prot", "5020"]',
    ),
    ('"--port", "8000", "--data-dir", "/data"]', '"--port", "eighty", "--data-dir", "/data"]'),
    ('command: ["worker", "--data-dir", "/data"]', 'command: ["wroker", "--data-dir", "/data"]'),
    ('command: ["worker", "--data-dir", "/data"]', 'command: ["worker", "--data-dir"]'),
    ('command: ["worker", "--data-dir", "/data"]', 'command: ["worker", "--catalog", "/data/catalog.sqlite"]'),
    ('command: ["worker", "--data-dir", "/data"]', 'command: ["worker", "--data-dir", "/srv"]'),
    ('"--data-dir", "/data", "--scheduler"', '"--data-dir", "/data", "--sched"'),
    ('"--nthreads", "2"', '"--nthread", "2"'),
    ('["scheduler", "--host"', '["schedular", "--host"'),
    ('MG_ARM__PORT: "5020"', 'MG_ARM__PORT: "502"'),
    ("MG_ARM__KIND: modbus-tcp", "MG_ARM__KIND: modbus"),
    ("MG_TOKEN: ${MG_TOKEN:?set MG_TOKEN to the API token}", "MG_TOKEN: ${MG_TOKEN:-}"),
    ("condition: service_healthy  # the daemon", "condition: service_started  # the daemon"),
    ("'http://127.0.0.1:8000/health'", "'http://127.0.0.1:8080/health'"),
    ("'http://127.0.0.1:8000/health'", "'http://daemon:8000/health'"),  # a Host the daemon refuses
    ('"tcp://dask-scheduler:8786"]', '"tcp://dask-scheduler:8788"]'),
    # The lab: a worker that mounts the rig's volume, a catalog that is not catalog-db's, a
    # daemon that tells the workers a wrong address, the database's image replaced.
    (
        'command: ["worker", "--data-dir", "/tmp/worker"]',
        'command: ["worker", "--data-dir", "/tmp/worker"]\n    volumes:\n      - mg-rig-data:/data',
    ),
    ("@catalog-db:5432/mirrorgonio\n      MG_RIG_NAME", "@catalog-db:5433/mirrorgonio\n      MG_RIG_NAME"),
    ("MG_PUBLIC_URL: http://lab-daemon:8000", "MG_PUBLIC_URL: http://lab-daemon:8001"),
    ("image: postgres:16-bookworm", "image: mirrorgonio:latest"),
]


@pytest.mark.parametrize("tool", ["docker-compose", "parser"])
@pytest.mark.parametrize(("old", "new"), PLANTED, ids=[new for _, new in PLANTED])
def test_a_planted_mistake_is_found(tmp_path, old, new, tool):
    if tool == "docker-compose" and DOCKER_COMPOSE is None:
        _without_docker_compose("the planted mistake is checked by the parser alone")
    text = COMPOSE.read_text()
    assert text.count(old) >= 1, f"the compose file changed: update the planted mistake {old!r}"
    broken = tmp_path / "docker-compose.yml"
    broken.write_text(text.replace(old, new, 1))  # the first: the one-host daemon's, where the lab's repeats it
    env = {} if "MG_TOKEN:-" in new else None
    chosen = DOCKER_COMPOSE if tool == "docker-compose" else None
    problems = compose_problems(broken, env=env, tool=chosen)
    # Found on its own: a problem the real file does not have.
    assert set(problems) - set(compose_problems(tool=chosen)), f"planting {new!r} went unnoticed"


def test_the_daemon_is_published_on_this_host_only_unless_asked():
    """Plain HTTP: published on 127.0.0.1 (a reverse proxy with TLS in front, docs/deploy.md)
    unless MG_HTTP_BIND says otherwise; the same in the real rig's file."""
    for path, env in ((COMPOSE, {}), (RIG_COMPOSE, {"MG_RIG_FILE": str(ROOT / "rigs" / "default.toml")})):
        env = {"MG_TOKEN": "x", **env}
        daemon = _parse_compose(path, env)["services"]["daemon"]
        assert published_ports(daemon) == [("127.0.0.1", "8000", "8000")], path.name
        daemon = _parse_compose(path, {**env, "MG_HTTP_BIND": "0.0.0.0", "MG_HTTP_PORT": "8080"})["services"]["daemon"]
        assert published_ports(daemon) == [("0.0.0.0", "8080", "8000")], path.name


# --- the real rig: docker-compose.rig.yml ---------------------------------------------------------
def rig_problems(path: Path = RIG_COMPOSE, env: dict[str, str] | None = None, tool: str | None = DOCKER_COMPOSE):
    """What is wrong with the real rig's compose file: the daemon's settings name real
    drivers, and the devices they open are passed to the container, to a user of the groups
    that own them on the host."""
    from acquisition.daemon.settings import SettingsError

    env = (
        {"MG_TOKEN": "test-token-0123456789", "MG_RIG_FILE": str(ROOT / "rigs" / "default.toml")}
        if env is None
        else env
    )
    try:
        config = resolve_compose(path, env, tool)
    except ComposeError as exc:
        return [f"compose file does not resolve: {exc}"]
    services = config.get("services") or {}
    if set(services) != {"daemon", "worker"}:
        return [f"services {sorted(services)}, expected the daemon and the worker (no simulated arm)"]
    problems = []
    argv = {name: service_argv(svc) for name, svc in services.items()}
    for name, args in argv.items():
        try:
            parse_command_line(args)
        except USAGE_ERRORS as exc:
            problems.append(f"{name}: {shlex.join(args)}: {exc.format_message()}")
    base = _parse_compose(COMPOSE, {"MG_TOKEN": "x"})["services"]["daemon"]
    for name, svc in services.items():
        if svc.get("image") != base["image"]:
            problems.append(f"{name}: image {svc.get('image')}, not docker-compose.yml's {base['image']}")
        mounts = [str(v) if isinstance(v, str) else f"{v.get('source')}:{v.get('target')}" for v in svc["volumes"]]
        if not any(m.startswith("mg-data:/data") for m in mounts):
            problems.append(f"{name}: /data is not the mg-data volume ({mounts})")
    daemon = services["daemon"]
    if (daemon.get("depends_on") or {}) or (services["worker"].get("depends_on") or {}).get("daemon") != {
        "condition": "service_healthy"
    }:
        problems.append("the worker waits for a healthy daemon, the daemon for nothing")
    if _healthcheck_code(daemon) != _healthcheck_code(base):
        problems.append("daemon: not docker-compose.yml's healthcheck")
    try:
        settings = daemon_settings(daemon, argv["daemon"])
    except (SettingsError, ValueError) as exc:
        return [*problems, f"daemon: its configuration is refused: {exc}"]
    mounts = [str(v) if isinstance(v, str) else f"{v.get('source')}:{v.get('target')}" for v in daemon["volumes"]]
    targets = {m.split(":")[1] for m in mounts}
    devices = {str(d).split(":")[1] for d in daemon.get("devices") or []}
    if str(settings.rig) not in targets:
        problems.append(f"daemon: its rig {settings.rig} is not mounted ({mounts})")
    if settings.camera.kind != "gphoto2":
        problems.append(f"daemon: camera {settings.camera.kind}, not the real camera (gphoto2)")
    elif "/dev/bus/usb" not in targets | devices or "c 189:* rmw" not in (daemon.get("device_cgroup_rules") or []):
        problems.append("daemon: the USB bus (/dev/bus/usb, character major 189) is not passed to the camera")
    if settings.arm.kind not in ("serial", "modbus-rtu"):
        problems.append(f"daemon: arm {settings.arm.kind}, not a serial arm")
    elif settings.arm.serial_port not in devices:
        problems.append(f"daemon: the arm's serial port {settings.arm.serial_port} is not among the devices {devices}")
    # The host's plugdev and dialout (Debian's numbers by default), which own the device nodes.
    if {str(g) for g in daemon.get("group_add") or []} != {"46", "20"}:
        problems.append(f"daemon: group_add {daemon.get('group_add')}, not the host's plugdev (46) and dialout (20)")
    return problems


@pytest.mark.parametrize("tool", ["docker-compose", "parser"])
def test_the_real_rig_file_passes_the_devices_to_the_real_drivers(tool):
    if tool == "docker-compose" and DOCKER_COMPOSE is None:
        _without_docker_compose("the rig file is checked by the parser alone")
    assert rig_problems(tool=DOCKER_COMPOSE if tool == "docker-compose" else None) == []
    # The rig description is the lab's own: no default.
    env = {"MG_TOKEN": "x"}
    assert rig_problems(env=env, tool=None) == [
        f'compose file does not resolve: Missing mandatory value for "compose.services.daemon.volumes": '
        f"{RIG_FILE_MESSAGE}"
    ]
    if tool == "docker-compose":
        assert RIG_FILE_MESSAGE in rig_problems(env=env)[0]


RIG_PLANTED = [
    ("MG_CAMERA__KIND: gphoto2", "MG_CAMERA__KIND: simulated"),
    ('      - "c 189:* rmw"', '      - "c 188:* rmw"'),
    ("MG_ARM__SERIAL_PORT: ${MG_ARM_SERIAL_DEVICE:-/dev/ttyUSB0}", "MG_ARM__SERIAL_PORT: /dev/ttyACM0"),
    ('      - "${MG_DIALOUT_GID:-20}"\n', ""),
    ("MG_RIG: /config/rig.toml", "MG_RIG: /config/my-rig.toml"),
    ("MG_ARM__KIND: serial", "MG_ARM__KIND: modbus-tcp"),
]


@pytest.mark.parametrize(("old", "new"), RIG_PLANTED, ids=[new or f"without {old.strip()}" for old, new in RIG_PLANTED])
def test_a_planted_mistake_in_the_rig_file_is_found(tmp_path, old, new):
    text = RIG_COMPOSE.read_text()
    assert text.count(old) == 1, f"the rig file changed: update the planted mistake {old!r}"
    broken = tmp_path / "docker-compose.rig.yml"
    broken.write_text(text.replace(old, new))
    shutil.copy(COMPOSE, tmp_path / "docker-compose.yml")
    assert rig_problems(broken, tool=None), f"planting {new!r} went unnoticed"


# --- the Dockerfile -------------------------------------------------------------------------------
def _shell_commands(script: str) -> list[list[str]]:
    """The simple commands of a RUN line, split at ``&&``, ``||``, ``;`` and ``|`` outside quotes."""
    lexer = shlex.shlex(script, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    commands: list[list[str]] = [[]]
    for token in lexer:
        if token in ("&&", "||", ";", "|"):
            commands.append([])
        else:
            commands[-1].append(token)
    return [c for c in commands if c]


def test_the_dockerfile_installs_this_project_as_a_user_with_data_on_a_volume():
    instructions = dockerfile_instructions()
    keywords = [k for k, _ in instructions]
    assert instructions[0] == ("FROM", "python:3.11-slim-bookworm")
    workdir = next(args for k, args in instructions if k == "WORKDIR")
    copied_before = set()
    installs_project = False
    for keyword, args in instructions:
        if keyword == "COPY":
            copied_before.update(shlex.split(args)[:-1])
        if keyword == "RUN" and "pip install" in args:
            for words in _shell_commands(args):
                if words[:2] == ["pip", "install"] and {".", workdir, "-e."} & set(words[2:]):
                    installs_project = True
                    assert {"pyproject.toml", "acquisition", "processing", "drivers", "sim_devices"} <= copied_before, (
                        copied_before
                    )
    assert installs_project, "no `pip install .` (or -e .) of the project after copying it"
    user = [args for k, args in instructions if k == "USER"]
    assert user and user[-1] not in ("root", "0"), user
    assert keywords.index("USER") > max(
        i for i, k in enumerate(keywords) if k == "RUN" and "pip install" in instructions[i][1]
    )
    assert any(k == "VOLUME" and "/data" in args for k, args in instructions)
    assert any(k == "RUN" and "chown" in args and "/data" in args for k, args in instructions), (
        "/data is not writable by the user"
    )


def _pip_installs() -> list[list[str]]:
    return [
        words
        for keyword, args in dockerfile_instructions()
        if keyword == "RUN"
        for words in _shell_commands(args)
        if words[:2] == ["pip", "install"]
    ]


def test_the_image_installs_the_gphoto2_extra_at_the_pinned_versions_for_a_user_of_the_device_groups():
    """Every pip install that resolves dependencies takes constraints.txt, copied before it; the
    requirements the Dockerfile's own snippet lists (run here on pyproject.toml) are the
    project's and its gphoto2 extra's; Debian's libgphoto2 and gphoto2 tool are installed; the
    user is in plugdev and dialout."""
    import tomllib

    instructions = dockerfile_instructions()
    copies = [i for i, (k, args) in enumerate(instructions) if k == "COPY" and "constraints.txt" in shlex.split(args)]
    assert copies, "constraints.txt is not copied into the image"
    resolving = [words for words in _pip_installs() if "--no-deps" not in words]
    assert resolving
    for words in resolving:
        assert "-c" in words and words[words.index("-c") + 1] == "constraints.txt", words
    # The requirement list, from the Dockerfile's snippet itself.
    (snippet,) = [
        words[2]
        for keyword, args in instructions
        if keyword == "RUN"
        for words in _shell_commands(args)
        if words[:2] == ["python", "-c"] and "pyproject.toml" in words[2]
    ]
    listed = subprocess.run([sys.executable, "-c", snippet], capture_output=True, text=True, cwd=ROOT, check=True)
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    wanted = project["dependencies"] + project["optional-dependencies"]["gphoto2"]
    assert listed.stdout.split("\n")[: len(wanted)] == wanted
    assert any(r.startswith("gphoto2") for r in listed.stdout.split())
    apt = [
        w for k, args in instructions if k == "RUN" for w in _shell_commands(args) if w[:2] == ["apt-get", "install"]
    ]
    assert apt and {"libgphoto2-6", "gphoto2"} <= set(apt[0]), apt
    (useradd,) = [w for k, args in instructions if k == "RUN" for w in _shell_commands(args) if w[:1] == ["useradd"]]
    groups = useradd[useradd.index("--groups") + 1].split(",")
    assert {"plugdev", "dialout"} <= set(groups), useradd


def constraints() -> dict[str, str]:
    """constraints.txt as ``{canonical name: version}``; every line ``NAME==VERSION``, once."""
    from packaging.utils import canonicalize_name

    pins: dict[str, str] = {}
    for number, line in enumerate((ROOT / "constraints.txt").read_text().splitlines(), 1):
        if not line.strip() or line.startswith("#"):
            continue
        match = re.fullmatch(r"([A-Za-z0-9][A-Za-z0-9._-]*)==([A-Za-z0-9.+!_-]+)", line.strip())
        assert match, f"constraints.txt:{number}: {line!r} is not NAME==VERSION"
        name = canonicalize_name(match[1])
        assert name not in pins, f"constraints.txt:{number}: {name} pinned twice"
        pins[name] = match[2]
    return pins


def test_the_constraints_pin_every_dependency_within_pyproject_s_ranges():
    """Every dependency of the image (pyproject's, its extras' that the image takes, the build's
    setuptools and wheel) is pinned with == to a version its range in pyproject.toml allows,
    and the project itself is not (it is installed from the source)."""
    import tomllib

    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    pins = constraints()
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    requirements = [
        Requirement(text)
        for text in pyproject["project"]["dependencies"]
        + pyproject["project"]["optional-dependencies"]["gphoto2"]
        + pyproject["build-system"]["requires"]
    ]
    for requirement in requirements:
        name = canonicalize_name(requirement.name)
        assert name in pins, f"{requirement}: not in constraints.txt"
        assert requirement.specifier.contains(pins[name], prereleases=True), f"{requirement}: pinned {pins[name]}"
    # dask[distributed]: the extra's own package is pinned too.
    assert "distributed" in pins
    assert "mirrorgonio" not in pins and "pip" not in pins


def test_the_dockerfile_copies_what_exists_and_is_not_ignored():
    patterns = dockerignore_patterns()
    sources = []
    for keyword, args in dockerfile_instructions():
        if keyword in ("COPY", "ADD"):
            words = [w for w in shlex.split(args) if not w.startswith("--")]
            sources += words[:-1]
    assert sources
    for source in sources:
        matches = list(ROOT.glob(source))
        assert matches, f"COPY {source}: nothing in the build context"
        for match in matches:
            relative = match.relative_to(ROOT).as_posix()
            assert not dockerignored(relative, patterns), f"COPY {source}: excluded by .dockerignore"
    # What the installed project reads at run time is in the context and copied.
    needed = [
        "drivers/contracts/rigs/default.toml",
        "drivers/profiles/sim_stage.toml",
        "acquisition/daemon/web/index.html",
        "README.md",
    ]
    for relative in needed:
        assert (ROOT / relative).exists(), relative
        assert not dockerignored(relative, patterns), relative
        assert any(relative == s or relative.startswith(s.rstrip("/") + "/") for s in sources), (
            f"{relative} is not copied"
        )
    # The packages setuptools finds are all copied.
    import tomllib

    include = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]["include"]
    for package in {p.rstrip("*") for p in include}:
        assert package in sources, f"package {package} is not copied"


def test_dockerignore_keeps_the_build_context_small():
    patterns = dockerignore_patterns()
    for heavy in (
        ".venv/bin/python",
        ".git/HEAD",
        "data/runs/x.h5",
        "acquisition/__pycache__/cli.cpython-311.pyc",
        "demo-output/a.dng",
    ):
        assert dockerignored(heavy, patterns), heavy
    assert not dockerignored("sim_devices/lights/five-gaussians.toml", patterns)


def test_the_wheel_carries_the_rigs_and_a_plain_install_finds_the_default_rig(tmp_path):
    """The rigs are package data: a wheel holds them, and installed from it (not in place)
    the package loads its default rig from inside site-packages."""
    import zipfile

    built = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path / "dist"), str(ROOT)],
        capture_output=True,
        text=True,
    )
    assert built.returncode == 0, built.stderr
    (wheel,) = (tmp_path / "dist").glob("mirrorgonio-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    shipped = {
        p.relative_to(ROOT).as_posix() for p in (ROOT / "drivers" / "contracts" / "rigs").rglob("*") if p.is_file()
    }
    assert shipped and shipped <= names
    assert "acquisition/daemon/web/index.html" in names and "drivers/profiles/sim_stage.toml" in names
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)  # what a plain install puts in site-packages
    probe = (
        "import drivers.contracts.rig as r, acquisition.demo as d; "
        "print(r.DEFAULT_RIG_PATH.is_relative_to(r'{site}'), r.load_rig().camera.width, d.DEMO_RIG_PATH.is_file())"
    )
    # -S: no .pth files, so not this checkout's in-place install; the dependencies from this
    # environment's site-packages, after the unpacked wheel.
    libraries = next(p for p in sys.path if p.endswith("site-packages"))
    ran = subprocess.run(
        [sys.executable, "-S", "-c", probe.format(site=site)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": f"{site}{os.pathsep}{libraries}"},
    )
    assert ran.returncode == 0, ran.stderr
    assert ran.stdout.split() == ["True", "2000", "True"]
