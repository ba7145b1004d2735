"""The latest frame of whatever ran last (a run or a test shot), and the test shot."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Request, Response, status

from acquisition.daemon import manual
from acquisition.daemon.api.deps import (
    TOKEN_ERRORS,
    WRITE_ERRORS,
    EngineDep,
    ReadTokenDep,
    Responses,
    SettingsDep,
    TokenDep,
)
from acquisition.daemon.models import FrameSummary, Problem, ShotRequest, ShotResult
from acquisition.daemon.preview import Previews

router = APIRouter(tags=["preview"], dependencies=[ReadTokenDep], responses=TOKEN_ERRORS)
NO_FRAME: Responses = {404: {"model": Problem, "description": "no frame has been taken yet"}}
PNG: Responses = {200: {"content": {"image/png": {}}}}


def previews(request: Request) -> Previews:
    return request.app.state.previews


def _no_frame() -> HTTPException:
    return HTTPException(status.HTTP_404_NOT_FOUND, "no frame has been taken yet")


@router.get("/preview.png", responses={**PNG, **NO_FRAME})
def latest_preview(request: Request) -> Response:
    """The latest frame taken, tone-mapped and downscaled (a quick look)."""
    made = previews(request).quick_look()
    if made is None:
        raise _no_frame()
    return Response(made[0], media_type="image/png", headers={"Cache-Control": "no-store"})


@router.get("/preview/frame.png", responses={**PNG, **NO_FRAME})
def frame_view(request: Request) -> Response:
    """The latest frame at the sensor's resolution on a log scale (1 DN above black to the
    white level), saturated photosites magenta: what the page aligns the rig with."""
    png = previews(request).view()
    if png is None:
        raise _no_frame()
    return Response(png, media_type="image/png", headers={"Cache-Control": "no-store"})


@router.get("/preview/frame", response_model=FrameSummary, responses=NO_FRAME)
def frame_summary(request: Request) -> FrameSummary:
    """What goes beside the view: the exposure, the levels, the saturated photosites, each
    channel's histogram, and the ball's expected outline from the rig."""
    summary = previews(request).summary()
    if summary is None:
        raise _no_frame()
    return FrameSummary.model_validate(summary)


@router.post(
    "/preview/shot",
    response_model=ShotResult,
    dependencies=[TokenDep],
    responses={
        409: {"model": Problem, "description": "a run is active, or the devices are busy"},
        503: {"model": Problem, "description": "the camera failed"},
        **WRITE_ERRORS,
    },
)
def test_shot(engine: EngineDep, settings: SettingsDep, body: ShotRequest | None = None) -> ShotResult:
    """One bracket at the arm's current pose (the request's exposures, or the daemon's default
    bracket), shown in the preview; nothing is stored in a run. Refused (409) while a run is
    active."""
    exposures = (body.exposures_s if body is not None else None) or list(settings.default_exposures_s)
    frames = manual.take_test_shot(engine, exposures)
    return ShotResult.model_validate({"frames": frames, "serial": engine.frame_serial})
