"""The FastAPI daemon: devices created in the lifespan, routers per resource, one error map.

``create_app(settings)`` builds the application; ``mirrorgonio serve`` runs it under uvicorn.
"""

from __future__ import annotations

import logging
import math
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI, Request, status
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse

from acquisition.daemon.api import arm, health, jobs, presets, preview, queue, runs, session
from acquisition.daemon.api import log as log_api
from acquisition.daemon.api.deps import GUARD_ERRORS
from acquisition.daemon.api.guard import RequestGuard
from acquisition.daemon.catalog import (
    ActiveRunError,
    Catalog,
    CatalogError,
    InvalidTransitionError,
    JobClaimError,
    NotQueuedError,
    OtherRigError,
    UnknownJobError,
    UnknownRunError,
)
from acquisition.daemon.client_files import ClientFileError
from acquisition.daemon.devices import open_devices
from acquisition.daemon.engine import RunConflictError, RunEngine, RunEngineError
from acquisition.daemon.log_buffer import LogBuffer
from acquisition.daemon.manual import MoveRefusedError
from acquisition.daemon.preview import Previews
from acquisition.daemon.settings import DaemonSettings
from acquisition.daemon.storage import InsufficientStorageError, StorageUnavailableError
from acquisition.daemon.transfer import DigestCache, TransferError
from drivers.contracts.rig import RigError, load_rig
from drivers.contracts.version import __version__
from drivers.errors import DeviceError

log = logging.getLogger("mirrorgonio.daemon")
WEB_DIR = Path(__file__).resolve().parent / "web"
WEB_PAGE = WEB_DIR / "index.html"
#: The loggers whose lines the page's log panel shows (``GET /log``): the daemon's and the server's.
LOGGED = ("mirrorgonio", "uvicorn.error")

# Domain errors and the HTTP status each one means (the first that matches). A storage that
# refuses a write (the catalog's or a run's) comes before the catalog's other errors.
ERROR_STATUS: list[tuple[type[Exception], int]] = [
    (InsufficientStorageError, status.HTTP_507_INSUFFICIENT_STORAGE),
    (StorageUnavailableError, status.HTTP_503_SERVICE_UNAVAILABLE),
    (UnknownRunError, status.HTTP_404_NOT_FOUND),
    (UnknownJobError, status.HTTP_404_NOT_FOUND),
    (InvalidTransitionError, status.HTTP_409_CONFLICT),
    (ActiveRunError, status.HTTP_409_CONFLICT),
    (NotQueuedError, status.HTTP_409_CONFLICT),
    (JobClaimError, status.HTTP_409_CONFLICT),
    (OtherRigError, status.HTTP_403_FORBIDDEN),
    (RunConflictError, status.HTTP_409_CONFLICT),
    (RigError, status.HTTP_422_UNPROCESSABLE_CONTENT),
    (MoveRefusedError, status.HTTP_422_UNPROCESSABLE_CONTENT),
    (ClientFileError, status.HTTP_422_UNPROCESSABLE_CONTENT),
    (TransferError, status.HTTP_422_UNPROCESSABLE_CONTENT),
    (CatalogError, status.HTTP_400_BAD_REQUEST),
    (RunEngineError, status.HTTP_400_BAD_REQUEST),
    (DeviceError, status.HTTP_503_SERVICE_UNAVAILABLE),
]


def _json_safe(value):
    """``value`` with what strict JSON cannot carry spelled out: NaN and ±Infinity (which
    Python's JSON parser accepts in a request) as text, and lone surrogates (``"\\ud800"``
    is valid JSON but not Unicode, so it cannot be encoded as UTF-8) backslash-escaped."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, str):
        return value.encode("utf-8", "backslashreplace").decode("utf-8")
    if isinstance(value, dict):
        return {_json_safe(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


def _public_detail(exc: Exception, settings: DaemonSettings) -> str:
    """What an error answer says. A file a client named: why it cannot be used only where a
    token is configured (the request then held it: only control endpoints read such files);
    without one, any local program or web page may ask, and the answer says nothing of the
    machine's filesystem."""
    if isinstance(exc, ClientFileError):
        return exc.detail if settings.token is not None and settings.token.get_secret_value() else str(exc)
    return str(exc)


def create_app(settings: DaemonSettings) -> FastAPI:
    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        log_buffer = LogBuffer()
        for name in LOGGED:
            log_buffer.attach(name)
        app.state.log_buffer = log_buffer
        rig = load_rig(settings.rig)
        Path(settings.data_dir).mkdir(parents=True, exist_ok=True)
        catalog = Catalog(settings.catalog_url, rig=settings.rig_name)
        catalog.register_daemon(settings.daemon_url())  # where workers without this disk fetch runs
        interrupted = catalog.mark_interrupted()
        if interrupted:
            log.warning("runs interrupted by the last shutdown: %s", ", ".join(interrupted))
        devices = open_devices(settings, rig)
        engine = RunEngine(settings, rig, devices, catalog)
        engine.after_restart(interrupted)  # the queued runs wait for the operator
        app.state.settings, app.state.catalog, app.state.engine = settings, catalog, engine
        app.state.digests = DigestCache()
        app.state.previews = Previews(lambda: (engine.frame_serial, engine.latest_frame, engine.latest_frame_run), rig)
        try:
            yield
        finally:
            engine.shutdown()
            devices.close()
            catalog.close()
            for name in LOGGED:
                log_buffer.detach(name)

    app = FastAPI(
        title="mirrorgonio daemon",
        version=__version__,
        description="Drives the arm and the camera of a mirror-ball goniophotometer and writes run files.",
        lifespan=lifespan,
        responses=GUARD_ERRORS,
    )
    routers = (health, presets, runs, queue, preview, arm, jobs, session, log_api)
    for module in routers:
        app.include_router(module.router)
    # Host, Origin, content type and body size, before routing, the token and the body's parsing.
    app.add_middleware(RequestGuard, settings=settings)

    async def domain_error(request: Request, exc: Exception) -> JSONResponse:
        for kind, code in ERROR_STATUS:
            if isinstance(exc, kind):
                return JSONResponse({"detail": _public_detail(exc, settings)}, status_code=code)
        raise exc  # pragma: no cover - only registered for the kinds above

    for kind, _ in ERROR_STATUS:
        app.add_exception_handler(kind, domain_error)

    async def validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        # FastAPI's own 422, but its errors echo the input, which made a 500 of a request
        # holding NaN or a lone surrogate: the answer could not be rendered.
        detail = _json_safe(jsonable_encoder(exc.errors()))
        return JSONResponse({"detail": detail}, status_code=status.HTTP_422_UNPROCESSABLE_CONTENT)

    # Starlette types a handler as taking any Exception, though it is called only with the class it is registered for.
    app.add_exception_handler(RequestValidationError, validation_error)  # type: ignore[arg-type]

    @app.get("/", response_class=HTMLResponse, include_in_schema=False)
    def web_page() -> HTMLResponse:
        return HTMLResponse(WEB_PAGE.read_text(encoding="utf-8"))

    # The page's script and style (no build step, nothing from the network).
    @app.get("/app.js", include_in_schema=False)
    def web_script() -> FileResponse:
        return FileResponse(WEB_DIR / "app.js", media_type="text/javascript", headers={"Cache-Control": "no-cache"})

    @app.get("/align.js", include_in_schema=False)
    def align_script() -> FileResponse:
        return FileResponse(WEB_DIR / "align.js", media_type="text/javascript", headers={"Cache-Control": "no-cache"})

    @app.get("/app.css", include_in_schema=False)
    def web_style() -> FileResponse:
        return FileResponse(WEB_DIR / "app.css", media_type="text/css", headers={"Cache-Control": "no-cache"})

    return app
