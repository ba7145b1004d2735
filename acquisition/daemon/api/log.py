"""The daemon's recent log lines (the page's log panel)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request

from acquisition.daemon.api.deps import TOKEN_ERRORS, ReadTokenDep
from acquisition.daemon.log_buffer import LOG_LINES
from acquisition.daemon.models import LogLine

router = APIRouter(tags=["log"], dependencies=[ReadTokenDep], responses=TOKEN_ERRORS)


@router.get("/log", response_model=list[LogLine])
def recent_log(
    request: Request,
    after: Annotated[int, Query(ge=0, description="only the lines numbered above this")] = 0,
    limit: Annotated[int, Query(ge=1, le=LOG_LINES)] = 200,
) -> list[LogLine]:
    """The daemon's latest log lines (INFO and above), oldest first."""
    return [LogLine.model_validate(line) for line in request.app.state.log_buffer.lines(after, limit)]
