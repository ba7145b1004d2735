"""Dependencies shared by the routers: the engine, the catalog, and the bearer token."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, HTTPException, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from acquisition.catalog import Catalog
from acquisition.models import Problem
from acquisition.runner import RunEngine
from acquisition.settings import DaemonSettings


def get_engine(request: Request) -> RunEngine:
    return request.app.state.engine


def get_catalog(request: Request) -> Catalog:
    return request.app.state.catalog


def get_settings(request: Request) -> DaemonSettings:
    return request.app.state.settings


EngineDep = Annotated[RunEngine, Depends(get_engine)]
CatalogDep = Annotated[Catalog, Depends(get_catalog)]
SettingsDep = Annotated[DaemonSettings, Depends(get_settings)]

_bearer = HTTPBearer(auto_error=False, description="The daemon's API token (configuration `token` or MG_TOKEN).")


def require_token(
    settings: SettingsDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> None:
    """Guard for every endpoint that changes anything: 401 without a token, 403 with a wrong one."""
    expected = settings.token.get_secret_value() if settings.token else ""
    if not expected:
        return  # no token configured: serve only listens on loopback then
    if credentials is None or credentials.scheme.lower() != "bearer":
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED, "a bearer token is required", headers={"WWW-Authenticate": "Bearer"}
        )
    if not hmac.compare_digest(credentials.credentials.encode(), expected.encode()):
        raise HTTPException(status.HTTP_403_FORBIDDEN, "the token is not valid for this daemon")


TokenDep = Depends(require_token)
#: The answers ``require_token`` adds to an endpoint it guards (for its OpenAPI ``responses``).
TOKEN_ERRORS = {
    401: {"model": Problem, "description": "no bearer token (a token is configured)"},
    403: {"model": Problem, "description": "the token is not valid for this daemon"},
}
