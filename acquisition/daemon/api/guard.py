"""The checks every request passes before routing, authentication and body parsing
(``docs/daemon.md``, "Security"): a pure ASGI middleware.

- ``Host`` must name an allowed host (setting ``allowed_hosts``), else 400: a page that
  reaches the daemon through a name of its own (DNS rebinding) names that in ``Host``.
- A request that changes something (any method but GET, HEAD and OPTIONS) needs
  ``Content-Type: application/json``, body or none, else 415: a browser sends a cross-site
  request without asking the daemon first (a "simple request", which no CORS policy stops)
  only with a form or text content type, or none.
- Its ``Origin``, when there is one, must name an allowed host, else 403.
- A body over ``max_body_bytes`` is 413: at once from ``Content-Length``, before any byte
  of it is read; a body of unannounced length (chunked) as soon as what has arrived passes
  the limit, and the rest is not read.
- The one upload, a worker's results (``PUT /jobs/{id}/results``), is a tar archive
  (``application/x-tar``, which no browser form sends) up to ``max_results_bytes``; the
  route itself needs the token.

Each refusal is a JSON problem (``{"detail": "one line"}``), like the API's other errors.
"""

from __future__ import annotations

import json
import re
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any
from urllib.parse import urlsplit

from acquisition.daemon.settings import DaemonSettings, split_host

# The ASGI interface (as ``starlette.types`` spells it).
Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

#: The methods that change nothing: no content type or origin is asked of them.
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
JSON_TYPE = "application/json"
TAR_TYPE = "application/x-tar"
#: The routes that take a body other than JSON: (method, path) -> its media type.
UPLOAD_ROUTES = ((("PUT", re.compile(r"/jobs/[^/]+/results\Z")), TAR_TYPE),)


class _BodyTooLarge(Exception):
    """Raised into the application when a streamed body passes the limit (its 413 is sent)."""


def _problem(status: int, detail: str) -> tuple[Message, Message]:
    body = json.dumps({"detail": detail}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    if status == 413:
        headers.append((b"connection", b"close"))  # the rest of the body is not read
    start = {"type": "http.response.start", "status": status, "headers": headers}
    return start, {"type": "http.response.body", "body": body}


class RequestGuard:
    """The ASGI middleware of the module's checks, for ``settings`` (its allowed hosts and
    body limit)."""

    def __init__(self, app: ASGIApp, settings: DaemonSettings) -> None:
        self.app = app
        self.hosts = settings.host_allow_list()
        self.limit = settings.max_body_bytes
        self.upload_limit = settings.max_results_bytes

    def body_rule(self, scope: Scope) -> tuple[str, int]:
        """The media type a request's body must have, and its size limit."""
        for (method, path), media in UPLOAD_ROUTES:
            if scope.get("method") == method and path.match(scope.get("path", "")):
                return media, self.upload_limit
        return JSON_TYPE, self.limit

    def allowed(self, netloc: str) -> bool:
        """Whether ``netloc`` (``NAME[:PORT]``) names an allowed host."""
        try:
            name, port = split_host(netloc)
        except ValueError:
            return False
        return any(h == "*" or (h == name and p in (None, port)) for h, p in self.hosts)

    def refusal(self, scope: Scope) -> tuple[int, str] | None:
        """The status and reason to refuse the request with, from its headers alone."""
        headers: dict[str, list[str]] = {}
        for key, value in scope["headers"]:
            headers.setdefault(key.decode("latin-1").lower(), []).append(value.decode("latin-1"))
        hosts = headers.get("host", [])
        if len(hosts) != 1:
            return 400, f"host: a request names one Host (it has {len(hosts)})"
        if not self.allowed(hosts[0]):
            return 400, (
                f"host: {hosts[0]!r} is not a host this daemon answers to (its setting allowed_hosts, MG_ALLOWED_HOSTS)"
            )
        expected, limit = self.body_rule(scope)
        lengths = headers.get("content-length", [])
        if lengths:
            if len(set(lengths)) != 1 or not lengths[0].strip().isdigit():
                return 400, f"content-length: {lengths!r} is not one length"
            if int(lengths[0]) > limit:
                return 413, f"the body ({int(lengths[0])} bytes) is larger than the limit of {limit} bytes"
        if scope["method"] in SAFE_METHODS:
            return None
        for origin in headers.get("origin", []):
            netloc = urlsplit(origin).netloc if "://" in origin else ""
            if not self.allowed(netloc):
                return 403, (
                    f"origin: {origin!r} may not change anything here (only pages of the hosts "
                    "in allowed_hosts, MG_ALLOWED_HOSTS)"
                )
        types = headers.get("content-type", [])
        media = types[0].partition(";")[0].strip().lower() if len(types) == 1 else None
        if media != expected:
            got = repr(types[0]) if len(types) == 1 else "none" if not types else f"{len(types)} Content-Type headers"
            return 415, (
                f"content-type: a request that changes something is sent as {expected}, "
                f"with or without a body (got {got})"
            )
        return None

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        refused = self.refusal(scope)
        if refused is not None:
            for message in _problem(*refused):
                await send(message)
            return
        received = 0
        started = cut = False
        limit = self.body_rule(scope)[1]

        async def counted_receive() -> Message:
            nonlocal received, cut
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    if not cut and not started:
                        detail = f"the body is larger than the limit of {limit} bytes"
                        for answer in _problem(413, detail):
                            await send(answer)
                    cut = True
                    raise _BodyTooLarge
            return message

        async def tracked_send(message: Message) -> None:
            nonlocal started
            if cut:
                return  # the 413 has been sent; the application's answer to the cut body is not
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, counted_receive, tracked_send)
        except _BodyTooLarge:
            pass  # answered (413), or, had the answer begun, cut short: the server closes the connection
