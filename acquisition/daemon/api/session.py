"""The web page's session: a cookie that lets the browser's own requests read.

The page sends its requests with the bearer token, but the browser fetches some things by
itself: the event stream, the preview image, the file downloads, the report opened in a
tab. While tokens guard reads (``token_guards_reads``), these carry the session cookie
instead: ``HttpOnly`` (no script reads it), ``SameSite=Strict`` (no other site's page
sends it), a digest of the token rather than the token. It opens reads only: a request
that changes something needs the bearer token itself, so the cookie cannot be used for a
cross-site request forgery.
"""

from __future__ import annotations

from fastapi import APIRouter, Request, Response, status

from acquisition.daemon.api.deps import (
    SESSION_COOKIE,
    WRITE_ERRORS,
    SettingsDep,
    TokenDep,
    configured_token,
    session_value,
)
from acquisition.daemon.models import Problem

router = APIRouter(prefix="/session", tags=["session"])


@router.post("", status_code=status.HTTP_204_NO_CONTENT, dependencies=[TokenDep], responses=WRITE_ERRORS)
def open_session(request: Request, settings: SettingsDep) -> Response:
    """Set the session cookie for the bearer token sent (nothing to set without a configured
    token). The browser's requests to this daemon then read with it."""
    response = Response(status_code=status.HTTP_204_NO_CONTENT)
    token = configured_token(settings)
    if token:
        response.set_cookie(
            SESSION_COOKIE,
            session_value(token),
            httponly=True,
            samesite="strict",
            secure=request.url.scheme == "https",
            path="/",
        )
    return response


@router.delete(
    "",
    status_code=status.HTTP_204_NO_CONTENT,
    responses={403: {"model": Problem, "description": "the Origin is not allowed"}, 415: WRITE_ERRORS[415]},
)
def close_session() -> Response:
    """Remove the session cookie."""
    response = Response(status_code=status.HTTP_204_NO_CONTENT)
    response.delete_cookie(SESSION_COOKIE, path="/", httponly=True, samesite="strict")
    return response
