"""The arm: its emergency stop, and the technician's jog and homing outside a run."""

from __future__ import annotations

from fastapi import APIRouter, status

from acquisition.daemon import manual
from acquisition.daemon.api.deps import WRITE_ERRORS, EngineDep, Responses, TokenDep
from acquisition.daemon.models import ArmMove, JogRequest, Problem

router = APIRouter(prefix="/arm", tags=["arm"])
MOVE_ERRORS: Responses = {
    **WRITE_ERRORS,
    409: {"model": Problem, "description": "a run is active, or the devices are busy"},
    503: {"model": Problem, "description": "the arm failed (alarm, timeout, stopped short)"},
}


@router.post("/stop", status_code=status.HTTP_202_ACCEPTED, dependencies=[TokenDep], responses=WRITE_ERRORS)
def stop_arm(engine: EngineDep) -> dict:
    """Stop the arm at once, also mid-move. A run in progress is paused when this answers
    (``last_error`` says where the arm stopped) and re-takes a move cut short when resumed."""
    engine.stop_arm()
    return {"stopped": True}


@router.post(
    "/jog",
    response_model=ArmMove,
    dependencies=[TokenDep],
    responses={**MOVE_ERRORS, 422: {"model": Problem, "description": "the target is outside the soft limits"}},
)
def jog(body: JogRequest, engine: EngineDep) -> ArmMove:
    """Move one axis of the tool pose by ``step`` (mm, or degrees for rx, ry, rz) from where the
    arm is; answers once it is there. A target outside the rig's ``[arm.soft_limits]`` is refused
    (422) before anything is sent; a jog during a run is refused (409)."""
    reached, what = manual.jog(engine, body.axis, body.step)
    return ArmMove(position=manual.pose_record(reached), moved=what)


@router.post("/home", response_model=ArmMove, dependencies=[TokenDep], responses=MOVE_ERRORS)
def home(engine: EngineDep) -> ArmMove:
    """Run the controller's homing; answers once the arm is home. Refused (409) during a run."""
    reached, what = manual.home(engine)
    return ArmMove(position=manual.pose_record(reached), moved=what)
