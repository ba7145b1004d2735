"""The arm's emergency stop."""

from __future__ import annotations

from fastapi import APIRouter, status

from acquisition.api.deps import WRITE_ERRORS, EngineDep, TokenDep

router = APIRouter(prefix="/arm", tags=["arm"])


@router.post("/stop", status_code=status.HTTP_202_ACCEPTED, dependencies=[TokenDep], responses=WRITE_ERRORS)
def stop_arm(engine: EngineDep) -> dict:
    """Stop the arm at once, also mid-move. A run in progress is paused when this answers
    (``last_error`` says where the arm stopped) and re-takes a move cut short when resumed."""
    engine.stop_arm()
    return {"stopped": True}
