"""Dependencies shared by the routers: the engine, the catalog, and the bearer token (and the
web page's session cookie, for reads)."""

from __future__ import annotations

import hashlib
import hmac
from typing import Annotated, Any

from fastapi import Depends, HTTPException, Query, Request, status
from fastapi.security import APIKeyCookie, HTTPAuthorizationCredentials, HTTPBearer

from acquisition.daemon.catalog import Catalog
from acquisition.daemon.engine import RunEngine
from acquisition.daemon.models import Problem
from acquisition.daemon.settings import DaemonSettings


def get_engine(request: Request) -> RunEngine:
    return request.app.state.engine


def get_catalog(request: Request) -> Catalog:
    return request.app.state.catalog


def get_settings(request: Request) -> DaemonSettings:
    return request.app.state.settings


#: Which rig's runs or jobs a listing shows: this daemon's (absent), another's (its name), the lab's (``all``).
RigQuery = Annotated[
    str | None,
    Query(max_length=63, description="a rig's name, or 'all' for every rig sharing the catalog; default this rig"),
]


def catalog_rig(rig: str | None) -> str | None:
    """The catalog's ``rig=`` of a listing's ``rig`` query: ``""`` this rig, None the whole lab."""
    if rig is None:
        return ""
    return None if rig == "all" else rig


EngineDep = Annotated[RunEngine, Depends(get_engine)]
CatalogDep = Annotated[Catalog, Depends(get_catalog)]
SettingsDep = Annotated[DaemonSettings, Depends(get_settings)]

_bearer = HTTPBearer(auto_error=False, description="The daemon's API token (configuration `token` or MG_TOKEN).")
#: The web page's session cookie (``POST /session``): what the browser's own requests carry.
SESSION_COOKIE = "mirrorgonio_session"
_session = APIKeyCookie(
    name=SESSION_COOKIE,
    auto_error=False,
    description="The web page's session (POST /session): reads only; a change needs the bearer token.",
)
BearerDep = Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]


def session_value(token: str) -> str:
    """The session cookie of ``token``: a digest of it (the cookie does not hold the token)."""
    return hmac.new(token.encode(), b"mirrorgonio web session", hashlib.sha256).hexdigest()


def configured_token(settings: DaemonSettings) -> str:
    return settings.token.get_secret_value() if settings.token else ""


def _check_bearer(expected: str, credentials: HTTPAuthorizationCredentials | None) -> None:
    if credentials is None or credentials.scheme.lower() != "bearer":
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED, "a bearer token is required", headers={"WWW-Authenticate": "Bearer"}
        )
    if not hmac.compare_digest(credentials.credentials.encode(), expected.encode()):
        raise HTTPException(status.HTTP_403_FORBIDDEN, "the token is not valid for this daemon")


def require_token(settings: SettingsDep, credentials: BearerDep) -> None:
    """Guard for every endpoint that changes anything: 401 without a token, 403 with a wrong one."""
    expected = configured_token(settings)
    if expected:  # no token configured: serve only listens on loopback then
        _check_bearer(expected, credentials)


def require_read_token(
    settings: SettingsDep, credentials: BearerDep, session: Annotated[str | None, Depends(_session)]
) -> None:
    """Guard for the endpoints that read (all but ``/health`` and the page's shell) while
    ``token_guards_reads`` is on: the bearer token, or the page's session cookie."""
    expected = configured_token(settings)
    if not expected or not settings.token_guards_reads:
        return
    if credentials is None and session and hmac.compare_digest(session.encode(), session_value(expected).encode()):
        return
    _check_bearer(expected, credentials)


TokenDep = Depends(require_token)
ReadTokenDep = Depends(require_read_token)
#: An endpoint's OpenAPI ``responses``: the extra answers it documents, by status code.
Responses = dict[int | str, dict[str, Any]]
#: The answers ``require_token`` adds to an endpoint it guards (for its OpenAPI ``responses``).
TOKEN_ERRORS: Responses = {
    401: {"model": Problem, "description": "no bearer token (a token is configured)"},
    403: {"model": Problem, "description": "the token is not valid for this daemon"},
}
#: The answers of an endpoint that changes something: the token's, and the request guard's
#: (``acquisition.daemon.api.guard``).
WRITE_ERRORS: Responses = {
    **TOKEN_ERRORS,
    403: {"model": Problem, "description": "the token is not valid for this daemon, or the Origin is not allowed"},
    415: {"model": Problem, "description": "not sent as application/json"},
}
#: The request guard's answers to any request.
GUARD_ERRORS: Responses = {
    400: {"model": Problem, "description": "the Host is not allowed, or the request cannot be read"},
    413: {"model": Problem, "description": "the body is larger than the limit (max_body_bytes)"},
}
