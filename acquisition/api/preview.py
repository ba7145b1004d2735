"""The latest frame of whatever ran last."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Response, status

from acquisition.api.deps import TOKEN_ERRORS, EngineDep, ReadTokenDep
from acquisition.models import Problem

router = APIRouter(tags=["runs"], dependencies=[ReadTokenDep], responses=TOKEN_ERRORS)


@router.get("/preview.png", responses={200: {"content": {"image/png": {}}}, 404: {"model": Problem}})
def latest_preview(engine: EngineDep) -> Response:
    """The latest frame taken, tone-mapped and downscaled."""
    png = engine.preview()
    if png is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, "no frame has been taken yet")
    return Response(png, media_type="image/png", headers={"Cache-Control": "no-store"})
