"""What a run request becomes before anything moves (``acquisition.daemon.engine``): its schedule on
the rig, the files it belongs with, its calibration plan, its estimated size against the free
space, and its run file's header. Each check refuses a request with one line before a run
starts, whether it starts at once or from the queue."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

from acquisition.daemon.bracketing import auto_bracket_rule
from acquisition.daemon.client_files import load_client_file
from acquisition.daemon.devices import Devices
from acquisition.daemon.models import AutoBracket, RunRequest
from acquisition.daemon.run_plan import (
    DARK_IN_LIT_ROOM,
    RunPlan,
    calibration_sets,
    calibration_shot,
    light_model_record,
)
from acquisition.daemon.settings import DaemonSettings
from acquisition.daemon.storage import check_room, run_bytes
from drivers.contracts.rig import LightSweep, ObjectArc, ObjectDome, Raster, Rig, RigError, rig_from_dict
from drivers.contracts.runfile import RunHeader, file_sha256
from drivers.contracts.version import __version__
from drivers.pose import Pose

OBJECT_PRESETS = ("object-arc", "object-dome")  # schedules that light an object, not the ball


class RunPreflight:
    """The checks and plans of a run request on one rig's devices (no device is moved)."""

    def __init__(self, settings: DaemonSettings, rig: Rig, devices: Devices):
        self.settings = settings
        self.rig = rig
        self.devices = devices

    # --- the schedule and the files a run belongs with ------------------------------------
    def presets(self) -> dict[str, dict]:
        """Schedules a run can use: the rig's own, and the other kinds' defaults."""
        base = {"light-sweep": LightSweep(), "object-arc": ObjectArc(), "object-dome": ObjectDome(), "raster": Raster()}
        base[self.rig.schedule.kind] = self.rig.schedule
        return {name: schedule.model_dump(mode="json") for name, schedule in base.items()}

    def plan_schedule(self, request: RunRequest) -> Rig:
        """The rig with the request's schedule, validated (limits, collisions)."""
        if request.preset == "poses":
            schedule = {"kind": "poses", "poses": [p.model_dump(mode="json") for p in request.poses or []]}
        else:
            schedule = self.presets()[request.preset]
        if request.preset in OBJECT_PRESETS and self.rig.object is None:
            raise RigError(
                f"preset {request.preset}: the rig has no [object] (the mesh and pose of what is photographed)"
            )
        data = self.rig.model_dump(mode="json", exclude_none=True)
        data["schedule"] = schedule
        return rig_from_dict(data, f"preset {request.preset}")

    def references(self, rig: Rig, request: RunRequest) -> dict:
        """The files an object run belongs with (``RunHeader.references``), checked now.

        A light model that cannot be read is refused before the run starts, so an
        hour of captures is never recorded against the wrong file: a
        :class:`~acquisition.daemon.client_files.ClientFileError` (the path is the client's).
        """
        refs: dict = {}
        if rig.object is not None:
            mesh = Path(rig.object.mesh)
            if not mesh.is_file():
                raise RigError(f"object.mesh: {mesh}: no such file")
            refs["object_mesh"] = {
                "path": str(mesh.resolve()),
                "sha256": file_sha256(mesh),
                "units_m": rig.object.units_m,
                "pose": rig.object.pose.model_dump(mode="json"),
            }
        if request.light_results is not None:
            model, sha256 = load_client_file(request.light_results, "light_results", "light model", light_model_record)
            provenance = model.get("provenance")
            provenance = provenance if isinstance(provenance, dict) else {}
            refs["light_model"] = {
                "path": str(Path(request.light_results).expanduser().resolve()),
                "sha256": sha256,
                "run_id": str(provenance.get("run_id", "")),
            }
        return refs

    def poses(self, request: RunRequest) -> tuple[Rig, list[Pose], list[Pose]]:
        """The rig with the request's schedule, and the tool and light poses the run takes
        (the first ``count`` of them when the request says so)."""
        rig = self.plan_schedule(request)
        tool, light = rig.tool_poses(), rig.light_poses()
        if request.count is not None:
            tool, light = tool[: request.count], light[: request.count]
        return rig, tool, light

    def plan(self, request: RunRequest, *, with_references: bool = True) -> RunPlan:
        """What ``request``'s run takes, worked out once for the run: its schedule on the rig,
        its calibration plan, its auto-bracket rule, and (``with_references``) the files it
        belongs with, read now so that one that cannot be read refuses the run."""
        rig, tool, light = self.poses(request)
        bracket = request.bracket
        return RunPlan(
            request=request,
            rig=rig,
            tool_poses=tool,
            light_poses=light,
            calibration=self.calibration_plan(request),
            auto_bracket=auto_bracket_rule(self.settings.auto_bracket, bracket)
            if isinstance(bracket, AutoBracket)
            else None,
            references=self.references(rig, request) if with_references else None,
        )

    # --- storage -------------------------------------------------------------------------
    def check_room(self, plan: RunPlan, positions: int, extra_bytes: int = 0) -> None:
        """Refuse a run of ``plan`` (or what a resumed one has left: ``positions``, and
        ``extra_bytes`` for the salvaged copy of its file) whose estimated size does not fit in
        the free space.

        The estimate is every frame (the longest bracket at each position, and the calibration
        sets) at ``storage.compression_ratio`` of its raw size, plus the run file's records.

        Raises
        ------
        InsufficientStorageError
            It does not fit (HTTP 507; the request's ``force`` starts it anyway).
        StorageUnavailableError
            The runs' directory cannot be written (HTTP 503).
        """
        if not self.settings.storage.check_before_run:
            return
        calibration = plan.calibration
        frames = positions * plan.max_exposures
        frames += sum(len(calibration_shot(calibration, role)[1]) for role, _ in calibration_sets(calibration))
        shape = (self.rig.camera.height, self.rig.camera.width)
        needed = run_bytes(frames, shape, self.settings.storage.compression_ratio) + extra_bytes
        what = f"the run ({positions} positions, {frames} frames of {shape[1]} x {shape[0]})"
        check_room(Path(self.settings.runs_dir), needed, what)

    # --- the run file's header and its calibration plan -----------------------------------
    def header(self, run_id: str, plan: RunPlan) -> RunHeader:
        """The header of run ``run_id``'s file, created as the run starts."""
        request = plan.request
        return RunHeader(
            run_id=run_id,
            rig=plan.rig,
            tool_poses=plan.tool_poses,
            light_poses=plan.light_poses,
            max_exposures=plan.max_exposures,
            frame_shape=(plan.rig.camera.height, plan.rig.camera.width),
            bracket=request.bracket.model_dump(mode="json"),
            metadata={"operator": request.operator, "light_source": request.light_source, "notes": request.notes},
            devices={"arm": self.devices.arm.identity, "camera": self.devices.camera.identity},
            software_version=__version__,
            created_utc=datetime.now(UTC).isoformat(timespec="seconds"),
            preset=request.preset,
            references=plan.references if plan.references is not None else self.references(plan.rig, request),
            calibration=plan.calibration,
        )

    def calibration_plan(self, request: RunRequest) -> dict:
        """The calibration sets a new run takes, and how (``RunHeader.calibration``): worked
        out once per run, into its plan (:meth:`plan`)."""
        options, switch = request.calibration, self.devices.light
        plan: dict = {"switch": switch.identity, "sets": []}
        if not switch.takes_calibration:
            return {**plan, "reason": "the daemon has no light switch (light.kind = none)"}
        roles = ["ambient", "dark"] if options.dark else ["ambient"]
        for when, asked in (("before", options.before), ("after", options.after)):
            plan["sets"] += [[role, when] for role in roles] if asked else []
        if not plan["sets"]:
            return {**plan, "reason": "the run request asked for none"}
        plan["ambient_exposures_s"] = list(options.ambient_exposures_s)
        if options.dark and self.settings.light.room_can_be_dark:
            plan.update(dark="room dark", dark_exposures_s=list(options.ambient_exposures_s))
        elif options.dark:
            plan.update(dark=DARK_IN_LIT_ROOM, dark_exposures_s=[self.settings.light.dark_exposure_s])
        return plan
