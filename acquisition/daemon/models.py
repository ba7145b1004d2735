"""Request and response models of the daemon's REST API (with OpenAPI examples)."""

from __future__ import annotations

from collections import Counter
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PositiveFloat,
    StrictBool,
    create_model,
    field_validator,
    model_validator,
)

from acquisition.daemon.catalog import DEFAULT_RIG
from acquisition.daemon.settings import BRACKET_MAX_LENGTH, BRACKET_MIN_LENGTH, DEFAULT_AMBIENT_EXPOSURES_S, Exposure
from drivers.contracts.rig import MAX_POSITIONS, PoseSpec
from processing import Option, ProcessingOptions, StepsError, declared_options, resolve_steps

# --- requests ------------------------------------------------------------------------------
# A request's bracket must name its ``mode``: it is the discriminator of ``Bracket``. The
# defaults serve Python callers only, so the JSON schemas list ``mode`` as required.
# Every value is checked here, when the request is made (a 422 naming the field), and the
# bounds are in the schema: an exposure is one the camera can take and the raw and run files
# can hold (``drivers.camera.SHORTEST_EXPOSURE_S`` to ``LONGEST_EXPOSURE_S``), every number
# is finite.
_EXPOSURES_DOC = "seconds, each from 1e-05 (1/100000 s) to 3600"


class FixedBracket(BaseModel):
    """A fixed list of exposure times, taken at every position in this order."""

    model_config = ConfigDict(
        extra="forbid",
        allow_inf_nan=False,
        json_schema_extra={
            "required": ["mode", "exposures_s"],
            "examples": [{"mode": "fixed", "exposures_s": [0.0002, 0.001, 0.005]}],
        },
    )
    mode: Literal["fixed"] = "fixed"
    exposures_s: list[Exposure] = Field(
        min_length=BRACKET_MIN_LENGTH, max_length=BRACKET_MAX_LENGTH, description=_EXPOSURES_DOC
    )


class AutoBracket(BaseModel):
    """Exposures chosen per position from a metering frame (``docs/daemon.md``)."""

    model_config = ConfigDict(
        extra="forbid",
        allow_inf_nan=False,
        json_schema_extra={"required": ["mode"], "examples": [{"mode": "auto", "target_snr": 20}]},
    )
    mode: Literal["auto"] = "auto"
    target_snr: PositiveFloat | None = Field(default=None, le=1000.0)
    useful_fraction: float | None = Field(default=None, gt=0.0, lt=1.0)
    max_exposures: int | None = Field(default=None, ge=1, le=16)

    def overrides(self) -> dict:
        return {k: v for k, v in self.model_dump(exclude={"mode"}).items() if v is not None}


Bracket = Annotated[FixedBracket | AutoBracket, Field(discriminator="mode")]


class CalibrationOptions(BaseModel):
    """The run's calibration frames, taken with the measured light off (``docs/daemon.md``)."""

    model_config = ConfigDict(
        extra="forbid",
        allow_inf_nan=False,
        json_schema_extra={
            "examples": [{"before": True, "after": True, "ambient_exposures_s": [0.01, 0.04, 0.16], "dark": True}]
        },
    )
    before: StrictBool = Field(default=True, description="take calibration frames before the first position")
    after: StrictBool = Field(default=False, description="and after the last position too (to see drift)")
    ambient_exposures_s: list[Exposure] = Field(
        default_factory=lambda: list(DEFAULT_AMBIENT_EXPOSURES_S),
        min_length=BRACKET_MIN_LENGTH,
        max_length=BRACKET_MAX_LENGTH,
        description=f"the bracket of the ambient frames (the light off, the room lit; {_EXPOSURES_DOC}); "
        "default: the daemon's",
    )
    dark: StrictBool = Field(default=True, description="take dark frames too (the light off, the room dark)")


class RunRequest(BaseModel):
    """Start a run: a schedule preset × a bracket × metadata."""

    model_config = ConfigDict(
        extra="forbid",
        allow_inf_nan=False,
        json_schema_extra={
            "examples": [
                {
                    "preset": "light-sweep",
                    "bracket": {"mode": "fixed", "exposures_s": [0.0002, 0.001, 0.005]},
                    "operator": "A. Technician",
                    "light_source": "LED flashlight #3",
                    "notes": "first sweep after cleaning the ball",
                }
            ]
        },
    )
    preset: Literal["light-sweep", "object-arc", "object-dome", "raster", "poses"] = "light-sweep"
    poses: list[PoseSpec] | None = Field(default=None, max_length=10000, description="light poses, for preset 'poses'")
    count: int | None = Field(default=None, ge=1, le=MAX_POSITIONS, description="take only the first COUNT positions")
    bracket: Bracket = Field(default_factory=lambda: FixedBracket(exposures_s=[0.0002, 0.001, 0.005]))
    calibration: CalibrationOptions = Field(
        default_factory=lambda: CalibrationOptions(),
        description="calibration frames with the light off, before (and after) the sweep",
    )
    force: StrictBool = Field(
        default=False, description="start even if the run's estimated size exceeds the free space (else 507)"
    )
    operator: str = Field(default="", max_length=200)
    light_source: str = Field(default="", max_length=200)
    notes: str = Field(default="", max_length=4000)
    light_results: str | None = Field(
        default=None,
        max_length=4096,
        description="object runs: the processed light run's model (RUN.light.json) that lights the object",
    )

    @model_validator(mode="after")
    def _poses_with_their_preset(self):
        if self.preset == "poses" and not self.poses:
            raise ValueError("poses: preset 'poses' needs a list of poses")
        if self.preset != "poses" and self.poses:
            raise ValueError(f"poses: only for preset 'poses', not '{self.preset}'")
        return self


def _job_field(option: Option) -> tuple[Any, Any]:
    """The job request's field of a declared option: its type, bounds, default and description.

    A boolean is strict (``true``, ``false``); a path is the text of one on the worker's machine;
    a number is finite; an option without a default may be null.
    """
    kind = {bool: StrictBool, Path: str}.get(option.kind, option.kind)
    bounds = {
        "gt" if option.exclusive_minimum else "ge": option.minimum,
        "lt" if option.exclusive_maximum else "le": option.maximum,
        "min_length": option.min_length,
        "max_length": option.max_length,
        "pattern": option.pattern,
        "allow_inf_nan": False if kind is float else None,
    }
    bounds = {key: value for key, value in bounds.items() if value is not None}
    if bounds:
        kind = Annotated[kind, Field(**bounds)]  # type: ignore[call-overload]  # pydantic's overloads take no **dict
    if option.given_default is None:
        kind = kind | None
    return kind, Field(default=option.given_default, description=option.help_as(lambda public: public))


class _JobRequest(BaseModel):
    """Process a run: which steps, and how (``docs/daemon.md``, "Worker").

    The processing's options are those of :mod:`processing.options`, as it declares them
    (:data:`JOB_OPTIONS`); the job's own option is ``partial``.
    """

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={"examples": [{"steps": "hdr,sources"}, {"steps": "hdr,sources", "partial": True}]},
    )
    partial: StrictBool = Field(
        default=False,
        description="process the positions complete now even while the run is "
        "being acquired (otherwise the job waits for the run to end)",
    )

    @field_validator("steps", check_fields=False)
    @classmethod
    def _each_step_once(cls, steps: str) -> str:
        names = steps.split(",")
        if len(set(names)) != len(names):
            raise ValueError("names a step twice")
        try:
            resolve_steps(steps)
        except StepsError as exc:
            raise ValueError(str(exc)) from None
        return steps

    @model_validator(mode="after")
    def _one_photometric_scale(self):
        if getattr(self, "lamp_lumens", None) is not None and getattr(self, "candela_per_unit", None) is not None:
            raise ValueError("lamp_lumens, candela_per_unit: give one (relative scaled to a lamp flux, or candela)")
        if getattr(self, "photometric_calibration", None) is not None and (
            getattr(self, "lamp_lumens", None) is not None or getattr(self, "candela_per_unit", None) is not None
        ):
            raise ValueError("photometric_calibration: not with lamp_lumens or candela_per_unit (one scale)")
        return self

    def options(self) -> dict:
        """The job's options as the catalog stores them (only those not at their default)."""
        return self.model_dump(mode="json", exclude={"steps"}, exclude_defaults=True)


#: The processing's options a job takes, as ``processing.options`` declares them.
JOB_OPTIONS = tuple(option for option in declared_options(ProcessingOptions) if option.job)
JobRequest = create_model(  # type: ignore[call-overload]  # its overloads take no **fields of a built dict
    "JobRequest",
    __base__=_JobRequest,
    __doc__=_JobRequest.__doc__,
    __module__=__name__,
    **{option.public: _job_field(option) for option in JOB_OPTIONS},
)


#: The instant the API document's examples start at (its run's id says it too).
_EXAMPLE_START = datetime(2026, 11, 21, 13, 45, 1, tzinfo=UTC)


def _example_time(seconds: float) -> str:
    """An example timestamp, ``seconds`` after :data:`_EXAMPLE_START`, as the API writes them."""
    return (_EXAMPLE_START + timedelta(seconds=seconds)).isoformat()


# --- responses -----------------------------------------------------------------------------
class RunStatus(BaseModel):
    """Everything about a run in one answer."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "id": "run-20261121-134501-3f2a",
                    "state": "running",
                    "preset": "light-sweep",
                    "n_positions": 66,
                    "positions_done": 12,
                    "percent_done": 18.2,
                    "current_position": 12,
                    "eta_s": 310.0,
                    "last_error": None,
                    "created_utc": _example_time(0),
                    "started_utc": _example_time(1),
                    "finished_utc": None,
                    "exposures_per_position": 3,
                    "file_url": "/runs/run-20261121-134501-3f2a/file",
                    "step": "sweep: position 13 of 66",
                }
            ]
        }
    )
    id: str
    rig: str = Field(default=DEFAULT_RIG, description="the rig that took (or takes) the run")
    read_only: bool = Field(
        default=False, description="another rig's run: this daemon shows it, and only its own daemon changes it"
    )
    state: str
    preset: str | None
    n_positions: int
    positions_done: int
    percent_done: float
    current_position: int | None
    eta_s: float | None
    last_error: str | None
    created_utc: datetime
    started_utc: datetime | None
    finished_utc: datetime | None
    exposures_per_position: int | None
    file_url: str
    step: str | None = Field(
        default=None,
        description="what the run is doing now (the calibration frames, the sweep), or what the operator must "
        "do before resuming it; None when the run is not in progress",
    )
    queue_position: int | None = Field(
        default=None,
        description="a queued run's place in the queue, from 1 (the next to start); None once it has left it",
    )


class QueueStatus(BaseModel):
    """The queue of runs: the runs waiting, the next to start first, and whether it is held."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "held": "run run-20261121-134501-3f2a failed: arm: move_to: alarm 0x0010: overtravel",
                    "held_utc": _example_time(600),
                    "runs": [],
                }
            ]
        }
    )
    held: str | None = Field(
        description="why no queued run starts by itself until the queue is started again (a run failed or "
        "was aborted, a queued run cannot start, the daemon restarted); None while the queue runs on"
    )
    held_utc: datetime | None = Field(default=None, description="since when it is held")
    runs: list[RunStatus] = Field(description="the queued runs, in the order they start")


class QueueOrder(BaseModel):
    """A new order of the queue (``PUT /queue``)."""

    model_config = ConfigDict(
        extra="forbid", json_schema_extra={"examples": [{"run_ids": ["run-20261121-140210-77c1"]}]}
    )
    run_ids: list[Annotated[str, Field(min_length=1, max_length=100)]] = Field(
        max_length=10_000,
        description="queued runs, in the order they are to start; the queued runs not named follow them, in "
        "their order. Each once; a run that is not queued (it has started, or was removed) is a 409",
    )

    @field_validator("run_ids")
    @classmethod
    def _each_once(cls, run_ids: list[str]) -> list[str]:
        twice = sorted(run_id for run_id, n in Counter(run_ids).items() if n > 1)
        if twice:
            raise ValueError(f"named more than once: {', '.join(twice)}")
        return run_ids


class JobStatus(BaseModel):
    """A processing job: its state and, once complete, where to download its results."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "id": "job-20261121-140000-aa01",
                    "run_id": "run-20261121-134501-3f2a",
                    "state": "complete",
                    "steps": "hdr,sources",
                    "options": {},
                    "progress": 1.0,
                    "step": None,
                    "error": None,
                    "message": "66 of 66 positions in 21.4 s on local Dask cluster: 2 worker processes x 1 thread",
                    "result_dir": "/srv/mirrorgonio/runs",
                    "claimed_by": "lab-pc-4242",
                    "heartbeat_utc": _example_time(924),
                    "created_utc": _example_time(899),
                    "updated_utc": _example_time(925),
                    "artifacts": {
                        "report": "/jobs/job-20261121-140000-aa01/artifacts/report",
                        "ies": "/jobs/job-20261121-140000-aa01/artifacts/ies",
                        "tm25": "/jobs/job-20261121-140000-aa01/artifacts/tm25",
                    },
                }
            ]
        }
    )
    id: str
    run_id: str
    rig: str = Field(default=DEFAULT_RIG, description="the rig of the job's run")
    state: str
    steps: str
    options: dict = Field(default_factory=dict)
    progress: float
    step: str | None = Field(
        default=None,
        description="the processing step a running job is in, one of checksums, noise, hdr, calibration, layout, "
        "camera, estimate, fits, exports, report (in that order; message says how far it is); a failed job keeps "
        "the step it failed in; None before the first heartbeat and once complete",
    )
    error: str | None
    message: str | None = Field(
        default=None, description="why a queued job waits, how far a running job's step is, what a finished job did"
    )
    result_dir: str | None
    claimed_by: str | None = None
    heartbeat_utc: datetime | None = None
    created_utc: datetime
    updated_utc: datetime
    artifacts: dict[str, str] = Field(default_factory=dict, description="download URL of each result file, by kind")


class ArmState(BaseModel):
    connected: bool
    identity: str
    position: dict[str, float] | None = Field(
        default=None, description="read-back pose: x, y, z in m; rx, ry, rz in degrees"
    )
    moving: bool | None = None
    in_position: bool | None = None
    alarm_code: int | None = None
    alarm_text: str | None = None
    error: str | None = None


class CameraState(BaseModel):
    connected: bool
    identity: str
    error: str | None = None


class DevicesStatus(BaseModel):
    arm: ArmState
    camera: CameraState


class ResumeRequest(BaseModel):
    """Options of a resume (the body is optional)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{"force": True}]})
    force: StrictBool = Field(
        default=False, description="resume even if what the run has left exceeds the free space (else 507)"
    )


class Health(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {"status": "degraded", "reasons": ["arm: connection refused"], "version": "0.1.0", "active_run": None}
            ]
        }
    )
    status: Literal["ok", "degraded"]
    reasons: list[str]
    version: str
    active_run: str | None
    rig: str = Field(default=DEFAULT_RIG, description="this daemon's rig (its name in the catalog)")
    queued_runs: int = Field(default=0, description="runs waiting in the queue")
    queue_held: str | None = Field(default=None, description="why the queue is held (GET /queue); None if it is not")


class Problem(BaseModel):
    """The body of every error answer."""

    model_config = ConfigDict(json_schema_extra={"examples": [{"detail": "run run-1 is already active on this rig"}]})
    detail: str | list


# --- manual control: the alignment preview, test shots, jog and home ------------------------
class ChannelHistogram(BaseModel):
    below: int = Field(description="photosites less than 1 DN above black")
    counts: list[int] = Field(description="photosites in each bin of `edges_dn`")


class Histogram(BaseModel):
    edges_dn: list[float] = Field(description="bin edges, DN above black, log-spaced from 1 to the white level")
    channels: dict[str, ChannelHistogram] = Field(description="by CFA colour: R, G, B")


class FrameSummary(BaseModel):
    """The latest frame beside its alignment view (``GET /preview/frame.png``)."""

    serial: int = Field(description="counts the frames shown: a new one means a new view")
    run_id: str | None = Field(description="the run that took it; None: a test shot")
    width: int
    height: int
    exposure_s: float
    captured_utc: str
    camera_id: str
    black_level_dn: float
    white_level_dn: int
    peak_dn: float = Field(description="the brightest photosite, DN above black")
    saturated_pixels: int = Field(description="photosites at 98 % of the range above black or more")
    saturated_share: float
    scale: dict[str, str | float] = Field(description="the view's grey scale: log10 of DN above black")
    histogram: Histogram
    ball_outline_px: list[list[float]] | None = Field(
        description="the ball's expected outline, (col, row) pixel centres, from the rig's camera and ball"
    )


class ShotRequest(BaseModel):
    """One bracket at the arm's current pose; nothing is stored in a run."""

    model_config = ConfigDict(
        extra="forbid", allow_inf_nan=False, json_schema_extra={"examples": [{"exposures_s": [0.001, 0.01]}]}
    )
    exposures_s: list[Exposure] | None = Field(
        default=None,
        min_length=BRACKET_MIN_LENGTH,
        max_length=BRACKET_MAX_LENGTH,
        description=f"{_EXPOSURES_DOC}; default: the daemon's default bracket",
    )


class ShotFrame(BaseModel):
    exposure_s: float
    peak_dn: float
    saturated_pixels: int
    saturated_share: float


class ShotResult(BaseModel):
    frames: list[ShotFrame]
    serial: int = Field(description="the preview's serial of the last frame (it shows that one)")


JOG_LIMIT = 100.0


class JogRequest(BaseModel):
    """A relative move of one axis of the arm's tool pose (the arm's own frame)."""

    model_config = ConfigDict(
        extra="forbid", allow_inf_nan=False, json_schema_extra={"examples": [{"axis": "z", "step": -5.0}]}
    )
    axis: Literal["x", "y", "z", "rx", "ry", "rz"]
    step: float = Field(
        ge=-JOG_LIMIT, le=JOG_LIMIT, description="millimetres for x, y, z; degrees for rx, ry, rz (at most 100)"
    )


class ArmMove(BaseModel):
    """Where the arm is after a jog or homing."""

    position: dict[str, float] = Field(description="read-back pose: x, y, z in m; rx, ry, rz in degrees")
    moved: str = Field(description="what was done, in one line")


class LogLine(BaseModel):
    seq: int = Field(description="increasing; ask for lines `after` the last one seen")
    time_utc: str
    level: str
    logger: str
    message: str


class PhotometrySummary(BaseModel):
    """The whole light's photometric summary, as the job's light model holds it
    (``photometry``; docs/light-model.md): what a lighting engineer reads first."""

    extrapolation: str = Field(description="what the light files hold beyond the measured θ: fitted, or none")
    intensity_units: str
    flux_units: str
    total_flux: float
    flux_beyond_measured_percent: float = Field(description="the share of the flux beyond the θ the sweep measured")
    measured_theta_max_deg: float
    peak_intensity: float
    peak_gamma_deg: float
    peak_c_deg: float
    beam_angle_deg: dict[str, float] = Field(description="where I ≥ 50 % of the peak, per C-plane pair")
    field_angle_deg: dict[str, float] = Field(description="where I ≥ 10 % of the peak, per C-plane pair")
    beam_angle_beyond_measured: bool
    field_angle_beyond_measured: bool
    near_field_distance_m: float | None = None
    near_field_difference_percent: float | None = Field(
        None, description="the array of sources against one point source: largest illuminance difference, % of peak"
    )


class ResultsReceived(BaseModel):
    """Where the daemon keeps the results a worker on another machine sent."""

    result_dir: str = Field(description="the folder of the results: the run file's")
    files: dict[str, str] = Field(description="each file's path in the archive -> its path on the daemon's disk")


class ReportFigure(BaseModel):
    """A figure of a job's report."""

    index: int
    alt: str
    caption: str
    url: str = Field(description="the figure as PNG")
