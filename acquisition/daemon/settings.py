"""The daemon's configuration: ``daemon.toml`` overlaid by ``MG_*`` environment variables.

With no file at all the daemon runs the simulated rig: the simulated stage served over
Modbus TCP on loopback and driven through the real :class:`~drivers.modbus_arm.ModbusArm`,
and the simulated camera. A file names real devices instead (``docs/daemon.md``).
"""

from __future__ import annotations

import ipaddress
import json
import socket
from pathlib import Path
from typing import Annotated, Literal
from urllib.parse import urlsplit

from pydantic import ConfigDict, Field, PositiveFloat, SecretStr, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from acquisition.daemon.catalog import DEFAULT_RIG
from acquisition.daemon.catalog.backends import POSTGRESQL_SCHEMES, SQLITE_PREFIX, redact_url
from acquisition.daemon.catalog.database import RIG_NAME_PATTERN
from drivers.camera import LONGEST_EXPOSURE_S, SHORTEST_EXPOSURE_S
from drivers.config_files import ConfigModel, read_toml, validate_model
from drivers.contracts.rig import DEFAULT_RIG_PATH
from drivers.modbus_profile import SIM_STAGE_PROFILE

#: Register-map profiles shipped with the drivers, named by ``arm.profile = "NAME"``.
SHIPPED_PROFILES_DIR = SIM_STAGE_PROFILE.parent


class SettingsError(ValueError):
    """An unreadable or impossible daemon configuration (one line: file, field, cause)."""


class _Section(ConfigModel):
    """A section of the settings. Each settings object has its own sections (``default_factory``):
    they are changed in place (relative paths resolved, tests' overrides), which must not reach
    another settings object."""

    model_config = ConfigDict(frozen=False)  # loading resolves relative paths in place


#: The longest wait or exposure: a day (threading refuses waits past ~9e9 s).
DAY_S = 86400.0
Seconds = Annotated[float, Field(gt=0, le=DAY_S)]
#: An exposure time, s: one a camera can take and a raw file can hold (``drivers.camera``).
Exposure = Annotated[float, Field(ge=SHORTEST_EXPOSURE_S, le=LONGEST_EXPOSURE_S, allow_inf_nan=False)]
#: A bracket: 1 to 16 exposures.
BRACKET_MIN_LENGTH = 1
BRACKET_MAX_LENGTH = 16
#: A simulated stage's speed or acceleration: ``inf`` makes that part of a move instantaneous.
StageRate = Annotated[float, Field(gt=0, allow_inf_nan=True)]


class SimulatedStageSettings(_Section):
    """Mechanics of the simulated stage (``speed_m_s = inf`` makes moves instantaneous)."""

    speed_m_s: StageRate = 0.05
    accel_m_s2: StageRate = 0.5
    angular_speed_rad_s: StageRate = 1.0


class ArmSettings(_Section):
    """Which arm, and how to reach it.

    ``simulated`` starts the simulated stage's Modbus TCP server on loopback (on
    ``port``, 0 for any free port) and drives it through ``ModbusArm``. ``profile`` is
    a register-map TOML file, or the bare name of one shipped with the drivers
    (``sim_stage``: the simulated arm of ``mirrorgonio simulate arm``).
    """

    kind: Literal["simulated", "modbus-tcp", "modbus-rtu", "serial"] = "simulated"
    profile: Path | None = None
    host: str = "127.0.0.1"
    port: int = Field(default=0, ge=0, le=65535)
    serial_port: str | None = None
    baudrate: int | None = None
    timeout_s: Seconds = 1.0
    retries: int = Field(default=3, ge=0)
    move_timeout_s: Seconds = 120.0
    simulated: SimulatedStageSettings = Field(default_factory=SimulatedStageSettings)

    @field_validator("profile")
    @classmethod
    def _shipped_profile(cls, value: Path | None) -> Path | None:
        """A bare name (no folder, no suffix) of a shipped profile means that file."""
        if value is not None and len(value.parts) == 1 and not value.suffix:
            shipped = SHIPPED_PROFILES_DIR / f"{value}.toml"
            if shipped.is_file():
                return shipped
        return value


class SimulatedCameraSettings(_Section):
    """The simulated camera: the truth light, noise, diffraction, the time a capture takes, and
    the radiance of the simulated room while its lights are on (the simulated camera's
    ``ROOM_RADIANCE`` when not given)."""

    truth: str | None = None
    noise: bool | None = None
    diffraction: bool | None = None
    latency_s: float = Field(default=0.0, ge=0.0, le=DAY_S)
    room_radiance: float | None = Field(default=None, ge=0.0, le=1e9)


class CameraSettings(_Section):
    """Which camera: ``simulated``, ``gphoto2`` (tethered over USB) or ``folder``."""

    kind: Literal["simulated", "gphoto2", "folder"] = "simulated"
    folder: Path | None = None
    gphoto2_port: str | None = None
    gphoto2_model: str | None = None
    capture_timeout_s: Seconds = 30.0
    keep_raw_files: bool = False
    simulated: SimulatedCameraSettings = Field(default_factory=SimulatedCameraSettings)


#: The shortest API token ``serve`` accepts (after stripping whitespace).
MIN_TOKEN_LENGTH = 16
#: The default limit of a request's body: the largest request the API takes (``POST /runs``
#: with 10 000 poses written at full float precision) is about 2 MB.
DEFAULT_MAX_BODY_BYTES = 4 * 1024 * 1024
#: The loopback names every daemon answers to, on any port (an SSH tunnel, a published port):
#: only a page the browser has from this machine names them (a rebound name is the page's own).
LOOPBACK_HOSTS = ("localhost", "127.0.0.1", "[::1]")


def split_host(value: str) -> tuple[str, int | None]:
    """``NAME``, ``NAME:PORT``, ``[IPV6]`` or ``[IPV6]:PORT`` (a Host header, or the network
    location of an Origin) as the lower-case name (an IPv6 address in brackets, a name without
    its final dot) and the port (None when not given). ``ValueError`` for anything else."""
    text = value.strip().lower()
    if text.startswith("["):
        inside, bracket, rest = text[1:].partition("]")
        try:
            ipaddress.IPv6Address(inside)
        except ValueError:
            raise ValueError(f"{value!r} is not HOST or HOST:PORT") from None
        if not bracket or (rest and not rest.startswith(":")):
            raise ValueError(f"{value!r} is not HOST or HOST:PORT")
        name, port_text = f"[{inside}]", (rest[1:] if rest else None)
    else:
        name, colon, after = text.partition(":")
        name, port_text = name.removesuffix("."), (after if colon else None)
        if not name or not name.isascii() or not all(c.isalnum() or c in "-._" for c in name):
            raise ValueError(f"{value!r} is not HOST or HOST:PORT")
    if port_text is None:
        return name, None
    if not port_text.isascii() or not port_text.isdigit():
        raise ValueError(f"{value!r} is not HOST or HOST:PORT")
    if not 0 < int(port_text) <= 65535:
        raise ValueError(f"{value!r}: the port is not a number from 1 to 65535")
    return name, int(port_text)


#: The default ambient bracket of a run's calibration frames: room light, seconds.
DEFAULT_AMBIENT_EXPOSURES_S = (0.01, 0.04, 0.16)


class LightSettings(_Section):
    """The light switch a run's calibration frames need (``docs/daemon.md``, "Calibration frames").

    ``kind``: ``simulated`` (the simulated world's lights; the default with the simulated
    camera), ``manual`` (the run pauses and tells the operator what to switch; the default
    with any other camera) or ``none`` (runs take no calibration frames).
    ``room_can_be_dark`` False: dark frames are taken with the room lit, at
    ``dark_exposure_s`` (the camera's shortest exposure), for the black level only.
    ``ambient_exposures_s``: the ambient bracket of a run request that does not give one.
    """

    kind: Literal["simulated", "manual", "none"] | None = None
    room_can_be_dark: bool = True
    dark_exposure_s: Exposure = 1e-4
    ambient_exposures_s: list[Exposure] = Field(
        default_factory=lambda: list(DEFAULT_AMBIENT_EXPOSURES_S),
        min_length=BRACKET_MIN_LENGTH,
        max_length=BRACKET_MAX_LENGTH,
    )


class AutoBracketSettings(_Section):
    """The ``auto`` bracket rule (``docs/daemon.md``, "Auto bracketing")."""

    metering_exposure_s: Exposure = 0.001
    saturation_fraction: float = Field(default=0.8, gt=0.0, le=1.0)
    useful_fraction: float = Field(default=1e-3, gt=0.0, lt=1.0)
    target_snr: PositiveFloat = 20.0
    step_ratio: float = Field(default=4.0, gt=1.0)
    max_exposures: int = Field(default=7, ge=1, le=16)
    min_exposure_s: Exposure = SHORTEST_EXPOSURE_S
    max_exposure_s: Exposure = 30.0


class StorageSettings(_Section):
    """The data directory's free space (``docs/daemon.md``, "When the disk fills").

    ``min_free_mb``: ``/health`` is degraded with less free space (default: one position of
    the default bracket, uncompressed, and 1 MB for the run file's records and the catalog).
    ``check_before_run``: refuse (507) a run whose estimated size exceeds the free space,
    unless its request says ``"force": true``. ``compression_ratio``: the stored size of a
    frame over its raw size in that estimate (measured on the demo rig's simulated frames:
    0.40 for the sweep's, 0.39-0.73 for the calibration frames; a real sensor's noise
    compresses less: 1.0 assumes none).
    """

    min_free_mb: float | None = Field(default=None, ge=0.0, le=1e9)
    check_before_run: bool = True
    compression_ratio: float = Field(default=0.75, gt=0.0, le=2.0)


class DaemonSettings(BaseSettings):
    """Everything ``mirrorgonio serve`` needs."""

    model_config = SettingsConfigDict(env_prefix="MG_", env_nested_delimiter="__", extra="forbid", allow_inf_nan=False)

    data_dir: Path = Path("data")
    rig: Path = DEFAULT_RIG_PATH
    rig_name: str = Field(
        default=DEFAULT_RIG,
        pattern=RIG_NAME_PATTERN,
        description="this rig's name in the catalog: its runs, their jobs and its queue carry it (lowercase "
        "letters, digits, '-', '_', '.'); several rigs that share one catalog each need their own",
    )
    catalog: str | None = Field(
        default=None,
        description="the catalog: sqlite:///PATH, or postgresql://USER:PASSWORD@HOST:PORT/DATABASE for a lab "
        "whose rigs and workers share one; default DATA_DIR/catalog.sqlite",
    )
    host: str = "127.0.0.1"
    port: int = Field(default=8000, ge=0, le=65535)
    token: SecretStr | None = Field(
        default=None, description=f"the API token: at least {MIN_TOKEN_LENGTH} characters; none: loopback only"
    )
    token_guards_reads: bool = Field(
        default=True, description="with a token, every endpoint but /health and the page's shell needs it"
    )
    allowed_hosts: Annotated[list[str] | None, NoDecode] = Field(
        default=None,
        description="the Host names (NAME or NAME:PORT, '*' for any) the daemon answers to besides "
        "localhost, 127.0.0.1, [::1] and the listening address",
    )
    max_body_bytes: int = Field(
        default=DEFAULT_MAX_BODY_BYTES, ge=1024, le=1 << 30, description="the largest request body taken"
    )
    max_results_bytes: int = Field(
        default=1 << 34,
        ge=1024,
        description="the largest results archive a worker on another machine may send back (PUT /jobs/{id}/results)",
    )
    public_url: str | None = Field(
        default=None,
        pattern=r"^https?://[^\s/]+(/\S*)?$",
        description="where workers on other machines reach this daemon (http://HOST:PORT), recorded in the "
        "catalog; default http://HOST:PORT of the listening address (the machine's name for 0.0.0.0)",
    )
    device_retries: int = Field(default=2, ge=0, description="retries of a transient device error")
    arm: ArmSettings = Field(default_factory=ArmSettings)
    camera: CameraSettings = Field(default_factory=CameraSettings)
    light: LightSettings = Field(default_factory=LightSettings)
    auto_bracket: AutoBracketSettings = Field(default_factory=AutoBracketSettings)
    storage: StorageSettings = Field(default_factory=StorageSettings)
    default_exposures_s: list[Exposure] = Field(
        default_factory=lambda: [0.0002, 0.001, 0.005], min_length=BRACKET_MIN_LENGTH, max_length=BRACKET_MAX_LENGTH
    )

    @field_validator("token", mode="before")
    @classmethod
    def _long_token(cls, value: object) -> object:
        """Whitespace around the token is dropped (an empty one is no token); a shorter token
        than :data:`MIN_TOKEN_LENGTH` is refused."""
        if value is None:
            return None
        text = (value.get_secret_value() if isinstance(value, SecretStr) else str(value)).strip()
        if not text:
            return None
        if len(text) < MIN_TOKEN_LENGTH:
            raise ValueError(
                f"too short ({len(text)} character{'s' * (len(text) > 1)}): at least {MIN_TOKEN_LENGTH} are needed "
                "(set token in the configuration or MG_TOKEN, e.g. to the output of "
                "`python3 -c 'import secrets; print(secrets.token_hex(16))'`)"
            )
        return text

    @field_validator("catalog")
    @classmethod
    def _catalog_url(cls, value: str | None) -> str | None:
        """An SQLite or PostgreSQL URL; an empty one is the default file."""
        if value is None or not value.strip():
            return None
        text = value.strip()
        scheme = text.split("://", 1)[0].lower() if "://" in text else ""
        if scheme not in ("sqlite", *POSTGRESQL_SCHEMES) or (scheme == "sqlite" and not text.startswith(SQLITE_PREFIX)):
            raise ValueError(
                f"not a catalog URL: {redact_url(text)!r} (sqlite:///PATH or postgresql://USER@HOST/DATABASE)"
            )
        return text

    @field_validator("allowed_hosts", mode="before")
    @classmethod
    def _host_list(cls, value: object) -> object:
        """A list, or (``MG_ALLOWED_HOSTS``) a JSON list or names separated by commas; empty:
        none besides the defaults."""
        if isinstance(value, str):
            text = value.strip()
            if not text:
                return None
            if text.startswith("["):
                try:
                    return json.loads(text)
                except json.JSONDecodeError:
                    raise ValueError(f"not a JSON list of host names: {text!r}") from None
            return [part.strip() for part in text.split(",") if part.strip()]
        return value

    @field_validator("allowed_hosts")
    @classmethod
    def _host_names(cls, value: list[str] | None) -> list[str] | None:
        if value is not None:
            for entry in value:
                if entry.strip() != "*":
                    split_host(entry)
        return value

    def host_allow_list(self) -> list[tuple[str, int | None]]:
        """The hosts requests may name (``Host``, and ``Origin`` of a request that changes
        something), as (name, port or None for any); ``("*", None)`` for any host: the
        loopback names, the listening address on its port, the name workers are told to reach
        it by (:meth:`daemon_url`), and ``allowed_hosts``."""
        hosts: list[tuple[str, int | None]] = [(name, None) for name in LOOPBACK_HOSTS]
        for entry in self.allowed_hosts or []:
            hosts.append(("*", None) if entry.strip() == "*" else split_host(entry))
        bind = self.host.strip().lower()
        name = f"[{bind}]" if ":" in bind and not bind.startswith("[") else bind
        if name not in ("", "0.0.0.0", "[::]", *LOOPBACK_HOSTS):  # a wildcard address is no name
            hosts.append((name, self.port or None))
        told = urlsplit(self.daemon_url())
        if told.hostname:
            hosts.append((told.hostname.lower(), told.port or (443 if told.scheme == "https" else 80)))
        return hosts

    @property
    def catalog_path(self) -> Path:
        """The SQLite catalog's file where no ``catalog`` URL is set."""
        return self.data_dir / "catalog.sqlite"

    @property
    def catalog_url(self) -> str:
        """Where the catalog is: the ``catalog`` URL, else the SQLite file in the data folder."""
        return self.catalog if self.catalog is not None else str(self.catalog_path)

    @property
    def shared_catalog(self) -> bool:
        """The catalog is on a server, shared with other rigs and workers (not a file of this daemon's)."""
        return self.catalog is not None and not self.catalog.startswith(SQLITE_PREFIX)

    def daemon_url(self) -> str:
        """:attr:`public_url`, else the listening address (this machine's name for a wildcard one)."""
        if self.public_url is not None:
            return self.public_url.rstrip("/")
        host = self.host.strip()
        if host in ("", "0.0.0.0", "::", "[::]"):
            host = socket.gethostname()
        elif ":" in host and not host.startswith("["):
            host = f"[{host}]"
        return f"http://{host}:{self.port}"

    @property
    def runs_dir(self) -> Path:
        return self.data_dir / "runs"

    def require_token_off_loopback(self) -> None:
        """``serve`` refuses a non-loopback address without a token."""
        if self.token is not None and self.token.get_secret_value():
            return
        if not is_loopback(self.host):
            raise SettingsError(
                f"host: refusing to listen on {self.host} without a token (set token in the configuration or MG_TOKEN)"
            )


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def load_settings(path: str | Path | None = None, **overrides: object) -> DaemonSettings:
    """Read ``daemon.toml`` (optional); ``MG_*`` variables fill what the file leaves out."""
    data = read_toml(path, "configuration file", SettingsError) if path is not None else {}
    data.update({k: v for k, v in overrides.items() if v is not None})
    source = str(path) if path is not None else "<settings>"
    settings = validate_model(DaemonSettings, data, source, SettingsError)
    if path is not None:
        # Relative paths in the file are relative to the file, not to the working directory.
        base = Path(path).resolve().parent
        for name in ("data_dir", "rig"):
            value = getattr(settings, name)
            if name in data and not Path(value).is_absolute():
                setattr(settings, name, base / value)
        if settings.arm.profile is not None and not settings.arm.profile.is_absolute():
            settings.arm.profile = base / settings.arm.profile
        if settings.camera.folder is not None and not settings.camera.folder.is_absolute():
            settings.camera.folder = base / settings.camera.folder
    return settings
