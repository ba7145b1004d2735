"""Health that tells the truth, and the devices' own state."""

from __future__ import annotations

from fastapi import APIRouter, Response, status

from acquisition.daemon.api.deps import TOKEN_ERRORS, CatalogDep, EngineDep, ReadTokenDep, SettingsDep
from acquisition.daemon.engine import RunEngine
from acquisition.daemon.manual import pose_record
from acquisition.daemon.models import ArmState, CameraState, DevicesStatus, Health
from acquisition.daemon.settings import DaemonSettings
from acquisition.daemon.storage import StorageError, directory_problems, min_free_bytes
from drivers.contracts.version import __version__
from drivers.errors import DeviceError

router = APIRouter(tags=["health"])


def arm_state(engine: RunEngine) -> ArmState:
    arm = engine.devices.arm
    try:
        st = arm.status()
        pose = arm.position()
    except DeviceError as exc:
        return ArmState(connected=False, identity=arm.identity, error=str(exc))
    position = pose_record(pose)
    return ArmState(
        connected=True,
        identity=arm.identity,
        position=position,
        moving=st.moving,
        in_position=st.in_position,
        alarm_code=st.alarm_code,
        alarm_text=st.alarm_text or None,
    )


def camera_state(engine: RunEngine) -> CameraState:
    camera = engine.devices.camera
    problem = camera.problem()
    return CameraState(connected=problem is None, identity=camera.identity, error=problem)


@router.get("/health", response_model=Health, responses={503: {"model": Health, "description": "degraded"}})
def health(engine: EngineDep, catalog: CatalogDep, settings: SettingsDep, response: Response) -> Health:
    """``ok`` only when the arm answers without an alarm, the camera is there, and the data
    directory can be written with room for a position; else 503 with the reasons. Also the run
    in progress, the runs queued, and why the queue is held (a held queue is not a fault of
    the daemon: it waits for the operator)."""
    reasons = storage_problems(engine, settings)
    arm = arm_state(engine)
    if not arm.connected:
        reasons.append(f"arm: {arm.error}")
    elif arm.alarm_code:
        reasons.append(f"arm: alarm {arm.alarm_code:#06x}: {arm.alarm_text}")
    camera = camera_state(engine)
    if not camera.connected:
        reasons.append(f"camera: {camera.error}")
    active = catalog.active_run()
    if active is not None and active.id in engine.pending.held():
        active = None  # it has ended; the catalog does not know yet
    if reasons:
        response.status_code = status.HTTP_503_SERVICE_UNAVAILABLE
    hold = catalog.queue_hold()
    return Health(
        status="degraded" if reasons else "ok",
        reasons=reasons,
        version=__version__,
        active_run=active.id if active else None,
        rig=catalog.rig,
        queued_runs=len(catalog.queued_runs()),
        queue_held=hold[0] if hold else None,
    )


def storage_problems(engine: RunEngine, settings: DaemonSettings) -> list[str]:
    """The data directory's problems (read-only, not writable, too little free space), and the
    runs' ends the catalog could not record yet (recorded now if it can be written again)."""
    directories = [settings.data_dir, settings.runs_dir]
    frame_shape = (engine.rig.camera.height, engine.rig.camera.width)
    problems = directory_problems(
        directories, min_free_bytes(settings.storage.min_free_mb, frame_shape, len(settings.default_exposures_s))
    )
    try:
        engine.pending.save()
    except StorageError as exc:
        held = ", ".join(f"{run_id} {state}" for run_id, (state, _) in engine.pending.held().items())
        problems.append(f"catalog: not recorded yet ({held}): {exc}")
    return problems


@router.get(
    "/devices", response_model=DevicesStatus, tags=["devices"], dependencies=[ReadTokenDep], responses=TOKEN_ERRORS
)
def devices(engine: EngineDep) -> DevicesStatus:
    """Connection, read-back position and status of the arm; the camera's identity."""
    return DevicesStatus(arm=arm_state(engine), camera=camera_state(engine))
