"""Schedule presets a run can be started from."""

from __future__ import annotations

from fastapi import APIRouter

from acquisition.daemon.api.deps import TOKEN_ERRORS, EngineDep, ReadTokenDep, SettingsDep
from acquisition.daemon.models import RunRequest

router = APIRouter(tags=["presets"], dependencies=[ReadTokenDep], responses=TOKEN_ERRORS)


@router.get("/presets")
def presets(engine: EngineDep, settings: SettingsDep) -> dict:
    """The presets with their schedules, position counts and the default bracket."""
    out = {}
    schedules = engine.preflight.presets()
    for name in schedules:
        try:
            rig = engine.preflight.plan_schedule(RunRequest.model_validate({"preset": name}))
            out[name] = {
                "schedule": rig.schedule.model_dump(mode="json"),
                "positions": len(rig.light_poses()),
                "valid": True,
                "error": None,
            }
        except ValueError as exc:
            out[name] = {"schedule": schedules[name], "positions": None, "valid": False, "error": str(exc)}
    return {"presets": out, "default_bracket": {"mode": "fixed", "exposures_s": settings.default_exposures_s}}
